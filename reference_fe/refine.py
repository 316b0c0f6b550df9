"""The FE mesh, independent of the particle mesh: ``fe.refine`` uniform refinements of it,
and ``fe.local_refine`` refinements around each punch's rim.

:func:`fe_problem` turns the scene's (particle-mesh) :class:`~forcecal.problem.Problem`
into the problem the FE reference solves: the mesh refined ``fe.refine`` times with
``dolfinx.mesh.refine`` (uniform, every tet split into 8), which keeps every original
vertex, so each particle vertex is an FE vertex (found by its coordinates) and every
result is read back there. Test points keep their inward normals (each face around
them is split into four coplanar ones). The clamp is the particle mesh's P2 clamp at
every level: the fixed vertices and the midpoints of the edges joining two of them (the
fixed-node rule's distance tolerance is not re-applied, it could catch new vertices
above the base).

A rigid punch's stress is singular along its rim, so its force converges like the mesh
size there (a uniform split changes it by 8-11 % on the default liver).
:func:`rim_refined_problem` refines, for one test point, only the cells near the rim of its
footprint's patch, ``fe.local_refine`` times, each time within half the previous band
(plaza refinement of the marked edges, the same vertex-keeping rules): a mesh per punch,
graded towards its rim, at a cost that grows like the rim's length.

A refinement level is refused before any work when its estimated factorisation would not
fit in the machine's memory (:func:`check_memory`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
import ufl
from dolfinx import mesh as dmesh
from mpi4py import MPI

from forcecal.errors import MeshError, SceneError
from forcecal.mesh import TetMesh, check_mesh
from forcecal.problem import Problem
from forcecal.scene import FESection

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class FEProblem:
    """The problem on the FE mesh and how to read its results at the particle vertices.

    Attributes:
        problem: the FE mesh, its clamped vertices, the test points (as FE vertex ids,
            all in ``calibration``) and the tracked node.
        vertex_map: (N,) int64, FE vertex id of each particle-mesh vertex.
        levels: uniform refinements applied (``fe.refine``).
        local_levels: rim refinements applied on top (``fe.local_refine``, one punch's mesh).
    """
    problem: Problem
    vertex_map: np.ndarray
    levels: int
    local_levels: int = 0


def refine_uniformly(mesh: TetMesh) -> TetMesh:
    """Every tet split into 8 (dolfinx's plaza refinement); original vertices are kept."""
    return refine_mesh(mesh)


def refine_mesh(mesh: TetMesh, marked: Callable[[np.ndarray], np.ndarray] | None = None
                ) -> TetMesh:
    """``mesh`` after one plaza refinement (original vertices kept, new ones at edge
    midpoints): uniform without ``marked``, else of the edges whose (E, 3) midpoints
    ``marked`` maps to True (and those plaza splits to keep the mesh conforming)."""
    cell = ufl.Mesh(ufl.VectorElement("Lagrange", "tetrahedron", 1))
    coarse = dmesh.create_mesh(MPI.COMM_SELF, mesh.tets, mesh.vertices, cell)
    coarse.topology.create_entities(1)
    if marked is None:
        fine = dmesh.refine(coarse, redistribute=False)
    else:
        edges = np.arange(coarse.topology.index_map(1).size_local, dtype=np.int32)
        chosen = np.asarray(marked(dmesh.compute_midpoints(coarse, 1, edges)), dtype=bool)
        fine = dmesh.refine(coarse, edges[chosen], redistribute=False)
    vertices = fine.geometry.x[:, :3].copy()
    tets = fine.geometry.dofmap.array.reshape(-1, 4).astype(np.int64)
    x = vertices[tets]
    volume = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                       x[:, 3] - x[:, 0])
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]  # dolfinx does not orient cells
    return check_mesh(TetMesh(vertices, tets))


def vertex_ids(mesh: TetMesh, points: np.ndarray, *, missing_ok: bool = False) -> np.ndarray:
    """Ids of the vertices of ``mesh`` at coordinates ``points`` (MeshError if one is missing,
    or, ``missing_ok``, the ids of those present)."""
    from scipy.spatial import cKDTree

    distance, ids = cKDTree(mesh.vertices).query(points)
    scale = np.ptp(mesh.vertices, axis=0).max()
    found = distance <= 1e-9 * scale
    if not missing_ok and not found.all():
        raise MeshError("refined mesh lost a vertex of the coarse mesh")
    return ids[found].astype(np.int64)


