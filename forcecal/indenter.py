"""The indenter's contact set: which surface nodes a rigid flat punch holds.

One rule, shared by the FE reference (on its own, possibly refined, mesh) and the
particle model (on the particle mesh). A rigid, bonded, flat circular punch of
radius ``R`` centred on surface vertex ``i`` and pushed along its inward normal
``n_i`` holds the *footprint*: the surface nodes ``j``

* whose projection on the tangent plane at ``i`` lies within ``R`` of ``x_i``
  (``|(x_j - x_i) - ((x_j - x_i) . n_i) n_i| <= R``),
* that face the same way (``m_j . m_i > 0`` with ``m`` the area-weighted outward unit
  vertex normals of :attr:`~forcecal.mesh.TetMesh.vertex_normals`; at right angles, up to
  :data:`FACING_TOLERANCE`, is not the same way), and
* that are connected to ``i`` through surface edges between such nodes (a punch on
  one lobe does not grab a fold of another one that happens to project inside).

Every footprint node is displaced by ``d n_i``; the punch force is the sum of their
reactions. ``indentation.indenter = "vertex"`` (the paper's) is the footprint ``{i}``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from forcecal.errors import SceneError
from forcecal.mesh import TetMesh

# a node exactly on the punch's rim (a mesh made to fit it) is inside, despite round-off
RIM_TOLERANCE = 1e-9
# a node whose normal is at right angles to the test point's (a box's edge across a face from
# an edge) has m_j . m_i = 0 up to round-off, whose sign differs between machines (BLAS
# kernels, summation order): it is out on every machine, so a footprint does not depend on one
FACING_TOLERANCE = 1e-9
# fewer held particles than this is a point load, not a punch
MIN_FOOTPRINT = 3


def surface_edges(mesh: TetMesh) -> np.ndarray:
    """(Es, 2) int64, unique edges (i < j) of the boundary triangles, sorted."""
    f = mesh.surface_faces
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def _tangential_distance(mesh: TetMesh, vertex: int, normal: np.ndarray) -> np.ndarray:
    """(N,) distance of every vertex's projection on the tangent plane at ``vertex`` [m]."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    d = mesh.vertices - mesh.vertices[vertex]
    return np.linalg.norm(d - np.outer(d @ n, n), axis=1)


def _facing(mesh: TetMesh, vertex: int) -> np.ndarray:
    """(N,) bool: the vertices whose normal faces the same way as ``vertex``'s (module
    docstring)."""
    m = mesh.vertex_normals
    return m @ m[vertex] > FACING_TOLERANCE


def _footprint(mesh: TetMesh, edges: np.ndarray, vertex: int, distance: np.ndarray,
               radius: float) -> np.ndarray:
    """The rule of the module docstring for one radius, given the tangential distances."""
    candidate = np.zeros(mesh.n_vertices, dtype=bool)
    candidate[mesh.surface_vertices] = True
    candidate &= distance <= radius * (1.0 + RIM_TOLERANCE)
    candidate &= _facing(mesh, vertex)
    candidate[vertex] = True
    keep = edges[candidate[edges].all(axis=1)]
    graph = sp.coo_matrix((np.ones(len(keep)), (keep[:, 0], keep[:, 1])),
                          shape=(mesh.n_vertices, mesh.n_vertices))
    _, label = connected_components(graph, directed=False)
    return np.nonzero(candidate & (label == label[vertex]))[0].astype(np.int64)


