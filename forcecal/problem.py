"""The geometric set-up of a scene: mesh, fixed nodes, test points, normals, tracked node.

:func:`build_problem` turns a :class:`~forcecal.scene.Scene` into a
:class:`Problem`. The FE stage stores it in ``reference.h5`` and every later
stage reads it back from there (:func:`forcecal.h5io.read_reference`), so the
particle side never re-derives geometry on its own.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from forcecal.errors import MeshError, SceneError
from forcecal.indenter import punch_candidates
from forcecal.liver_mesh import generate_liver
from forcecal.mesh import TetMesh, read_mesh
from forcecal.point_selection import (coverage, euclidean_distance, farthest_points, fixed_nodes,
                                      free_surface_vertices, geodesic_distance,
                                      select_calibration_points, select_held_out_points,
                                      validate_test_points)
from forcecal.scene import MIN_HELD_OUT, Scene

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything geometric a scene's experiments need.

    Attributes:
        mesh: the tetrahedral mesh (vertices [m], tets).
        fixed: (F,) int64, ids of the fixed (clamped) vertices.
        calibration: (Pc,) int64, calibration test points (vertex ids).
        held_out: (Ph,) int64, held-out test points, disjoint from ``calibration``.
        tracked_node: vertex id whose gravity displacement history is compared.
    """
    mesh: TetMesh
    fixed: np.ndarray
    calibration: np.ndarray
    held_out: np.ndarray
    tracked_node: int

    @property
    def test_points(self) -> np.ndarray:
        """(P,) int64: calibration points followed by held-out points (the curve order in files)."""
        return np.concatenate([self.calibration, self.held_out])

    @property
    def normals(self) -> np.ndarray:
        """(P, 3) float64: inward unit normals of :attr:`test_points` (indentation directions)."""
        return self.mesh.inward_normals(self.test_points)

    @property
    def free(self) -> np.ndarray:
        """(N,) bool: True for vertices that are not fixed."""
        m = np.ones(self.mesh.n_vertices, dtype=bool)
        m[self.fixed] = False
        return m

    @property
    def coverage(self) -> dict[str, float]:
        """Fraction of the free surface vertices that are a calibration (held-out) point or
        share a mesh edge with one (:func:`forcecal.point_selection.coverage`), by point set."""
        return {"calibration": coverage(self.mesh, self.fixed, self.calibration),
                "held_out": coverage(self.mesh, self.fixed, self.held_out)}


def load_mesh(scene: Scene) -> TetMesh:
    """The scene's mesh: generated liver or file (already checked).

    A generated liver is priced before gmsh runs (:func:`forcecal.cost.check_generated_cost`:
    an estimated vertex count whose work is above the cost limit is refused)."""
    path = scene.mesh_source_path()
    if path is None:
        from forcecal.cost import check_generated_cost
        check_generated_cost(scene)
        mesh = generate_liver(scene.mesh.characteristic_length)
    else:
        mesh = read_mesh(path, scale=scene.mesh.scale)
        check_organ_scale(mesh, str(path), scene.mesh.scale)
    log.info("mesh: %s", mesh.summary())
    return mesh


#: bounding-box diagonals of a plausible organ [m]: outside, the file's unit is likely not metres
ORGAN_SIZE = (0.005, 3.0)


def check_organ_scale(mesh: TetMesh, what: str, scale: float = 1.0) -> None:
    """Refuse a mesh whose size is no organ's in metres (a file in mm or um without
    ``mesh.scale``), before any FE work would fail to converge on it.

    Args:
        mesh: the mesh, coordinates already multiplied by ``scale``.
        what: the file (for the message).
        scale: the scene's ``mesh.scale``.

    Raises:
        MeshError: naming the bounding box, the mean edge length and the ``mesh.scale``
            (this one times a power of 1000: a unit conversion) that brings the diagonal
            nearest to 0.2 m.
    """
    diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    low, high = ORGAN_SIZE
    if low <= diagonal <= high:
        return
    edge = float(np.mean(np.linalg.norm(mesh.vertices[mesh.edges[:, 1]]
                                        - mesh.vertices[mesh.edges[:, 0]], axis=1)))
    factor = 1000.0 ** round(math.log(0.2 / diagonal, 1000)) if diagonal > 0 else 1.0
    raise MeshError(f"{what}: bounding-box diagonal {diagonal:.4g} m, mean edge length "
                    f"{edge:.4g} m (with mesh.scale = {scale:g}): not an organ's size in "
                    f"metres (expected {low}-{high} m); is the file in other units? set "
                    f"mesh.scale (e.g. mesh.scale = {scale * factor:g})")


