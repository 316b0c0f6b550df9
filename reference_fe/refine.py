"""The FE mesh, independent of the particle mesh: ``fe.refine`` uniform refinements of it.

:func:`fe_problem` turns the scene's (particle-mesh) :class:`~forcecal.problem.Problem`
into the problem the FE reference solves: the mesh refined ``fe.refine`` times with
``dolfinx.mesh.refine`` (uniform, every tet split into 8), which keeps every original
vertex, so each particle vertex is an FE vertex (found by its coordinates) and every
result is read back there. Test points keep their inward normals (each face around
them is split into four coplanar ones). The clamp is the particle mesh's P2 clamp at
every level: the fixed vertices and the midpoints of the edges joining two of them (the
fixed-node rule's distance tolerance is not re-applied, it could catch new vertices
above the base).

A refinement level is refused before any work when its estimated factorisation would not
fit in the machine's memory (:func:`check_memory`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

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
    """
    problem: Problem
    vertex_map: np.ndarray
    levels: int


def refine_uniformly(mesh: TetMesh) -> TetMesh:
    """Every tet split into 8 (dolfinx's plaza refinement); original vertices are kept."""
    cell = ufl.Mesh(ufl.VectorElement("Lagrange", "tetrahedron", 1))
    coarse = dmesh.create_mesh(MPI.COMM_SELF, mesh.tets, mesh.vertices, cell)
    coarse.topology.create_entities(1)
    fine = dmesh.refine(coarse, redistribute=False)
    vertices = fine.geometry.x[:, :3].copy()
    tets = fine.geometry.dofmap.array.reshape(-1, 4).astype(np.int64)
    x = vertices[tets]
    volume = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]),
                       x[:, 3] - x[:, 0])
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]  # dolfinx does not orient cells
    return check_mesh(TetMesh(vertices, tets))


def vertex_ids(mesh: TetMesh, points: np.ndarray) -> np.ndarray:
    """Ids of the vertices of ``mesh`` at coordinates ``points`` (MeshError if one is missing)."""
    from scipy.spatial import cKDTree

    distance, ids = cKDTree(mesh.vertices).query(points)
    scale = np.ptp(mesh.vertices, axis=0).max()
    if np.any(distance > 1e-9 * scale):
        raise MeshError("refined mesh lost a vertex of the coarse mesh")
    return ids.astype(np.int64)


def refine_problem(problem: Problem, points: np.ndarray | None = None) -> tuple[Problem,
                                                                                  np.ndarray]:
    """The problem on the mesh refined once, and the fine id of every coarse vertex.

    ``points`` (coarse ids, default: the test points) become the refined problem's
    calibration points; the clamp is the coarse P2 clamp (module docstring).
    """
    coarse = problem.mesh
    points = problem.test_points if points is None else np.asarray(points, dtype=np.int64)
    fine = refine_uniformly(coarse)
    vertex_map = vertex_ids(fine, coarse.vertices)
    is_fixed = np.zeros(coarse.n_vertices, dtype=bool)
    is_fixed[problem.fixed] = True
    base_edges = coarse.edges[is_fixed[coarse.edges].all(axis=1)]
    clamped = np.concatenate([vertex_map[problem.fixed],
                              vertex_ids(fine, coarse.vertices[base_edges].mean(axis=1))])
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
    return {"P1": 3 * v, "P2": 3 * (v + e), "TH": 3 * (v + e) + v}[element]


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


def check_memory(mesh: TetMesh, fe: FESection, ranks: int = 1) -> int:
    """Refuse an ``fe.refine`` whose FE models (one per rank) would not fit in memory.

    Returns the estimated dofs. Raises SceneError naming ``fe.refine``.
    """
    dofs = estimated_dofs(mesh, fe.element, fe.refine)
    need = ranks * estimated_bytes(dofs)
    have = available_memory()
    if need > have:
        raise SceneError(f"fe.refine = {fe.refine}: the {fe.element} model would have "
                         f"{dofs} dofs and needs an estimated {need / 1e9:.1f} GB with {ranks} "
                         f"rank(s), more than the {have / 1e9:.1f} GB available; lower "
                         "fe.refine")
    return dofs


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


def patch_on_fe_mesh(fe: FEProblem, mesh: TetMesh, footprint: np.ndarray) -> tuple[np.ndarray,
                                                                                    np.ndarray]:
    """The FE nodes of a particle footprint's surface patch: (FE vertex ids, FE surface edges).

    The patch is the particle mesh's surface triangles with three footprint vertices and its
    surface edges with two; uniform refinement puts FE vertices on them (edge midpoints of
    flat triangles), and those, with the FE surface edges between two of them (their P2
    mid-edge nodes), are the FE nodes of the patch. The same polygon at every level: a punch
    the particle model can hold exactly, whose FE force converges with the level.
    """
    from forcecal.indenter import footprint_edges, surface_edges

    footprint = np.asarray(footprint, dtype=np.int64)
    fine = fe.problem.mesh
    if fe.levels == 0:
        return footprint, footprint_edges(mesh, footprint)
    inside = np.zeros(mesh.n_vertices, dtype=bool)
    inside[footprint] = True
    triangles = mesh.surface_faces[inside[mesh.surface_faces].all(axis=1)]
    segments = footprint_edges(mesh, footprint)
    candidates = fine.surface_vertices
    x = fine.vertices[candidates]
    tol = 1e-9 * float(np.ptp(mesh.vertices, axis=0).max())
    on = np.zeros(len(candidates), dtype=bool)
    for p, q in mesh.vertices[segments]:
        d = q - p
        s = np.clip((x - p) @ d / (d @ d), 0.0, 1.0)
        on |= np.linalg.norm(x - p - s[:, None] * d, axis=1) <= tol
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
