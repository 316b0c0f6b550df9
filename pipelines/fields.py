"""XDMF time series of the gravity test for ParaView: gravity_fe.xdmf, gravity_particle.xdmf.

Both files hold the same tetrahedral mesh (vertex coordinates [m]) and, at
every sample time [s] of the dynamic run, two vertex fields:
``displacement`` (N, 3) [m] (the dynamic run at that time) and
``static_displacement`` (N, 3) [m] (the static sag, repeated so that any step
can be warped by either). Open both in ParaView and apply *Warp By Vector* to
compare them side by side. meshio writes the heavy data to a companion
``<name>.h5`` next to each ``.xdmf``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from forcecal.errors import DataFileError
from forcecal.mesh import TetMesh


@contextlib.contextmanager
def _working_directory(path: Path) -> Iterator[None]:
    # meshio 5.0's TimeSeriesWriter creates its .h5 relative to the current directory
    # (not next to the .xdmf), so the writer runs with the output folder as cwd
    previous = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(previous)


def write_time_series(path: str | Path, mesh: TetMesh, times: np.ndarray,
                      displacement: np.ndarray, static_displacement: np.ndarray) -> list[Path]:
    """Write ``path`` (.xdmf) and its ``.h5`` atomically; returns both paths.

    Args:
        times: (S,) sample times [s].
        displacement: (S, N, 3) vertex displacements [m].
        static_displacement: (N, 3) static sag [m].
    """
    import meshio

    path = Path(path)
    n = mesh.n_vertices
    if displacement.shape != (len(times), n, 3) or static_displacement.shape != (n, 3):
        raise DataFileError(f"{path.name}: displacement shapes {displacement.shape} and "
                            f"{static_displacement.shape} do not fit {len(times)} times x {n} "
                            "vertices")
    path.parent.mkdir(parents=True, exist_ok=True)
    heavy = path.with_suffix(".h5")
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=f".{path.stem}-") as tmp:
        with _working_directory(Path(tmp)), meshio.xdmf.TimeSeriesWriter(path.name) as writer:
            writer.write_points_cells(mesh.vertices, [("tetra", mesh.tets)])
            for t, u in zip(times, displacement):
                writer.write_data(float(t), point_data={
                    "displacement": u, "static_displacement": static_displacement})
        # the .h5 first: the .xdmf that points to it appears last
        shutil.move(os.path.join(tmp, heavy.name), heavy)
        shutil.move(os.path.join(tmp, path.name), path)
    return [path, heavy]