def tracked_node_by_rule(mesh: TetMesh, fixed: np.ndarray, rule: str) -> int:
    """The free vertex a gravity comparison tracks, by rule.

    ``farthest_from_support``: farthest from the centroid of the fixed nodes —
    the tip of an overhanging part, which sags and swings the most (the
    paper's "far-right node"). ``max_x``: the free vertex with the largest x.
    """
    free = np.setdiff1d(np.arange(mesh.n_vertices), fixed)
    if rule == "farthest_from_support":
        distance = np.linalg.norm(mesh.vertices[free] - mesh.vertices[fixed].mean(axis=0), axis=1)
        return int(free[np.argmax(distance)])
    if rule == "max_x":
        return int(free[np.argmax(mesh.vertices[free, 0])])
    raise MeshError(f"unknown tracked-node rule {rule!r}")


# a vertex pushed deeper than this fraction of the mean edge length crushes the tets around it
MAX_DEPTH_PER_EDGE = 0.5


def check_depths(scene: Scene, mesh: TetMesh) -> None:
    """Refuse indentation depths that cannot be meant for this mesh (a value in mm, say).

    Raises:
        SceneError: ``indentation.depth`` or ``relaxation.depth`` is not below
            :data:`MAX_DEPTH_PER_EDGE` x the mean edge length.
    """
    edge = float(np.mean(mesh.edge_lengths))
    for name, depth in (("indentation.depth", scene.indentation.depth),
                        ("relaxation.depth", scene.relaxation.depth)):
        if not depth < MAX_DEPTH_PER_EDGE * edge:
            raise SceneError(f"{name} = {depth:g} m is not below {MAX_DEPTH_PER_EDGE:g} x the "
                             f"mesh's mean edge length ({MAX_DEPTH_PER_EDGE:g} x {edge:.3g} = "
                             f"{MAX_DEPTH_PER_EDGE * edge:.3g} m; a vertex pushed deeper "
                             "crushes the tets around it); scene values are in metres "
                             "(5 mm is 0.005)")


def indentable_vertices(scene: Scene, mesh: TetMesh, fixed: np.ndarray) -> np.ndarray | None:
    """The vertices the scene's punch can indent (:func:`forcecal.indenter.punch_candidates`),
    or None for the vertex indenter (any free surface vertex)."""
    if scene.indentation.indenter != "punch":
        return None
    return punch_candidates(mesh, fixed, scene.indentation.radius)


def replacement_point(scene: Scene, problem: Problem, index: int, avoid: set[int]
                      ) -> int | None:
    """The vertex that takes the place of test point ``index`` (of ``problem.test_points``)
    after its FE run failed: the next candidate of the scene's selection rule, or None when
    the points are an explicit list (the point is dropped) or no candidate is left.

    The rules pick points one at a time, each the farthest from those picked before
    (:func:`forcecal.point_selection.select_calibration_points`,
    :func:`~forcecal.point_selection.select_held_out_points`);
    the next candidate continues that sequence: the free surface vertex (one the punch can
    indent, for a punch) farthest from every point picked so far (the failed one and
    ``avoid``, earlier failures, included), along the surface from the clamp and the
    calibration points for ``"auto"`` calibration points, in a straight line from the
    calibration points for ``"cover"`` ones and from every test point for held-out points.
    It is never a current test point nor one of ``avoid``.
    """
    calibration = index < len(problem.calibration)
    tp = scene.test_points
    rule = tp.calibration if calibration else tp.held_out
    if not isinstance(rule, str):
        return None
    mesh = problem.mesh
    taken = np.union1d(problem.test_points, np.fromiter(avoid, np.int64, len(avoid)))
    rest = np.setdiff1d(free_surface_vertices(mesh, problem.fixed), taken)
    indentable = indentable_vertices(scene, mesh, problem.fixed)
    if indentable is not None:
        rest = np.intersect1d(rest, indentable)
    if not len(rest):
        return None
    picked = problem.calibration if calibration else problem.test_points
    if calibration and rule == "auto":  # its sampling starts from the clamp
        picked = np.union1d(picked, problem.fixed)
    sources = np.union1d(picked, np.fromiter(avoid, np.int64, len(avoid)))
    distance = (geodesic_distance if calibration and rule == "auto"
                else euclidean_distance)(mesh, rest)
    return int(farthest_points(distance, rest, 1, sources, "replacement test points")[0])


