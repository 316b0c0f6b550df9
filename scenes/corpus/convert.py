"""Convert the corpus's third-party tetrahedral meshes to ``scenes/corpus/meshes/<name>.vtu``.

Each mesh is read from one file of one public git repository at a pinned commit
(:data:`SOURCES`; ``SOURCES.md`` beside this file gives the licence of each).
Nothing about a mesh is changed but its container: the linear tets are kept as
they are, vertices no tet uses are dropped (none of the current sources has
any), tets that some tools store with the opposite orientation are turned
positive by swapping two of their vertices (counted and printed), and the
coordinates stay in the source's own units (each scene sets ``mesh.scale``).
Every written file is read back with :func:`forcecal.mesh.read_mesh`, which
applies forcecal's mesh checks.

Usage (each repository cloned, any depth that holds the commit, into
``REPOS/<owner>+<name>``, or a directory holding its git directory as ``repo``)::

    python scenes/corpus/convert.py --repos REPOS [--only NAME ...]

It prints one line per mesh: vertices, tets, edge lengths, SHA-256 of the file.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

OUT = Path(__file__).with_name("meshes")


@dataclass(frozen=True)
class Source:
    """One corpus mesh: where it comes from and how its file is read.

    Attributes:
        name: corpus name (``meshes/<name>.vtu``, ``<name>.toml``).
        repo: ``owner/name`` of the public GitHub repository.
        commit: the commit the file is read at (40 hex digits).
        path: the file in that repository (a TetGen pair: the ``.node`` file).
        reader: ``"meshio"`` (gmsh .msh), ``"tetgen"`` (.node + .ele) or ``"dolfin_h5"``
            (a legacy-dolfin HDF5 mesh: ``<group>/coordinates``, ``<group>/topology``).
        licence: SPDX identifier of the licence it is distributed under.
        group: the HDF5 group of a ``dolfin_h5`` mesh.
    """
    name: str
    repo: str
    commit: str
    path: str
    reader: str
    licence: str
    group: str = ""


SOURCES = (
    Source("torus", "ipc-sim/IPC", "573d2c7e04104d3f9baf526bdaee7745891a571a",
           "input/tetMeshes/torus.msh", "meshio", "MIT"),
    Source("soft_bar", "ipc-sim/IPC", "573d2c7e04104d3f9baf526bdaee7745891a571a",
           "input/tetMeshes/bar-651.msh", "meshio", "MIT"),
    Source("left_ventricle", "termi-official/Thunderbolt.jl",
           "9787e76a005f3c71e4c8da5789186b8afcaec1a6",
           "data/meshes/LV/EllipsoidalLeftVentricle.msh", "meshio", "MIT"),
    Source("biventricle", "ComputationalPhysiology/pulse",
           "5731c82e01903e3d8ac4f0ed172012d9845a4a73",
           "pulse/example_meshes/biv_ellipsoid.h5", "dolfin_h5", "LGPL-3.0",
           group="geometry/mesh"),
    Source("lv_benchmark", "ComputationalPhysiology/pulse",
           "5731c82e01903e3d8ac4f0ed172012d9845a4a73",
           "pulse/example_meshes/benchmark.h5", "dolfin_h5", "LGPL-3.0",
           group="geometry/mesh"),
    Source("armadillo", "InteractiveComputerGraphics/PositionBasedDynamics",
           "d0894bdb0190c5f273c0500ecad0e8c2bf21fc5f",
           "data/models/armadillo_4k.node", "tetgen", "MIT"),
)


def git_dir(repos: Path, repo: str) -> Path:
    """The git directory of ``repo`` (``owner/name``) under ``repos``."""
    base = repos / repo.replace("/", "+")
    for candidate in (base / "repo", base / ".git", base):
        if (candidate / "HEAD").is_file() and (candidate / "objects").is_dir():
            return candidate
    raise SystemExit(f"error: no git repository of {repo} at {base} (clone "
                     f"https://github.com/{repo} there)")


def git_show(gdir: Path, commit: str, path: str) -> bytes:
    """The bytes of ``path`` at ``commit``."""
    done = subprocess.run(["git", "--git-dir", str(gdir), "show", f"{commit}:{path}"],
                          capture_output=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"error: {gdir}: cannot read {path} at {commit}: "
                         f"{done.stderr.decode(errors='replace').strip()}")
    return done.stdout


def read_source(source: Source, gdir: Path, scratch: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3), tets (T, 4)) of one source file, as the file stores them."""
    data = git_show(gdir, source.commit, source.path)
    if source.reader == "meshio":
        import meshio
        file = scratch / Path(source.path).name
        file.write_bytes(data)
        m = meshio.read(file)
        tets = np.concatenate([c.data for c in m.cells if c.type == "tetra"])
        return np.asarray(m.points, dtype=np.float64), tets.astype(np.int64)
    if source.reader == "tetgen":  # .node: "id x y z", .ele: "id a b c d", one header line each
        ele = git_show(gdir, source.commit, source.path[:-len(".node")] + ".ele")
        nodes = np.loadtxt(io.BytesIO(data), skiprows=1, comments="#")
        elems = np.loadtxt(io.BytesIO(ele), skiprows=1, comments="#", dtype=np.int64)
        first = int(nodes[0, 0])  # TetGen numbers from 0 or 1; the ids must be consecutive
        if not np.array_equal(nodes[:, 0], np.arange(first, first + len(nodes))):
            raise SystemExit(f"error: {source.path}: node ids are not consecutive")
        return nodes[:, 1:4], elems[:, 1:5] - first
    if source.reader == "dolfin_h5":
        import h5py
        with h5py.File(io.BytesIO(data), "r") as h5:
            return (np.asarray(h5[f"{source.group}/coordinates"], dtype=np.float64),
                    np.asarray(h5[f"{source.group}/topology"], dtype=np.int64))
    raise ValueError(f"unknown reader {source.reader!r}")


