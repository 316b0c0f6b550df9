"""Tetrahedral meshes: the one geometry both the FE reference and the particle model use.

A :class:`TetMesh` is two arrays (vertices, tets) plus derived quantities that
are pure functions of them (edges, volumes, surface, normals). Meshes come
from :func:`forcecal.liver_mesh.generate_liver` (deterministic gmsh model of a
liver-like organ), :func:`read_mesh` (any tetrahedral mesh meshio reads, and Gmsh's
legacy format) or :func:`box_mesh` (structured boxes for tests), and always pass
:func:`check_mesh` before use. Which vertices are held and which are indented is chosen in
:mod:`forcecal.point_selection`.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from forcecal.errors import MeshError

log = logging.getLogger(__name__)

# the 6 edges of a tet as local vertex pairs
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# the 4 faces of a tet, each ordered so its normal points out of a positive tet
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


@dataclass(frozen=True, eq=False)
class TetMesh:
    """Linear tetrahedral mesh.

    Attributes:
        vertices: (N, 3) float64, vertex coordinates [m].
        tets: (T, 4) int64, vertex ids of each tet, positively oriented
            (``det[x1-x0, x2-x0, x3-x0] > 0``).
    """
    vertices: np.ndarray
    tets: np.ndarray

    def __post_init__(self) -> None:
        try:
            v = np.array(self.vertices, dtype=np.float64, order="C")  # own copy: frozen below
        except (TypeError, ValueError) as exc:
            raise MeshError(f"bad mesh: vertices must be an (N, 3) array of numbers: {exc}"
                            ) from None
        t = np.array(vertex_ids(self.tets, "tets"), order="C")
        v.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "tets", t)

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[0]

    @property
    def n_tets(self) -> int:
        return self.tets.shape[0]

    @cached_property
    def signed_volumes(self) -> np.ndarray:
        """(T,) float64, signed tet volumes [m^3] (positive for a valid mesh)."""
        x = self.vertices[self.tets]
        return np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                         x[:, 3] - x[:, 0]) / 6.0

    @cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) int64, unique edges (i < j), sorted lexicographically: one connector each."""
        e = np.sort(self.tets[:, TET_EDGES].reshape(-1, 2), axis=1)
        out = np.unique(e, axis=0)
        out.setflags(write=False)
        return out

    @cached_property
    def edge_lengths(self) -> np.ndarray:
        """(E,) float64, rest lengths of the edges [m]."""
        d = self.vertices[self.edges[:, 1]] - self.vertices[self.edges[:, 0]]
        return np.linalg.norm(d, axis=1)

    @cached_property
    def edge_tet_volume(self) -> np.ndarray:
        """(E,) float64, summed volume of the tets sharing each edge [m^3]."""
        e = np.sort(self.tets[:, TET_EDGES].reshape(-1, 2), axis=1)
        idx = self.edge_index(e[:, 0], e[:, 1])
        return np.bincount(idx, weights=np.repeat(np.abs(self.signed_volumes), 6),
                           minlength=len(self.edges))

    def edge_index(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Index into :attr:`edges` of the edges (i, j) (any order); MeshError if absent."""
        i = np.asarray(i, dtype=np.int64)
        j = np.asarray(j, dtype=np.int64)
        a, b = np.minimum(i, j), np.maximum(i, j)
        keys = self.edges[:, 0] * self.n_vertices + self.edges[:, 1]
        q = a * self.n_vertices + b
        pos = np.searchsorted(keys, q)
        pos = np.minimum(pos, len(keys) - 1)
        if not np.all(keys[pos] == q):
            raise MeshError("edge_index: some vertex pairs are not mesh edges")
        return pos

    @cached_property
    def surface_faces(self) -> np.ndarray:
        """(S, 3) int64, boundary triangles, ordered so their normals point outwards."""
        return boundary_faces(self.tets)

    @cached_property
    def surface_vertices(self) -> np.ndarray:
        """(Ns,) int64, sorted ids of the vertices on the boundary."""
        return np.unique(self.surface_faces)

    @cached_property
    def vertex_normals(self) -> np.ndarray:
        """(N, 3) float64, area-weighted *outward* unit normals (zero for interior vertices)."""
        return area_weighted_normals(self.vertices, self.surface_faces)

    def inward_normals(self, nodes: np.ndarray) -> np.ndarray:
        """(P, 3) float64, inward unit normals of surface vertices ``nodes``."""
        nodes = np.asarray(nodes, dtype=np.int64)
        not_surface = np.setdiff1d(nodes, self.surface_vertices)
        if len(not_surface):
            raise MeshError(f"vertices {not_surface.tolist()} are not on the surface; "
                            "test points must be surface vertices")
        return -self.vertex_normals[nodes]

    @cached_property
    def adjacency(self) -> sp.csr_matrix:
        """(N, N) symmetric vertex adjacency of the edge graph (CSR, bool)."""
        e = self.edges
        n = self.n_vertices
        a = sp.coo_matrix((np.ones(len(e), dtype=bool), (e[:, 0], e[:, 1])), shape=(n, n))
        return (a + a.T).tocsr()

    def lumped_masses(self, density: float) -> np.ndarray:
        """(N,) float64, lumped vertex masses [kg]: each tet's mass split equally to its 4
        vertices."""
        return np.bincount(self.tets.ravel(), weights=np.repeat(np.abs(self.signed_volumes)
                                                                * density / 4.0, 4),
                           minlength=self.n_vertices)

    def fingerprint(self) -> str:
        """SHA-256 of the vertex and tet arrays (exact bytes)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.vertices, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.tets, dtype="<i8").tobytes())
        return h.hexdigest()

    def summary(self) -> str:
        return f"{self.n_vertices} vertices, {self.n_tets} tets, {len(self.edges)} edges"


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """(S, 3) int64, read-only: the faces of the positively oriented ``tets`` (T, 4) that belong
    to one tet only (the boundary), in the tet's own vertex order, so their normals point out."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                               return_counts=True)
    out = faces[counts[inv.ravel()] == 1]
    out.setflags(write=False)
    return out


def area_weighted_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit normals at the ``vertices`` (N, 3) [m]: the area-weighted mean of the
    normals of the triangles ``faces`` (S, 3) that touch each one (zero where none does)."""
    x = vertices[faces]
    fn = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])  # length = 2 x area
    n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    norm = np.linalg.norm(n, axis=1)
    nz = norm > 0
    n[nz] /= norm[nz, None]
    return n