@dataclass(frozen=True, eq=False)
class SecondSupport:
    """The vertices the second held-out body test clamps (``[second_support]``) and the vertex
    whose release it compares.

    Attributes:
        fixed: (F2,) int64, ids of its clamped vertices (another set than ``problem.fixed``).
        tracked_node: its ``gravity.tracked_node`` (a rule applied to these fixed vertices).
    """
    fixed: np.ndarray
    tracked_node: int


def second_support(scene: Scene, problem: Problem) -> SecondSupport:
    """The scene's second support on ``problem``'s mesh, without the support check (the FE
    and the particle side both take it from here; :func:`check_second_support` refuses one
    that does not hold the body).

    Raises:
        SceneError: naming the ``second_support`` keys: the rule selects too few (or
            collinear, or all) vertices, the same set as ``[fixed]``, or the explicit
            ``gravity.tracked_node`` is one of them.
    """
    rule = _second_support_rule(scene)
    s = scene.second_support
    try:
        fixed = fixed_nodes(problem.mesh, s.axis, s.side, s.tolerance, "second_support")
    except MeshError as exc:
        raise SceneError(str(exc)) from None
    if np.array_equal(np.sort(fixed), np.sort(problem.fixed)):
        raise SceneError(f"{rule} selects the same {len(fixed)} vertices as [fixed]: the second "
                         "held-out body test needs another support (another "
                         "second_support.axis or second_support.side)")
    tracked = scene.gravity.tracked_node
    if isinstance(tracked, str):
        tracked = tracked_node_by_rule(problem.mesh, fixed, tracked)
    elif tracked in set(fixed.tolist()):
        raise SceneError(f"gravity.tracked_node = {tracked} is clamped by {rule}: the second "
                         "support's release would track a vertex that cannot move; track a "
                         "free vertex of both supports or use a rule")
    return SecondSupport(fixed, int(tracked))


def check_second_support(scene: Scene, problem: Problem) -> SecondSupport:
    """:func:`second_support`, refused unless it holds the body under the scene's gravity
    (:func:`forcecal.preflight.check_support`, the first support's linear check: no motion
    that costs no energy, a linear sag below :data:`~forcecal.preflight.SAG_LIMIT` x the
    body's size). Seconds on the meshes of the scenes (a sparse factorisation).

    Raises:
        SceneError: naming the ``second_support`` keys and what the check found.
    """
    from forcecal.preflight import SAG_LIMIT, check_support

    support = second_support(scene, problem)
    rule = _second_support_rule(scene)
    check = check_support(problem.mesh, support.fixed, scene.material,
                          scene.gravity.acceleration)
    if check.rigid_modes:
        raise SceneError(f"{rule} does not hold the body: with its {len(support.fixed)} "
                         f"vertices clamped, {check.rigid_modes} motion(s) cost no energy "
                         f"(they move {len(check.free_vertices)} vertices, e.g. "
                         f"{check.free_vertices[:10].tolist()}); clamp a larger patch "
                         "(second_support.tolerance) or another side")
    if not check.holds:
        raise SceneError(f"{rule} does not hold the body under its weight: the linear sag of "
                         f"its {len(support.fixed)} clamped vertices is {check.sag_m * 1e3:.4g} "
                         f"mm at vertex {check.sag_vertex}, more than {SAG_LIMIT:g} x the "
                         f"body's size {check.body_size_m * 1e3:.3g} mm; clamp a larger patch "
                         "(second_support.tolerance) or another side")
    log.info("%s: %d vertices clamped, linear sag %.3g mm, tracked node %d", rule,
             len(support.fixed), check.sag_m * 1e3, support.tracked_node)
    return support


