"""How far a scene's experiments strain the connectors, known before any FE work.

The particle model's initial tangent is exactly the linear connector network
(:mod:`calibration.network`), so one sparse solve per test point gives every connector's
strain per unit depth. Times the deepest indentation and ``calibration.strain_margin`` it
is the range on which the calibration keeps every spring stiff (:class:`StrainRange`). A
depth at which that estimate compresses some connector by 100 % or more (its length would
vanish) is refused: the calibration could not fit a spring law on it. The check needs the
mesh, the test points and the indenter only, so the pipeline makes it before the FE
reference (:func:`check_experiment_depths`), with the key to change and the largest depth
the mesh accepts, instead of after minutes of FE work.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from calibration.network import LinearIndentation, linear_indentation
from calibration.parametrisation import StrainRange, global_shape
from forcecal.errors import ParameterError, SceneError
from forcecal.indenter import indenter_footprints
from forcecal.problem import Problem, build_problem
from forcecal.scene import Scene


def experiment_depths(scene: Scene) -> dict[str, float]:
    """The deepest indentation [m] of each experiment the calibration fits, by scene key."""
    depths = {"indentation.depth": scene.indentation.depth}
    if scene.runs("relaxation"):
        depths["relaxation.depth"] = scene.relaxation.depth
    return depths


def largest_depth(strain_per_depth: np.ndarray, margin: float) -> float:
    """The depth [m] at which the linear estimate x ``margin`` compresses the most compressed
    connector by 100 % (``strain_per_depth`` (P, E) [1/m]); depths must stay below it."""
    return 1.0 / (margin * max(-float(np.min(strain_per_depth)), 1e-300))


def strain_range(strain_per_depth: np.ndarray, depth: float, margin: float) -> StrainRange:
    """Strains of the experiments (linear network at the deepest indentation ``depth`` [m])
    times ``margin``; :class:`ParameterError` where they collapse a connector."""
    low = float(strain_per_depth.min()) * depth * margin
    high = float(strain_per_depth.max()) * depth * margin
    if not (-1.0 < low < 0.0 < high):
        raise ParameterError(f"indenting {depth} m compresses connectors by {-low:.3g} "
                             f"(linear estimate x margin {margin}); the depth is too large for "
                             "the mesh (connectors would collapse)")
    return StrainRange(low, high)


@dataclass(frozen=True, eq=False)
class Reach:
    """The linear network's response at the test points and the strain range it implies.

    Attributes:
        linear: slopes and strains per unit depth of the network with the global shape's
            stiffnesses (:func:`calibration.network.linear_indentation`).
        strain: the experiments' strain range (:func:`strain_range`).
    """
    linear: LinearIndentation
    strain: StrainRange


def experiment_reach(scene: Scene, problem: Problem, shape: np.ndarray | None,
                     footprints: Sequence[np.ndarray] | None) -> Reach:
    """The scene's :class:`Reach` on ``problem`` (``shape``: the global set's (E,) factors or
    None; ``footprints``: the punch's held particles per test point or None).

    Raises:
        SceneError: a depth at which the linear estimate collapses a connector, naming the
            key(s) to change and the largest depth the mesh accepts.
    """
    mesh = problem.mesh
    linear = linear_indentation(mesh, problem.fixed, problem.test_points, problem.normals,
                                stiffness=shape, footprints=footprints)
    margin = scene.calibration.strain_margin
    depths = experiment_depths(scene)
    limit = largest_depth(linear.strain, margin)
    too_deep = {key: d for key, d in depths.items() if not d < limit}
    if too_deep:
        point, connector = np.unravel_index(int(np.argmin(linear.strain)), linear.strain.shape)
        a, b = mesh.edges[connector]
        deepest = max(too_deep.values())
        raise SceneError(
            f"{' and '.join(f'{k} = {d:g} m' for k, d in too_deep.items())}: indenting "
            f"{deepest:g} m compresses connectors by "
            f"{-float(np.min(linear.strain)) * deepest * margin:.3g} (linear estimate of the "
            f"connector network x calibration.strain_margin {margin:g}; connector {a}-{b}, "
            f"{mesh.edge_lengths[connector]:.3g} m long, at test point "
            f"{int(problem.test_points[point])}): they would collapse. Set "
            f"{' and '.join(too_deep)} below {limit:.3g} m, the largest depth this mesh "
            "accepts")
    return Reach(linear, strain_range(linear.strain, max(depths.values()), margin))


def _scene_indenter(scene: Scene, problem: Problem) -> tuple[np.ndarray | None,
                                                             Sequence[np.ndarray] | None]:
    """The calibration's global shape and the indenter's footprints on ``problem``."""
    mesh = problem.mesh
    footprints = (None if scene.indentation.indenter == "vertex" else indenter_footprints(
        mesh, problem.fixed, problem.test_points, problem.normals, scene.indentation.indenter,
        scene.indentation.radius))
    return global_shape(mesh, scene.calibration.global_shape), footprints


def check_experiment_depths(scene: Scene, problem: Problem | None = None) -> Reach:
    """:func:`experiment_reach` with the calibration's global shape and indenter, for a scene
    whose FE reference has not been computed (the pipeline's first stage)."""
    problem = build_problem(scene) if problem is None else problem
    return experiment_reach(scene, problem, *_scene_indenter(scene, problem))


def accepted_depth(scene: Scene, problem: Problem | None = None) -> float:
    """The largest depth [m] :func:`check_experiment_depths` accepts for the scene's mesh,
    test points and indenter (depths must stay below it)."""
    problem = build_problem(scene) if problem is None else problem
    shape, footprints = _scene_indenter(scene, problem)
    linear = linear_indentation(problem.mesh, problem.fixed, problem.test_points,
                                problem.normals, stiffness=shape, footprints=footprints)
    return largest_depth(linear.strain, scene.calibration.strain_margin)