def vertex_ids(ids, what: str) -> np.ndarray:
    """``ids`` as an int64 array, if they are integers (an integer array, or floats with
    integral values); else :class:`MeshError` naming ``what`` and the first offending value
    (``np.asarray(ids, dtype=np.int64)`` would truncate 1.7 to 1 without a word)."""
    try:
        arr = np.asarray(ids)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{what}: vertex ids must be integers: {exc}") from None
    if arr.dtype == bool or not (np.issubdtype(arr.dtype, np.integer)
                                 or np.issubdtype(arr.dtype, np.floating)):
        raise MeshError(f"{what}: vertex ids must be integers, got an array of {arr.dtype}")
    if np.issubdtype(arr.dtype, np.floating):
        with np.errstate(invalid="ignore"):
            bad = np.nonzero(~(np.isfinite(arr) & (arr == np.round(arr))).ravel())[0]
        if len(bad):
            where = tuple(int(i) for i in np.unravel_index(bad[0], arr.shape))
            raise MeshError(f"{what}: vertex ids must be integers, got {arr.ravel()[bad[0]]!r} "
                            f"at index {where[0] if len(where) == 1 else where} "
                            f"({len(bad)} non-integer value(s))")
    return arr.astype(np.int64)


def check_mesh_arrays(mesh: TetMesh) -> TetMesh:
    """The structural part of :func:`check_mesh`, what anything computed from a mesh needs:
    vertices an (N, 3) array with N > 0 and finite coordinates, tets a (T, 4) array with
    T > 0 and vertex ids in 0..N-1 (integers: :class:`TetMesh` refuses others). Raises
    :class:`MeshError` naming the problem; what a bare mesh given to the particle model
    (:func:`particle.model.build_model`) must pass."""
    v, t = mesh.vertices, mesh.tets
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"bad mesh: vertices must be an (N, 3) array, got shape {v.shape}")
    if t.size == 0:
        raise MeshError(f"bad mesh: no tetrahedra (tets array has shape {t.shape})")
    if t.ndim != 2 or t.shape[1] != 4:
        raise MeshError(f"bad mesh: tets must be a (T, 4) array of vertex ids (linear "
                        f"tetrahedra), got shape {t.shape}")
    if not np.all(np.isfinite(v)):
        bad = np.unique(np.nonzero(~np.isfinite(v))[0])
        raise MeshError(f"bad mesh: non-finite coordinates at vertices {bad[:10].tolist()}")
    if t.min() < 0 or t.max() >= len(v):
        bad = np.nonzero(np.any((t < 0) | (t >= len(v)), axis=1))[0]
        raise MeshError(f"bad mesh: tet vertex ids must lie in [0, {len(v) - 1}], "
                        f"got range [{t.min()}, {t.max()}] (e.g. tet {int(bad[0])}: "
                        f"{t[bad[0]].tolist()})")
    return mesh