def _second_support_rule(scene: Scene) -> str:
    s = scene.second_support
    return f"second_support (axis {s.axis!r}, side {s.side!r}, tolerance {s.tolerance} m)"


def build_problem(scene: Scene, mesh: TetMesh | None = None) -> Problem:
    """Mesh + fixed nodes + test points of a scene, validated.

    Raises:
        MeshError: the fixed-node rule or the test points do not suit the mesh.
        SceneError: an indentation depth implausible for the mesh, or an explicit
            ``held_out`` list shorter than :data:`~forcecal.scene.MIN_HELD_OUT`.
    """
    mesh = load_mesh(scene) if mesh is None else mesh
    check_depths(scene, mesh)
    f = scene.fixed
    fixed = fixed_nodes(mesh, f.axis, f.side, f.tolerance)
    tp = scene.test_points
    # a punch near the clamp would hold clamped vertices: the "auto" rules pick among the
    # vertices a punch of the scene's radius can indent ("cover", the paper's, stays as it is)
    auto = "auto" in (tp.calibration, tp.held_out)
    candidates = indentable_vertices(scene, mesh, fixed) if auto else None
    if isinstance(tp.calibration, str):
        calibration = select_calibration_points(
            mesh, fixed, tp.n_calibration, tp.calibration,
            candidates if tp.calibration == "auto" else None)
    else:
        calibration = validate_test_points(mesh, fixed, np.array(tp.calibration), "calibration")
    if isinstance(tp.held_out, str):
        held_out = select_held_out_points(mesh, fixed, calibration, tp.n_held_out, candidates)
    else:
        held_out = validate_test_points(mesh, fixed, np.array(tp.held_out), "held_out")
        if len(held_out) < MIN_HELD_OUT:
            raise SceneError(f"test_points.held_out lists {len(held_out)} vertices; at least "
                             f"{MIN_HELD_OUT} held-out points are needed (they give the "
                             "accuracy no fit has seen)")
    both = np.intersect1d(calibration, held_out)
    if len(both):
        raise MeshError(f"test points {both.tolist()} are both calibration and held-out points")
    tracked = scene.gravity.tracked_node
    if isinstance(tracked, str):
        tracked = tracked_node_by_rule(mesh, fixed, tracked)
    elif not 0 <= tracked < mesh.n_vertices or tracked in set(fixed.tolist()):
        raise MeshError(f"gravity.tracked_node = {tracked} is not a free vertex of the mesh")
    problem = Problem(mesh=mesh, fixed=fixed, calibration=calibration, held_out=held_out,
                      tracked_node=int(tracked))
    _ = problem.normals  # surface check of every test point
    covered = problem.coverage
    log.info("problem: %d fixed nodes, %d calibration + %d held-out test points, tracked node %d; "
             "the calibration points cover %.0f %% of the free surface (%s, a point or an edge "
             "neighbour of one), the held-out points %.0f %%", len(fixed), len(calibration),
             len(held_out), tracked, 100 * covered["calibration"],
             tp.calibration if isinstance(tp.calibration, str) else "listed",
             100 * covered["held_out"])
    return problem


def body_load_directions(acceleration: np.ndarray) -> np.ndarray:
    """(2, 3) unit vectors perpendicular to ``acceleration`` and to each other: the directions
    of the whole-body loads (experiment ``body``), which the gravity test does not use. The
    coordinate axis least aligned with gravity, gravity projected out, then gravity's
    direction crossed with it (for gravity along a coordinate axis: the other two axes,
    pointing the positive way)."""
    g = np.asarray(acceleration, dtype=np.float64)
    g = g / np.linalg.norm(g)
    first = np.eye(3)[int(np.argmin(np.abs(g)))]
    first = first - (first @ g) * g
    first /= np.linalg.norm(first)
    second = np.cross(g, first)
    if np.count_nonzero(np.abs(second) > 1e-12) == 1:  # an axis: point it the positive way
        second = np.abs(second)
    return np.stack([first, second / np.linalg.norm(second)])