def punch_footprint(mesh: TetMesh, vertex: int, normal: np.ndarray, radius: float, *,
                    fixed: np.ndarray | None = None,
                    min_nodes: int = MIN_FOOTPRINT) -> np.ndarray:
    """(K,) int64 sorted ids of the surface nodes a flat punch of ``radius`` holds (module
    docstring), ``vertex`` included.

    Args:
        mesh: the mesh the punch acts on.
        vertex: the test vertex (a surface vertex), the punch's centre.
        normal: (3,) its indentation direction (inward normal; only the plane matters).
        radius: punch radius [m].
        fixed: clamped vertex ids; a footprint that holds one is refused.
        min_nodes: smallest acceptable footprint (particle meshes: 3).

    Raises:
        SceneError: ``radius <= 0``, a footprint with fewer than ``min_nodes`` nodes (the
            message gives the smallest radius that holds enough) or one that touches the
            clamp (the message gives the largest radius that does not); each names
            ``indentation.radius`` and the test point.
    """
    vertex = int(vertex)
    if not radius > 0:
        raise SceneError(f"indentation.radius = {radius} m: a punch radius must be > 0")
    edges = surface_edges(mesh)
    distance = _tangential_distance(mesh, vertex, normal)
    nodes = _footprint(mesh, edges, vertex, distance, radius)
    if fixed is not None and len(fixed):
        touched = np.intersect1d(nodes, fixed)
        if len(touched):
            limit = float(distance[touched].min())
            raise SceneError(f"indentation.radius = {radius:.4g} m: the punch footprint of test "
                             f"point {vertex} reaches clamped vertices {touched[:5].tolist()}; "
                             f"use a radius below {limit:.4g} m or another test point")
    if len(nodes) < min_nodes:
        need = None
        same_side = np.nonzero(_facing(mesh, vertex))[0]
        for r in np.sort(distance[np.intersect1d(same_side, mesh.surface_vertices)]):
            if r > radius and len(_footprint(mesh, edges, vertex, distance, r)) >= min_nodes:
                need = r
                break
        hint = (f"use a radius of at least {need:.4g} m" if need is not None
                else "no radius reaches that many on this side of the surface")
        raise SceneError(f"indentation.radius = {radius:.4g} m: the punch footprint of test "
                         f"point {vertex} holds {len(nodes)} particle(s), fewer than "
                         f"{min_nodes}; {hint}")
    return nodes