def check_mesh(mesh: TetMesh) -> TetMesh:
    """Validate a mesh; raise :class:`MeshError` naming the first problem found.

    Checks: at least one tet, finite coordinates, ids in range
    (:func:`check_mesh_arrays`), no repeated vertex inside a tet, no inverted or
    zero-volume tets, no duplicate vertices, no unused vertices, one connected
    component.
    """
    check_mesh_arrays(mesh)
    v, t = mesh.vertices, mesh.tets
    s = np.sort(t, axis=1)
    rep = np.nonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))[0]
    if len(rep):
        raise MeshError(f"bad mesh: tets {rep[:10].tolist()} repeat a vertex")
    with np.errstate(over="ignore", invalid="ignore"):
        vol = mesh.signed_volumes
        scale = np.ptp(v, axis=0).max()
    if not (np.all(np.isfinite(vol)) and np.isfinite(scale)):
        bad = np.nonzero(~np.isfinite(vol))[0]
        raise MeshError(f"bad mesh: coordinates so large (up to {np.abs(v).max():.3g}) that "
                        f"tet volumes overflow, e.g. tets {bad[:10].tolist()}; check the mesh's "
                        "units (mesh.scale)")
    # a tet whose volume is below 1e-9 of a cube of the mesh's mean edge is degenerate
    mean_edge = float(np.mean(mesh.edge_lengths))
    tiny = 1e-9 * mean_edge ** 3
    zero = np.nonzero(np.abs(vol) <= tiny)[0]
    if len(zero):
        raise MeshError(f"bad mesh: {len(zero)} zero-volume (degenerate) tets, e.g. "
                        f"{zero[:10].tolist()}")
    inverted = np.nonzero(vol < 0)[0]
    if len(inverted):
        raise MeshError(f"bad mesh: {len(inverted)} inverted tets (negative volume), e.g. "
                        f"{inverted[:10].tolist()}")
    used = np.zeros(len(v), dtype=bool)
    used[t.ravel()] = True
    if not used.all():
        unused = np.nonzero(~used)[0]
        raise MeshError(f"bad mesh: {len(unused)} vertices belong to no tet, e.g. "
                        f"{unused[:10].tolist()}")
    # vertices closer than 1e-9 of the mesh size are the same point (exact or round-off copies)
    from scipy.spatial import cKDTree
    pairs = cKDTree(v).query_pairs(1e-9 * scale, output_type="ndarray")
    if len(pairs):
        a, b = min((int(i), int(j)) for i, j in pairs)  # i < j; the lowest pair, deterministically
        raise MeshError(f"bad mesh: duplicate vertices {a} and {b} at {v[a].tolist()}")
    ncomp, labels = connected_components(mesh.adjacency, directed=False)
    if ncomp != 1:
        sizes = np.bincount(labels)
        raise MeshError(f"bad mesh: {ncomp} disconnected parts (vertex counts "
                        f"{sorted(sizes.tolist(), reverse=True)[:10]}); one solid is expected")
    return mesh


