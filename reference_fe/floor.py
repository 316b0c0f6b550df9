"""The discretisation floor (experiment ``floor``): the gravity test of a vertex-only FE model.

A particle model has one particle per mesh vertex. The best such a model can do with the
true material is a finite-element model whose only displacement unknowns are the vertex
displacements of the same mesh: linear (P1) tetrahedra. Plain P1 tets lock in a nearly
incompressible body (one volume constraint per tet, about three tets per vertex), so the
floor is computed with the locking-free vertex-dof element ANP (average nodal pressure,
:func:`reference_fe.model.pressure_compliance`) and, for comparison, with plain P1 (so the
locking is visible). Both run the scene's gravity test exactly as the reference's
(:func:`~reference_fe.experiments.gravity_static`,
:func:`~reference_fe.experiments.gravity_dynamic`: same material, Prony terms, support,
load steps and time step) on the particle mesh itself, whatever ``fe.element`` and
``fe.refine`` the reference uses; the report measures them against the reference with the
calibrated model's metrics (:func:`pipelines.report.floor_block`).

The quadrature degree is :data:`QUADRATURE_DEGREE`: on straight P1 tets the deformation
gradient is constant and the pressure and displacement linear, so degree 2 integrates every
term of the residual (the mass term ``u . v`` is the highest, quadratic) exactly.

A run that fails (Newton, an unstable support) is recorded with its reason in place of its
arrays; the floor is information, it stops nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from forcecal.errors import ConvergenceError, StabilityError
from forcecal.h5io import FLOOR_ELEMENTS, FloorResult, GravityResult
from forcecal.problem import Problem
from forcecal.scene import GravitySection, Scene
from reference_fe import experiments
from reference_fe.model import FEModel

log = logging.getLogger(__name__)

#: the floor's elements: the locking-free one (the floor) first, plain P1 next to it
ELEMENTS = FLOOR_ELEMENTS
#: exact for every term of a P1 element's residual on straight tets (module docstring)
QUADRATURE_DEGREE = 2


def floor_runs(scene: Scene, problem: Problem, element: str) -> dict[str, np.ndarray | str]:
    """The gravity test of ``element`` on the particle mesh: ``static_displacement`` (N, 3)
    [m], ``time`` (S,) [s], ``displacement`` (S, N, 3) [m] and ``seconds`` (compute time,
    model build included); or ``failed`` (the reason) and ``seconds`` if a run failed."""
    start = time.perf_counter()
    fe = dataclasses.replace(scene.fe, element=element, refine=0, local_refine=0,
                             quadrature_degree=QUADRATURE_DEGREE)
    g = scene.gravity
    try:
        model = FEModel(problem.mesh, scene.material, fe)
        static = experiments.gravity_static(model, problem.fixed, g.acceleration,
                                            g.static_load_steps)
        times, displacement = experiments.gravity_dynamic(model, problem.fixed, g.acceleration,
                                                          g.duration, g.fe_dt, g.record_interval)
    except (ConvergenceError, StabilityError) as exc:
        log.warning("discretisation floor, %s: %s", element, exc)
        return {"failed": f"{type(exc).__name__}: {exc}",
                "seconds": time.perf_counter() - start}
    seconds = time.perf_counter() - start
    log.info("discretisation floor, %s: %d dofs, max static sag %.4g mm, %.1f s", element,
             model.n_dofs, 1e3 * float(np.linalg.norm(static, axis=1).max()), seconds)
    return {"static_displacement": static, "time": times, "displacement": displacement,
            "seconds": seconds}


def floor_arrays(scene: Scene, problem: Problem) -> dict[str, np.ndarray]:
    """The arrays of the ``floor`` work item (one checkpoint part): for each element ``e`` of
    :data:`ELEMENTS`, ``e_static_displacement``, ``e_time``, ``e_displacement`` and
    ``e_seconds`` (:func:`floor_runs`), or ``e_failed`` (the reason, a string array) and
    ``e_seconds``."""
    out: dict[str, np.ndarray] = {}
    for element in ELEMENTS:
        for name, value in floor_runs(scene, problem, element).items():
            out[f"{element}_{name}"] = np.asarray(value)
    return out


def result_of(arrays: dict[str, np.ndarray], settings: GravitySection) -> FloorResult:
    """The :class:`~forcecal.h5io.FloorResult` of the work item's arrays (:func:`floor_arrays`);
    ``settings`` the scene's ``[gravity]`` with the reference's tracked node."""
    runs, failed, seconds = {}, {}, {}
    for element in ELEMENTS:
        if f"{element}_seconds" not in arrays:
            continue
        seconds[element] = float(arrays[f"{element}_seconds"])
        if f"{element}_failed" in arrays:
            failed[element] = str(arrays[f"{element}_failed"])
            continue
        runs[element] = GravityResult(arrays[f"{element}_static_displacement"],
                                      arrays[f"{element}_time"],
                                      arrays[f"{element}_displacement"], settings)
    return FloorResult(runs, failed, seconds, QUADRATURE_DEGREE)


def arrays_of(result: FloorResult) -> dict[str, np.ndarray]:
    """A stored :class:`~forcecal.h5io.FloorResult` as the work item's arrays (:func:`result_of`'s
    inverse)."""
    out: dict[str, np.ndarray] = {}
    for element in result.elements:
        out[f"{element}_seconds"] = np.asarray(result.seconds.get(element, 0.0))
        if element in result.failed:
            out[f"{element}_failed"] = np.asarray(result.failed[element])
            continue
        runs = result.runs[element]
        out.update({f"{element}_static_displacement": runs.static_displacement,
                    f"{element}_time": runs.time, f"{element}_displacement": runs.displacement})
    return out