def refine_problem(problem: Problem, points: np.ndarray | None = None,
                   marked: Callable[[np.ndarray], np.ndarray] | None = None
                   ) -> tuple[Problem, np.ndarray]:
    """The problem on the mesh refined once (uniformly, or the ``marked`` edges:
    :func:`refine_mesh`), and the fine id of every coarse vertex.

    ``points`` (coarse ids, default: the test points) become the refined problem's
    calibration points; the clamp is the coarse P2 clamp (module docstring).
    """
    coarse = problem.mesh
    points = problem.test_points if points is None else np.asarray(points, dtype=np.int64)
    fine = refine_mesh(coarse, marked)
    vertex_map = vertex_ids(fine, coarse.vertices)
    is_fixed = np.zeros(coarse.n_vertices, dtype=bool)
    is_fixed[problem.fixed] = True
    base_edges = coarse.edges[is_fixed[coarse.edges].all(axis=1)]
    clamped = np.concatenate([vertex_map[problem.fixed],
                              vertex_ids(fine, coarse.vertices[base_edges].mean(axis=1),
                                         missing_ok=marked is not None)])
    refined = Problem(mesh=fine, fixed=np.sort(clamped), calibration=vertex_map[points],
                      held_out=np.zeros(0, np.int64),
                      tracked_node=int(vertex_map[problem.tracked_node]))
    return refined, vertex_map


def refined_counts(mesh: TetMesh, levels: int) -> tuple[int, int]:
    """(vertices, edges) of ``mesh`` after ``levels`` uniform refinements, exactly: each
    refinement adds a vertex per edge, splits each edge in 2, adds 3 edges per face and 1
    per tet, each face into 4 and each tet into 8."""
    v, e, t = mesh.n_vertices, len(mesh.edges), mesh.n_tets
    f = (4 * t + len(mesh.surface_faces)) // 2
    for _ in range(levels):
        v, e, f, t = v + e, 2 * e + 3 * f + t, 4 * f + 8 * t, 8 * t
    return v, e


def estimated_dofs(mesh: TetMesh, element: str, levels: int) -> int:
    """Length of the FE solution vector on ``mesh`` refined ``levels`` times."""
    v, e = refined_counts(mesh, levels)
    return {"P1": 3 * v, "P2": 3 * (v + e), "TH": 3 * (v + e) + v, "ANP": 4 * v}[element]


# bytes of one rank's FE model per dof^(4/3) (sparse 3-D LU fill grows like n^(4/3) with
# nested dissection); measured peak RSS at P2 refine = 1 on the default liver (34k dofs,
# 0.73 GB) gives ~0.5 kB; a factor 2 margin
BYTES_PER_DOF43 = 1000.0


def estimated_bytes(dofs: int) -> float:
    """Memory one rank's FE model of ``dofs`` unknowns is estimated to need [bytes]."""
    return BYTES_PER_DOF43 * dofs ** (4.0 / 3.0)


def available_memory() -> float:
    """Memory available on this machine now [bytes] (``MemAvailable``; total RAM otherwise)."""
    try:
        with open("/proc/meminfo") as fh:
            info = {line.split(":")[0]: float(line.split()[1]) * 1024.0 for line in fh}
        return info.get("MemAvailable", info["MemTotal"])
    except (OSError, KeyError, ValueError, IndexError):
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def check_memory(mesh: TetMesh, fe: FESection, ranks: int = 1,
                 punch_dofs: int | None = None) -> int:
    """Refuse an ``fe.refine`` or ``fe.local_refine`` whose FE models (one per rank) would not
    fit in memory.

    ``punch_dofs`` is the largest punch model's dofs when counted
    (:func:`reference_fe.run.largest_punch_dofs`). Otherwise a rim refinement is assumed to
    at most double the dofs, and a punch mesh is estimated at ``2**local_refine`` times the
    ``fe.refine`` mesh: measured x1.5-2.0 per level on the default liver's punches (its
    largest x2.03), but up to x3.5 on a coarse mesh with a large punch (SOFA's liver, 181
    vertices, a 40.7 mm punch: 146k dofs at ``local_refine = 3`` against 28k), where this
    underestimates.
    Returns the estimated dofs of the largest model. Raises SceneError naming the key.
    """
    dofs = estimated_dofs(mesh, fe.element, fe.refine)
    local = dofs * 2 ** fe.local_refine if punch_dofs is None else punch_dofs
    have = available_memory()
    for name, level, n in (("fe.refine", fe.refine, dofs),
                           ("fe.local_refine", fe.local_refine, local)):
        need = ranks * estimated_bytes(n)
        if need > have:
            raise SceneError(f"{name} = {level}: the {fe.element} model would have about "
                             f"{n} dofs and needs an estimated {need / 1e9:.1f} GB with "
                             f"{ranks} rank(s), more than the {have / 1e9:.1f} GB available; "
                             f"lower {name}")
    return local