def orient_tets(vertices: np.ndarray, tets: np.ndarray, origin: str) -> np.ndarray:
    """Return tets positively oriented when a file uses the opposite convention throughout."""
    m = TetMesh(vertices, tets)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite: check_mesh refuses it
        vol = m.signed_volumes
    if len(vol) and np.all(vol < 0):
        log.info("%s: every tet is negatively oriented; swapping two vertices of each", origin)
        return tets[:, [0, 2, 1, 3]]
    return tets


# Gmsh's legacy format 1 element types (by number): the name meshio gives them, their nodes
GMSH1_TYPES = {1: ("line", 2), 2: ("triangle", 3), 3: ("quad", 4), 4: ("tetra", 4),
               5: ("hexahedron", 8), 6: ("wedge", 6), 7: ("pyramid", 5), 8: ("line3", 3),
               9: ("triangle6", 6), 11: ("tetra10", 10), 15: ("vertex", 1)}


def is_gmsh1(path: Path) -> bool:
    """Whether ``path`` is in Gmsh's legacy format 1 (``$NOD`` ... ``$ELM``), which meshio
    does not read (SOFA's ``share/mesh/*.msh`` are)."""
    with open(path, "rb") as f:
        return f.read(64).lstrip().startswith(b"$NOD")


def read_gmsh1(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Points (N, 3) and cells by kind (each (n, k) of point rows) of a Gmsh format 1 file.

    A node line is ``id x y z``, an element line ``id type physical elementary n node-ids``;
    node ids are labels (any order, gaps allowed), mapped to rows in the order the nodes are
    listed. A missing section, a count that does not match its lines, a short or non-numeric
    line, a repeated node id or an element naming an unknown node is a :class:`MeshError`
    naming the line.
    """
    lines = path.read_text(errors="replace").splitlines()

    def section(name: str) -> tuple[int, list[str]]:
        """(line number of the first entry, the entries) of ``$name`` .. ``$ENDname``."""
        try:
            start = next(i for i, line in enumerate(lines) if line.strip() == f"${name}")
            end = next(i for i in range(start + 1, len(lines))
                       if lines[i].strip() == f"$END{name}")
        except StopIteration:
            raise MeshError(f"{path}: Gmsh format 1 file without a complete ${name} ... "
                            f"$END{name} section") from None
        body = lines[start + 1:end]
        try:
            count = int(body[0])
        except (IndexError, ValueError):
            raise MeshError(f"{path}:{start + 2}: expected the number of entries of ${name}, "
                            f"got {body[0] if body else 'nothing'!r}") from None
        if count != len(body) - 1:
            raise MeshError(f"{path}: ${name} says {count} entries but lists {len(body) - 1}")
        return start + 3, body[1:]

    def numbers(line: str, number: int, kind: type) -> list:
        try:
            return [kind(word) for word in line.split()]
        except ValueError:
            raise MeshError(f"{path}:{number}: not a line of numbers: {line.strip()!r}") from None

    first, node_lines = section("NOD")
    row_of: dict[int, int] = {}
    points = np.empty((len(node_lines), 3))
    for k, line in enumerate(node_lines):
        values = numbers(line, first + k, float)
        if len(values) != 4 or not values[0].is_integer():
            raise MeshError(f"{path}:{first + k}: a node line is 'id x y z', got "
                            f"{line.strip()!r}")
        label = int(values[0])
        if label in row_of:
            raise MeshError(f"{path}:{first + k}: node {label} listed twice")
        row_of[label] = k
        points[k] = values[1:]
    first, element_lines = section("ELM")
    cells: dict[str, list[list[int]]] = {}
    for k, line in enumerate(element_lines):
        values = numbers(line, first + k, int)
        if len(values) < 5 or len(values) != 5 + values[4]:
            raise MeshError(f"{path}:{first + k}: an element line is 'id type physical "
                            f"elementary n' and n node ids, got {line.strip()!r}")
        kind, nodes = GMSH1_TYPES.get(values[1], (f"type {values[1]}", values[4]))
        if values[4] != nodes:
            raise MeshError(f"{path}:{first + k}: element {values[0]} is a {kind} with "
                            f"{values[4]} nodes; a {kind} has {nodes}")
        try:
            rows = [row_of[label] for label in values[5:]]
        except KeyError as exc:
            raise MeshError(f"{path}:{first + k}: element {values[0]} names node {exc.args[0]}, "
                            "which $NOD does not list") from None
        cells.setdefault(kind, []).append(rows)
    return points, {kind: np.array(rows, dtype=np.int64) for kind, rows in cells.items()}


def read_mesh(path: str | Path, scale: float = 1.0) -> TetMesh:
    """Read a tetrahedral mesh with meshio (.msh, .vtu, .vtk, .xdmf, ...) and check it.

    Gmsh's legacy format 1, which meshio does not read, is read by :func:`read_gmsh1`.
    Only ``tetra`` cells are used (surface/line cells in the file are ignored);
    a file with no ``tetra`` cells is refused. A file whose tets are *all*
    negatively oriented is reoriented; a mix of orientations is an error.
    """
    path = Path(path)
    if path.is_dir():
        raise MeshError(f"mesh file {path} is a directory, not a file; give a tetrahedral "
                        "mesh file (.msh, .vtu, .vtk, .xdmf)")
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    if is_gmsh1(path):
        pts, cells = read_gmsh1(path)
    else:
        pts, cells = _read_meshio(path)
    if "tetra" not in cells:
        raise MeshError(f"{path}: no tetra cells (found {sorted(cells)}); forcecal needs "
                        "linear tets")
    tets = cells["tetra"]
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise MeshError(f"{path}: points array has shape {pts.shape}; expected (N, 3)")
    if pts.shape[1] == 2:
        raise MeshError(f"{path}: 2-D points; a 3-D tetrahedral mesh is needed")
    pts = pts * scale
    if len(tets) and tets.min() >= 0 and tets.max() < len(pts):
        tets = orient_tets(pts, tets, str(path))
    try:
        return check_mesh(TetMesh(pts, tets))
    except MeshError as exc:
        raise MeshError(f"{path}: {exc}") from None


def _read_meshio(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Points and cells by kind (:func:`read_gmsh1`'s) of a file meshio reads."""
    import meshio

    said = io.StringIO()  # meshio prints an "Error: ..." line before exiting on some files
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # many types for bad files; sys.exit for some
        words = " ".join(said.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        fmt = path.suffix.lstrip(".") or "(no suffix)"
        raise MeshError(f"{path}: meshio could not read it as {fmt}: {words} (a damaged file, "
                        "or not a mesh of that format?)") from None
    cells: dict[str, list[np.ndarray]] = {}
    for block in m.cells:
        cells.setdefault(block.type, []).append(np.asarray(block.data))
    return (np.asarray(m.points, dtype=np.float64),
            {kind: np.concatenate(blocks).astype(np.int64) for kind, blocks in cells.items()})


def box_mesh(n: tuple[int, int, int] = (2, 2, 2),
             size: tuple[float, float, float] = (1.0, 1.0, 1.0),
             origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> TetMesh:
    """Structured box of ``n`` cells per axis, each cell split into 6 tets (Kuhn split).

    The Kuhn split makes neighbouring cells conforming, so the mesh is valid
    for any ``n``; handy for tests with closed-form answers.
    """
    nx, ny, nz = n
    xs = [np.linspace(o, o + s, k + 1) for o, s, k in zip(origin, size, n)]
    X, Y, Z = np.meshgrid(*xs, indexing="ij")
    vertices = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    # the 6 tets of the unit cube sharing the main diagonal (0,0,0)-(1,1,1)
    kuhn = [((0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 1, 1)),
            ((0, 0, 0), (1, 0, 0), (1, 0, 1), (1, 1, 1)),
            ((0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 1, 1)),
            ((0, 0, 0), (0, 1, 0), (0, 1, 1), (1, 1, 1)),
            ((0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1)),
            ((0, 0, 0), (0, 0, 1), (0, 1, 1), (1, 1, 1))]
    tets = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                for tet in kuhn:
                    tets.append([vid(i + a, j + b, k + c) for a, b, c in tet])
    tets = np.asarray(tets, dtype=np.int64)
    vol = TetMesh(vertices, tets).signed_volumes
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    return check_mesh(TetMesh(vertices, tets))