def face_gaps(mesh: TetMesh, vertex: int, normal: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """(K,) distance [m] of each of ``nodes`` from the plane of a flat punch's face centred at
    ``vertex`` with ``normal``, on either side: behind the face (a convex surface) the punch
    reaches them only after that much travel, in front of it (a concave one) they stand
    that far proud of the face."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    return np.abs((mesh.vertices[nodes] - mesh.vertices[int(vertex)]) @ n)


def radii_within_reach(mesh: TetMesh, vertex: int, normal: np.ndarray, radius: float,
                       depth: float, *, min_nodes: int = MIN_FOOTPRINT
                       ) -> tuple[float, float] | None:
    """The radii ``(smallest, beyond)`` [m] at which the footprint at ``vertex`` holds at least
    ``min_nodes`` nodes, all within ``depth`` [m] of the punch's face (:func:`face_gaps`):
    every radius ``r`` with ``smallest <= r < beyond`` (``beyond`` just above ``radius`` when
    the scene's own footprint is within reach); None when no radius up to ``radius`` does.

    A footprint grows with the radius and changes only where the radius passes a surface
    node's distance from the punch's axis, so those distances are the radii tried, smallest
    first, up to the first footprint with a node out of reach."""
    vertex = int(vertex)
    edges = surface_edges(mesh)
    distance = _tangential_distance(mesh, vertex, normal)
    surface = np.unique(distance[mesh.surface_vertices])
    smallest = None
    for r in [*surface[surface < radius], radius]:
        nodes = _footprint(mesh, edges, vertex, distance, float(r))
        if face_gaps(mesh, vertex, normal, nodes).max() > depth:
            return None if smallest is None else (smallest, float(r))
        if smallest is None and len(nodes) >= min_nodes:
            smallest = float(r)
    return None if smallest is None else (smallest, float(np.nextafter(radius, np.inf)))


def footprint_edges(mesh: TetMesh, nodes: np.ndarray) -> np.ndarray:
    """(K', 2) int64 surface edges with both ends in ``nodes``: their mid-edge nodes (P2) lie
    on the punch face too."""
    inside = np.zeros(mesh.n_vertices, dtype=bool)
    inside[np.asarray(nodes, dtype=np.int64)] = True
    edges = surface_edges(mesh)
    return edges[inside[edges].all(axis=1)]


def mean_surface_edge(mesh: TetMesh) -> float:
    """Mean length of the surface edges of ``mesh`` [m]: the scale of punch radii and of the
    FE mesh's rim refinement."""
    x = mesh.vertices[surface_edges(mesh)]
    return float(np.linalg.norm(x[:, 1] - x[:, 0], axis=1).mean())


def patch_rim(mesh: TetMesh, nodes: np.ndarray) -> np.ndarray:
    """(R, 2) int64 vertex pairs: the rim of a footprint's surface patch (the surface triangles
    with three footprint vertices and the surface edges with two), i.e. the triangles' edges
    used by one of them and the edges that belong to no triangle. A rigid punch's stress is
    singular along it, which is where an FE mesh must be fine for its force to converge."""
    inside = np.zeros(mesh.n_vertices, dtype=bool)
    inside[np.asarray(nodes, dtype=np.int64)] = True
    triangles = mesh.surface_faces[inside[mesh.surface_faces].all(axis=1)]
    sides = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    sides, count = np.unique(sides, axis=0, return_counts=True)
    segments = np.sort(footprint_edges(mesh, nodes), axis=1)
    in_triangle = {tuple(e) for e in sides.tolist()}
    lone = [e for e in segments.tolist() if tuple(e) not in in_triangle]
    return np.concatenate([sides[count == 1], np.asarray(lone, dtype=np.int64).reshape(-1, 2)])


def distance_to_segments(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(P,) distance [m] of each of ``points`` (P, 3) to the nearest of the segments
    ``start``-``end`` (S, 3) each."""
    distance = np.full(len(points), np.inf)
    for p, q in zip(start, end):
        d = q - p
        s = np.clip((points - p) @ d / (d @ d), 0.0, 1.0)
        distance = np.minimum(distance, np.linalg.norm(points - p - s[:, None] * d, axis=1))
    return distance


def punch_candidates(mesh: TetMesh, fixed: np.ndarray, radius: float) -> np.ndarray:
    """(C,) int64 sorted free surface vertices a flat punch of ``radius`` can indent: its
    footprint (:func:`punch_footprint`, along the vertex's inward normal) holds at least
    :data:`MIN_FOOTPRINT` particles and no clamped vertex. The ``"auto"`` test point rules
    choose among these on a punch scene (a point near the clamp would be refused).

    Raises:
        SceneError: ``radius <= 0``, or no free surface vertex qualifies (the message gives
            the largest radius that stays off the clamp at some vertex, if one reached it).
    """
    if not radius > 0:
        raise SceneError(f"indentation.radius = {radius} m: a punch radius must be > 0")
    fixed = np.asarray(fixed, dtype=np.int64)
    free = np.setdiff1d(mesh.surface_vertices, fixed)
    clamped = np.zeros(mesh.n_vertices, dtype=bool)
    clamped[fixed] = True
    edges = surface_edges(mesh)
    ok, room = [], 0.0
    for vertex, normal in zip(free, mesh.inward_normals(free)):
        distance = _tangential_distance(mesh, int(vertex), normal)
        nodes = _footprint(mesh, edges, int(vertex), distance, radius)
        touched = nodes[clamped[nodes]]
        if len(nodes) >= MIN_FOOTPRINT and not len(touched):
            ok.append(int(vertex))
        elif len(touched):
            room = max(room, float(distance[touched].min()))
    if not ok:
        raise SceneError(f"indentation.radius = {radius:.4g} m: no free surface vertex has a "
                         f"punch footprint of at least {MIN_FOOTPRINT} particles that stays off "
                         "the clamp" + (f" (radii below {room:.4g} m stay off it somewhere)"
                                        if room > 0 else ""))
    return np.asarray(ok, dtype=np.int64)


def indenter_footprints(mesh: TetMesh, fixed: np.ndarray, test_points: np.ndarray,
                          normals: np.ndarray, indenter: str,
                          radius: float) -> tuple[np.ndarray, ...]:
    """The held particles of every test point: ``(vertex,)`` for ``"vertex"``, the punch
    footprint for ``"punch"`` (checked: >= 3 particles, off the clamp)."""
    if indenter == "vertex":
        return tuple(np.array([int(p)], dtype=np.int64) for p in test_points)
    if indenter != "punch":
        raise SceneError(f"indentation.indenter = {indenter!r}: known indenters are "
                         "'vertex' and 'punch'")
    return tuple(punch_footprint(mesh, int(p), n, radius, fixed=fixed)
                 for p, n in zip(test_points, normals))