def fe_problem(problem: Problem, fe: FESection) -> FEProblem:
    """The problem the FE reference solves for ``fe.refine`` (module docstring)."""
    current = Problem(mesh=problem.mesh, fixed=problem.fixed, calibration=problem.test_points,
                      held_out=np.zeros(0, np.int64), tracked_node=problem.tracked_node)
    vertex_map = np.arange(problem.mesh.n_vertices, dtype=np.int64)
    for _ in range(fe.refine):
        current, step = refine_problem(current)
        vertex_map = step[vertex_map]
    if fe.refine:
        log.info("FE mesh: %d uniform refinement(s): %s", fe.refine, current.mesh.summary())
    return FEProblem(current, vertex_map, fe.refine)


def fe_clamp(problem: Problem, fixed: np.ndarray, fe: FEProblem, section: FESection
             ) -> np.ndarray:
    """The FE vertices that clamp the particle vertices ``fixed`` (another support than
    ``problem.fixed``) on ``fe``'s mesh: ``fixed`` itself at ``fe.refine = 0``, else the P2
    clamp of every level (module docstring), from the same refinements of ``problem`` with
    ``fixed`` clamped.

    Raises:
        MeshError: the refinement did not give ``fe``'s mesh again.
    """
    if fe.levels == 0:
        return np.asarray(fixed, dtype=np.int64)
    other = fe_problem(dataclasses.replace(problem, fixed=np.asarray(fixed, dtype=np.int64)),
                       section)
    if not np.array_equal(other.problem.mesh.vertices, fe.problem.mesh.vertices):
        raise MeshError("refining the particle mesh again did not give the FE mesh")
    return other.problem.fixed


def rim_refined_problem(fe: FEProblem, mesh: TetMesh, footprint: np.ndarray,
                        levels: int) -> FEProblem:
    """``fe`` refined ``levels`` times near the rim of a surface patch (module docstring).

    ``mesh`` is the particle mesh and ``footprint`` the patch's particles: a punch's (the
    reference), or the clamped vertices (the convergence study's sag: the clamp's rim is
    singular too). Refinement k
    (1-based) splits the edges whose midpoint lies within ``h / 2**(k - 1)`` of the rim,
    ``h`` the mean surface edge length of ``fe``'s mesh: the cells touching the rim at
    every level, their size halved each time.
    """
    from forcecal.indenter import distance_to_segments, mean_surface_edge, patch_rim

    if levels == 0:
        return fe
    rim = mesh.vertices[patch_rim(mesh, footprint)]
    band = mean_surface_edge(fe.problem.mesh)
    current, vertex_map = fe.problem, fe.vertex_map
    for k in range(levels):
        width = band / 2 ** k
        current, step = refine_problem(
            current, marked=lambda x, w=width: distance_to_segments(x, rim[:, 0], rim[:, 1]) <= w)
        vertex_map = step[vertex_map]
    return FEProblem(current, vertex_map, fe.levels, levels)


def patch_on_fe_mesh(fe: FEProblem, mesh: TetMesh, footprint: np.ndarray) -> tuple[np.ndarray,
                                                                                    np.ndarray]:
    """The FE nodes of a particle footprint's surface patch: (FE vertex ids, FE surface edges).

    The patch is the particle mesh's surface triangles with three footprint vertices and its
    surface edges with two; uniform refinement puts FE vertices on them (edge midpoints of
    flat triangles), and those, with the FE surface edges between two of them (their P2
    mid-edge nodes), are the FE nodes of the patch. The same polygon at every level: a punch
    the particle model can hold exactly, whose FE force converges with the level.
    """
    from forcecal.indenter import distance_to_segments, footprint_edges, surface_edges

    footprint = np.asarray(footprint, dtype=np.int64)
    fine = fe.problem.mesh
    if fe.levels == 0 and fe.local_levels == 0:
        return footprint, footprint_edges(mesh, footprint)
    inside = np.zeros(mesh.n_vertices, dtype=bool)
    inside[footprint] = True
    triangles = mesh.surface_faces[inside[mesh.surface_faces].all(axis=1)]
    segments = footprint_edges(mesh, footprint)
    candidates = fine.surface_vertices
    x = fine.vertices[candidates]
    tol = 1e-9 * float(np.ptp(mesh.vertices, axis=0).max())
    ends = mesh.vertices[segments]
    on = distance_to_segments(x, ends[:, 0], ends[:, 1]) <= tol
    for a, b, c in mesh.vertices[triangles]:
        e1, e2 = b - a, c - a
        gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        st = np.linalg.solve(gram, np.stack([(x - a) @ e1, (x - a) @ e2]))
        distance = np.linalg.norm(x - a - np.outer(st[0], e1) - np.outer(st[1], e2), axis=1)
        on |= (distance <= tol) & (st[0] >= -1e-9) & (st[1] >= -1e-9) & (st.sum(0) <= 1 + 1e-9)
    nodes = np.union1d(candidates[on], fe.vertex_map[footprint])
    held = np.zeros(fine.n_vertices, dtype=bool)
    held[nodes] = True
    edges = surface_edges(fine)
    return nodes, edges[held[edges].all(axis=1)]