def tidy(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop unused vertices and turn negatively oriented tets positive.

    Returns (points, tets, number of tets reoriented)."""
    used = np.unique(tets)
    points, tets = points[used], np.searchsorted(used, tets)
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    negative = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) < 0
    tets[negative] = tets[negative][:, [0, 2, 1, 3]]
    return points, tets, int(negative.sum())


def convert(source: Source, repos: Path, scratch: Path) -> str:
    """Write ``meshes/<name>.vtu`` from ``source``; return its summary line."""
    import meshio

    from forcecal.mesh import read_mesh

    points, tets = read_source(source, git_dir(repos, source.repo), scratch)
    n_points = len(points)
    points, tets, flipped = tidy(points, tets)
    out = OUT / f"{source.name}.vtu"
    OUT.mkdir(exist_ok=True)
    meshio.write(out, meshio.Mesh(points, [("tetra", tets)]), compression="zlib")
    mesh = read_mesh(out)  # forcecal's checks of a user's mesh
    edges = mesh.edge_lengths
    digest = hashlib.sha256(out.read_bytes()).hexdigest()
    return (f"{source.name}: {mesh.n_vertices} vertices ({n_points - len(points)} unused "
            f"dropped), {mesh.n_tets} tets ({flipped} reoriented), {len(edges)} edges "
            f"{edges.min():.4g}-{edges.mean():.4g}-{edges.max():.4g} (min-mean-max, source "
            f"units), {out.stat().st_size} bytes, sha256 {digest}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repos", type=Path, required=True,
                        help="folder holding each source repository as <owner>+<name>")
    parser.add_argument("--only", nargs="*", help="convert only these corpus names")
    args = parser.parse_args(argv)
    import tempfile
    wanted = [s for s in SOURCES if not args.only or s.name in args.only]
    with tempfile.TemporaryDirectory() as scratch:
        for source in wanted:
            print(convert(source, args.repos, Path(scratch)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
