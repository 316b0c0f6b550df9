"""Tetrahedral meshes: the one geometry both the FE reference and the particle model use.

A :class:`TetMesh` is two arrays (vertices, tets) plus derived quantities that
are pure functions of them (edges, volumes, surface, normals). Meshes come
from :func:`generate_liver` (deterministic gmsh model of a liver-like organ)
or :func:`read_mesh` (any tetrahedral mesh meshio reads), and always pass
:func:`check_mesh` before use.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Iterator

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


def _orient(vertices: np.ndarray, tets: np.ndarray, origin: str) -> np.ndarray:
    """Return tets positively oriented when a file uses the opposite convention throughout."""
    m = TetMesh(vertices, tets)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite: check_mesh refuses it
        vol = m.signed_volumes
    if len(vol) and np.all(vol < 0):
        log.info("%s: every tet is negatively oriented; swapping two vertices of each", origin)
        return tets[:, [0, 2, 1, 3]]
    return tets


def read_mesh(path: str | Path, scale: float = 1.0) -> TetMesh:
    """Read a tetrahedral mesh with meshio (.msh, .vtu, .vtk, .xdmf, ...) and check it.

    Only ``tetra`` cells are used (surface/line cells in the file are ignored);
    a file with no ``tetra`` cells is refused. A file whose tets are *all*
    negatively oriented is reoriented; a mix of orientations is an error.
    """
    import meshio

    path = Path(path)
    if path.is_dir():
        raise MeshError(f"mesh file {path} is a directory, not a file; give a tetrahedral "
                        "mesh file (.msh, .vtu, .vtk, .xdmf)")
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    said = io.StringIO()  # meshio prints an "Error: ..." line before exiting on some files
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # many types for bad files; sys.exit for some
        words = " ".join(said.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        fmt = path.suffix.lstrip(".") or "(no suffix)"
        raise MeshError(f"{path}: meshio could not read it as {fmt}: {words} (a damaged file, "
                        "or not a mesh of that format?)") from None
    blocks = [c.data for c in m.cells if c.type == "tetra"]
    if not blocks:
        kinds = sorted({c.type for c in m.cells})
        raise MeshError(f"{path}: no tetra cells (found {kinds}); forcecal needs linear tets")
    tets = np.concatenate(blocks).astype(np.int64)
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise MeshError(f"{path}: points array has shape {pts.shape}; expected (N, 3)")
    if pts.shape[1] == 2:
        raise MeshError(f"{path}: 2-D points; a 3-D tetrahedral mesh is needed")
    pts = pts * scale
    if len(tets) and tets.min() >= 0 and tets.max() < len(pts):
        tets = _orient(pts, tets, str(path))
    try:
        return check_mesh(TetMesh(pts, tets))
    except MeshError as exc:
        raise MeshError(f"{path}: {exc}") from None


@contextmanager
def gmsh_session(name: str) -> Iterator:
    """The ``gmsh`` module, initialised with a model ``name``, for one meshing job; finalised
    on exit.

    One thread and a fixed random seed, terminal output off: the same geometry and
    sizes give the same mesh, bit for bit (the generated meshes are content-hashed).
    """
    import gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.model.add(name)
        yield gmsh
    finally:
        gmsh.finalize()


#: bounding box of the generated liver [m] (x, y, z extents) and its volume [m^3] and surface
#: area [m^2] (measured on generate_liver(0.004): 0.21 x 0.12 x 0.065 m, 0.84 L, 0.052 m^2)
LIVER_EXTENT = (0.21, 0.12, 0.065)
LIVER_VOLUME = 8.4e-4
LIVER_AREA = 0.052


def liver_length_error(length: float) -> str | None:
    """Why ``length`` cannot be the generated liver's ``mesh.characteristic_length`` (None if
    it can): an edge as long as the organ's smallest extent leaves no interior vertex, and
    gmsh silently clamps it to the geometry's own features (a value in mm, e.g. 40, gives the
    same 26-vertex liver as 0.4)."""
    thickness = min(LIVER_EXTENT)
    if length >= thickness:
        return (f"mesh.characteristic_length = {length:g} m is not small against the generated "
                f"liver ({' x '.join(f'{e:g}' for e in LIVER_EXTENT)} m): it must be below its "
                f"smallest extent, {thickness:g} m (the default is 0.0182 m); scene values are "
                f"in metres: is it in mm? ({length:g} mm is {length / 1000:g})")
    return None


def estimated_liver_vertices(length: float) -> int:
    """Vertices of ``generate_liver(length)`` estimated before meshing, from the organ's
    volume and surface area: 0.647 V / h^3 + 1.078 A / h^2 (fitted to the meshes at h = 4
    and 6 mm; within 10 % of the actual count from h = 4 to 18.2 mm)."""
    return int(round(0.647 * LIVER_VOLUME / length ** 3 + 1.078 * LIVER_AREA / length ** 2))


def generate_liver(characteristic_length: float = 0.0182) -> TetMesh:
    """Deterministic liver-like solid: two fused ellipsoidal lobes, flat bottom at z = -0.025 m.

    Right lobe semi-axes 75 x 60 x 40 mm centred at x = +30 mm, left lobe
    60 x 40 x 25 mm centred at (-45, 10, 0) mm; everything below z = -25 mm is
    cut off, giving a flat base for the fixed-node rule. Overall ~ 0.21 x 0.12 x
    0.065 m, about 0.55 L. gmsh runs single-threaded with a fixed seed, so the
    same length gives the same arrays, bit for bit.
    """
    if characteristic_length <= 0:
        raise MeshError(f"characteristic_length must be > 0, got {characteristic_length}")
    problem = liver_length_error(characteristic_length)
    if problem:  # before gmsh, which would clamp it silently
        raise MeshError(problem)
    with gmsh_session("forcecal_liver") as gmsh:
        occ = gmsh.model.occ
        right = occ.addSphere(0.03, 0.0, 0.0, 1.0)
        occ.dilate([(3, right)], 0.03, 0.0, 0.0, 0.075, 0.06, 0.04)
        left = occ.addSphere(-0.045, 0.01, 0.0, 1.0)
        occ.dilate([(3, left)], -0.045, 0.01, 0.0, 0.06, 0.04, 0.025)
        fused, _ = occ.fuse([(3, right)], [(3, left)])
        below = occ.addBox(-0.2, -0.2, -0.2, 0.4, 0.4, 0.2 - 0.025)
        occ.cut(fused, [(3, below)])
        occ.synchronize()
        vols = [tag for _, tag in gmsh.model.getEntities(3)]
        gmsh.model.addPhysicalGroup(3, vols, 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMin", characteristic_length)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", characteristic_length)
        gmsh.option.setNumber("Mesh.CharacteristicLengthFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.optimize("")
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        _, _, elem_nodes = gmsh.model.mesh.getElements(3)
        gmsh.model.remove()
    node_tags = np.asarray(node_tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    tet_tags = np.concatenate([np.asarray(e, dtype=np.int64) for e in elem_nodes]).reshape(-1, 4)
    # renumber: keep the vertices tets use, in the order of gmsh's node tags
    used = np.unique(tet_tags)
    order = np.argsort(node_tags)
    pos = order[np.searchsorted(node_tags[order], used)]
    vertices = coords[pos]
    tets = np.searchsorted(used, tet_tags)
    tets = _orient(vertices, tets, "generated liver")
    return check_mesh(TetMesh(vertices, tets))


def fixed_nodes(mesh: TetMesh, axis: str = "z", side: str = "min",
                tolerance: float = 0.001) -> np.ndarray:
    """(F,) int64 ids of the vertices within ``tolerance`` of the min/max coordinate along
    ``axis``."""
    k = "xyz".index(axis)
    c = mesh.vertices[:, k]
    ref = c.min() if side == "min" else c.max()
    ids = np.nonzero(np.abs(c - ref) <= tolerance)[0]
    rule = f"fixed-node rule ({axis} {side} +- {tolerance} m)"
    if len(ids) < 3:
        raise MeshError(f"{rule} selects {len(ids)} vertices; at least 3 non-collinear ones are "
                        "needed to hold the organ")
    if len(ids) == mesh.n_vertices:
        raise MeshError(f"{rule} selects all {len(ids)} vertices: nothing is left free to "
                        "indent or to sag; lower fixed.tolerance")
    # clamped points on one line leave the rotation about it free (a singular problem); they
    # are collinear when the second principal extent is below 1e-6 of the first
    x = mesh.vertices[ids]
    extent = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if extent[1] <= 1e-6 * extent[0]:
        raise MeshError(f"{rule} selects {len(ids)} collinear vertices ({ids[:10].tolist()}); "
                        "the organ could rotate about their line: at least 3 non-collinear "
                        "ones are needed (widen fixed.tolerance)")
    return ids.astype(np.int64)


# bounds of the exact minimum cover ("cover"): branch-and-bound nodes (deterministic: the same
# graph stops at the same point on any machine; the default liver needs 13) and wall time [s]
# (a last resort on a heavily loaded machine: the default liver needs 5 s of CPU)
COVER_NODE_LIMIT = 1000
COVER_TIME_LIMIT_S = 300.0


def _closed_neighbourhoods(adj: sp.csr_matrix, vertices: np.ndarray) -> sp.csr_matrix:
    """(V, V) bool CSR: row i marks ``vertices[i]`` and its edge neighbours among ``vertices``."""
    return (adj[vertices][:, vertices] + sp.identity(len(vertices), dtype=bool, format="csr")
            ).tocsr()


def _minimum_dominating_set(adj: sp.csr_matrix, vertices: np.ndarray, n: int) -> np.ndarray:
    """Smallest subset D of ``vertices`` such that each of them is in D or adjacent to one in D.

    Solved exactly as a 0/1 integer programme (HiGHS through scipy.optimize.milp):
    minimise sum(x) subject to sum(x over the closed neighbourhood of v) >= 1 for
    every v. Deterministic for a given graph. Its linear relaxation, solved first
    (milliseconds), bounds the cover's size from below: a cover that cannot fit in
    the budget ``n`` is refused before the integer programme runs.
    """
    from scipy.optimize import Bounds, LinearConstraint, linprog, milp

    sub = _closed_neighbourhoods(adj, vertices).astype(np.float64)
    relaxed = linprog(np.ones(len(vertices)), A_ub=-sub, b_ub=-np.ones(len(vertices)),
                      bounds=(0, 1), method="highs")
    at_least = int(np.ceil(relaxed.fun - 1e-6)) if relaxed.status == 0 else 1
    if at_least > n:
        raise MeshError(f"test_points.calibration = 'cover': covering the {len(vertices)} free "
                        f"surface vertices needs at least {at_least} calibration points but "
                        f"test_points.n_calibration = {n}; use 'auto' ({n} spread-out points, "
                        "coverage reported) or raise n_calibration")
    res = milp(c=np.ones(len(vertices)), integrality=np.ones(len(vertices)),
               bounds=Bounds(0, 1), constraints=LinearConstraint(sub, lb=1.0),
               options={"node_limit": COVER_NODE_LIMIT, "time_limit": COVER_TIME_LIMIT_S})
    # only a proven optimum is a function of the graph alone; a time-limited feasible answer
    # would depend on the machine's speed (and change the points and every cache key)
    if res.status != 0 or res.x is None:
        raise MeshError(f"test_points.calibration = 'cover': the minimum cover of "
                        f"{len(vertices)} free surface vertices (at least {at_least} points) was "
                        f"not proven optimal within {COVER_NODE_LIMIT} branch-and-bound nodes "
                        f"and {COVER_TIME_LIMIT_S:g} s ({res.message}); use 'auto' (fast, "
                        "coverage reported) or give test_points.calibration explicitly")
    return np.sort(vertices[res.x > 0.5])


def _greedy_dominating_set(adj: sp.csr_matrix, vertices: np.ndarray) -> np.ndarray:
    """A (not minimum) cover of ``vertices``, built fast and deterministically.

    Repeatedly takes the vertex whose closed neighbourhood holds the most
    uncovered vertices (ties: the lowest id), then drops every chosen vertex
    whose neighbourhood the others cover too, last chosen first.
    """
    sub = _closed_neighbourhoods(adj, vertices)
    uncovered = np.ones(len(vertices), dtype=np.int64)
    chosen: list[int] = []
    while uncovered.any():
        k = int(np.argmax(sub @ uncovered))
        chosen.append(k)
        uncovered[sub.indices[sub.indptr[k]:sub.indptr[k + 1]]] = 0
    times_covered = np.asarray(sub[chosen].sum(axis=0)).ravel()
    kept = []
    for k in reversed(chosen):
        ring = sub.indices[sub.indptr[k]:sub.indptr[k + 1]]
        if np.all(times_covered[ring] > 1):
            times_covered[ring] -= 1
        else:
            kept.append(k)
    return np.sort(vertices[np.asarray(kept, dtype=np.int64)])


def euclidean_distance(mesh: TetMesh, candidates: np.ndarray):
    """Distance function for :func:`farthest_points`: straight-line distances [m]."""
    x = mesh.vertices[candidates]

    def to(sources: np.ndarray) -> np.ndarray:
        return np.min(np.linalg.norm(x[:, None] - mesh.vertices[sources][None], axis=2), axis=1)
    return to


def geodesic_distance(mesh: TetMesh, candidates: np.ndarray):
    """Distance function for :func:`farthest_points`: shortest paths along the surface
    triangles' edges [m] (a part the surface does not reach is infinitely far)."""
    from scipy.sparse.csgraph import dijkstra

    f = mesh.surface_faces
    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1),
                  axis=0)
    length = np.linalg.norm(mesh.vertices[e[:, 1]] - mesh.vertices[e[:, 0]], axis=1)
    n = mesh.n_vertices
    graph = sp.coo_matrix((length, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()

    def to(sources: np.ndarray) -> np.ndarray:
        return dijkstra(graph, directed=False, indices=sources, min_only=True)[candidates]
    return to


def farthest_points(distance_to, candidates: np.ndarray, n: int, avoid: np.ndarray,
                    what: str) -> list[int]:
    """n candidates chosen one by one as far as possible from ``avoid`` and from each other
    (``distance_to(sources)`` gives the distance of every candidate to the nearest source;
    ``what`` names them in the error raised when there are fewer than n)."""
    if n == 0:
        return []
    if len(candidates) < n:
        raise MeshError(f"only {len(candidates)} free surface vertices left for {n} {what}")
    d = distance_to(avoid if len(avoid) else candidates[:1])
    chosen: list[int] = []
    for _ in range(n):
        k = int(np.argmax(d))
        chosen.append(int(candidates[k]))
        d = np.minimum(d, distance_to(candidates[k:k + 1]))
        d[k] = -1.0
    return chosen


def free_surface_vertices(mesh: TetMesh, fixed: np.ndarray) -> np.ndarray:
    """(Nf,) int64, sorted surface vertices that are not fixed (the candidate test points)."""
    return np.setdiff1d(mesh.surface_vertices, fixed)


def coverage(mesh: TetMesh, fixed: np.ndarray, points: np.ndarray) -> float:
    """Fraction of the free surface vertices that are one of ``points`` or share a mesh edge
    with one (1.0: the points cover the free surface)."""
    free_surface = free_surface_vertices(mesh, fixed)
    covered = np.zeros(mesh.n_vertices, dtype=bool)
    points = np.asarray(points, dtype=np.int64)
    covered[points] = True
    covered[mesh.adjacency[points].indices] = True
    return float(covered[free_surface].mean())


CALIBRATION_RULES = ("auto", "cover")


def select_calibration_points(mesh: TetMesh, fixed: np.ndarray, n: int = 31,
                              rule: str = "auto", candidates: np.ndarray | None = None
                              ) -> np.ndarray:
    """Choose ``n`` calibration points (sorted vertex ids) spread over the free surface.

    A cover (dominating set) of the free surface graph is a set of points such
    that every free surface vertex is a point or shares a mesh edge with one, so
    every surface connector lies in or touches the first ring of a point.

    * ``rule="cover"`` (the paper's): the proven *minimum* cover, topped up to
      ``n`` with the points farthest (straight line) from it and from each other.
      Refused when the cover needs more than ``n`` points or is not proven
      minimal within :data:`COVER_NODE_LIMIT` nodes or :data:`COVER_TIME_LIMIT_S`
      (meshes of a few hundred free surface vertices and more).
    * ``rule="auto"`` (any mesh, milliseconds): a greedy cover topped up the same
      way but by distance along the surface when it fits in ``n``; otherwise
      ``n`` points by farthest-point sampling along the surface, starting from
      the fixed nodes, which leaves part of the surface uncovered (see
      :func:`coverage`; it is logged).

    ``candidates`` (rule ``"auto"`` only): the free surface vertices the points may be and
    the cover covers (default: all of them); a punch scene passes those its punch can
    indent (:func:`forcecal.indenter.punch_candidates`).
    """
    if rule not in CALIBRATION_RULES:
        raise MeshError(f"unknown calibration point rule {rule!r}; expected one of "
                        f"{list(CALIBRATION_RULES)}")
    free_surface = free_surface_vertices(mesh, fixed)
    if candidates is not None:
        if rule != "auto":
            raise MeshError(f"calibration point rule {rule!r} takes no candidate set; "
                            "only 'auto' does")
        free_surface = np.intersect1d(free_surface, candidates)
    what = "calibration points (test_points.n_calibration)"
    if rule == "cover":
        cover = _minimum_dominating_set(mesh.adjacency, free_surface, n)
        if len(cover) > n:
            raise MeshError(f"covering the free surface needs {len(cover)} calibration points "
                            f"but test_points.n_calibration = {n}; use 'auto' or raise "
                            "n_calibration")
        distance_to = euclidean_distance(mesh, np.setdiff1d(free_surface, cover))
    else:
        cover = _greedy_dominating_set(mesh.adjacency, free_surface)
        if len(cover) > n:
            log.info("a greedy cover of the free surface needs %d points, more than "
                     "test_points.n_calibration = %d: sampling %d far-apart points instead",
                     len(cover), n, n)
            seeds = np.asarray(fixed, dtype=np.int64)  # the first point: farthest from them
            chosen = farthest_points(geodesic_distance(mesh, free_surface), free_surface, n,
                                     seeds, what)
            return np.sort(np.asarray(chosen, dtype=np.int64))
        distance_to = geodesic_distance(mesh, np.setdiff1d(free_surface, cover))
    rest = np.setdiff1d(free_surface, cover)
    chosen = list(cover) + farthest_points(distance_to, rest, n - len(cover), cover, what)
    return np.sort(np.asarray(chosen, dtype=np.int64))


def select_held_out_points(mesh: TetMesh, fixed: np.ndarray, calibration: np.ndarray,
                           n: int = 8, candidates: np.ndarray | None = None) -> np.ndarray:
    """``n`` free surface vertices farthest (straight line) from the calibration points and
    from each other: fast on any mesh (n passes over the free surface). ``candidates``: as
    :func:`select_calibration_points`."""
    rest = np.setdiff1d(free_surface_vertices(mesh, fixed), calibration)
    if candidates is not None:
        rest = np.intersect1d(rest, candidates)
    held = farthest_points(euclidean_distance(mesh, rest), rest, n, np.asarray(calibration),
                           "held-out points (test_points.n_held_out)")
    return np.sort(np.asarray(held, dtype=np.int64))


def validate_test_points(mesh: TetMesh, fixed: np.ndarray, points: np.ndarray,
                         what: str) -> np.ndarray:
    """Check user-given test points: in range, unique, on the surface, not fixed."""
    p = np.asarray(points, dtype=np.int64)
    if p.ndim != 1:
        raise MeshError(f"{what} test points must be a list of vertex ids")
    bad = p[(p < 0) | (p >= mesh.n_vertices)]
    if len(bad):
        raise MeshError(f"unknown test point(s) {bad.tolist()} in {what}: the mesh has "
                        f"vertices 0..{mesh.n_vertices - 1}")
    if len(np.unique(p)) != len(p):
        raise MeshError(f"{what} test points contain duplicates")
    off = np.setdiff1d(p, mesh.surface_vertices)
    if len(off):
        raise MeshError(f"{what} test point(s) {off.tolist()} are not on the surface")
    fx = np.intersect1d(p, fixed)
    if len(fx):
        raise MeshError(f"{what} test point(s) {fx.tolist()} are fixed nodes and cannot be "
                        "indented")
    return np.sort(p)


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
