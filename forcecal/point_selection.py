"""Which mesh vertices a scene holds and which it indents: the fixed-node rule, the
calibration points (a cover of the free surface, or far-apart points when none fits the
budget), the held-out points, the checks of user-given test points, and the coverage
reported for them."""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import scipy.sparse as sp

from forcecal.errors import MeshError
from forcecal.mesh import TetMesh

log = logging.getLogger(__name__)


def fixed_nodes(mesh: TetMesh, axis: str = "z", side: str = "min",
                tolerance: float = 0.001, section: str = "fixed") -> np.ndarray:
    """(F,) int64 ids of the vertices within ``tolerance`` of the min/max coordinate along
    ``axis``; ``section`` is the scene section whose keys they are (named in the errors)."""
    k = "xyz".index(axis)
    c = mesh.vertices[:, k]
    ref = c.min() if side == "min" else c.max()
    ids = np.nonzero(np.abs(c - ref) <= tolerance)[0]
    rule = (f"fixed-node rule ({axis} {side} +- {tolerance} m)" if section == "fixed"
            else f"{section} rule ({axis} {side} +- {tolerance} m)")
    if len(ids) < 3:
        raise MeshError(f"{rule} selects {len(ids)} vertices; at least 3 non-collinear ones are "
                        f"needed to hold the organ (widen {section}.tolerance)")
    if len(ids) == mesh.n_vertices:
        raise MeshError(f"{rule} selects all {len(ids)} vertices: nothing is left free to "
                        f"indent or to sag; lower {section}.tolerance")
    # clamped points on one line leave the rotation about it free (a singular problem); they
    # are collinear when the second principal extent is below 1e-6 of the first
    x = mesh.vertices[ids]
    extent = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    if extent[1] <= 1e-6 * extent[0]:
        raise MeshError(f"{rule} selects {len(ids)} collinear vertices ({ids[:10].tolist()}); "
                        "the organ could rotate about their line: at least 3 non-collinear "
                        f"ones are needed (widen {section}.tolerance)")
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
    from scipy.optimize import linprog

    sub = _closed_neighbourhoods(adj, vertices).astype(np.float64)
    relaxed = linprog(np.ones(len(vertices)), A_ub=-sub, b_ub=-np.ones(len(vertices)),
                      bounds=(0, 1), method="highs")
    at_least = int(np.ceil(relaxed.fun - 1e-6)) if relaxed.status == 0 else 1
    if at_least > n:
        raise MeshError(f"test_points.calibration = 'cover': covering the {len(vertices)} free "
                        f"surface vertices needs at least {at_least} calibration points but "
                        f"test_points.n_calibration = {n}; use 'auto' ({n} spread-out points, "
                        "coverage reported) or raise n_calibration")
    key = hashlib.sha256(sub.indptr.tobytes() + sub.indices.tobytes()).digest()
    if key not in _COVERS:
        _COVERS[key] = _exact_cover(sub, at_least)
        while len(_COVERS) > KEPT_COVERS:
            del _COVERS[next(iter(_COVERS))]
    return np.sort(vertices[_COVERS[key]])


#: proven minimum covers this process has found, by their graph (a proven optimum is a
#: function of the graph alone; the test points of every stage and test of one mesh are
#: chosen from the same graph)
_COVERS: dict[bytes, np.ndarray] = {}
KEPT_COVERS = 16


def _exact_cover(sub: sp.csr_matrix, at_least: int) -> np.ndarray:
    """(V,) bool, the proven minimum cover of :func:`_minimum_dominating_set`'s closed
    neighbourhoods ``sub`` (V, V), which need ``at_least`` points."""
    from scipy.optimize import Bounds, LinearConstraint, milp

    n_vertices = sub.shape[0]
    res = milp(c=np.ones(n_vertices), integrality=np.ones(n_vertices),
               bounds=Bounds(0, 1), constraints=LinearConstraint(sub, lb=1.0),
               options={"node_limit": COVER_NODE_LIMIT, "time_limit": COVER_TIME_LIMIT_S})
    # only a proven optimum is a function of the graph alone; a time-limited feasible answer
    # would depend on the machine's speed (and change the points and every cache key)
    if res.status != 0 or res.x is None:
        raise MeshError(f"test_points.calibration = 'cover': the minimum cover of "
                        f"{n_vertices} free surface vertices (at least {at_least} points) was "
                        f"not proven optimal within {COVER_NODE_LIMIT} branch-and-bound nodes "
                        f"and {COVER_TIME_LIMIT_S:g} s ({res.message}); use 'auto' (fast, "
                        "coverage reported) or give test_points.calibration explicitly")
    chosen = res.x > 0.5
    chosen.setflags(write=False)
    return chosen


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
