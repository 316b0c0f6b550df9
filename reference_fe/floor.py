"""The discretisation floor (experiment ``floor``): the reference's tests of a vertex-only FE model.

A particle model has one particle per mesh vertex. The best such a model can do with the
true material is a finite-element model whose only displacement unknowns are the vertex
displacements of the same mesh: linear (P1) tetrahedra. Plain P1 tets lock in a nearly
incompressible body (one volume constraint per tet, about three tets per vertex), so the
floor is computed with the locking-free vertex-dof element ANP (average nodal pressure,
:func:`reference_fe.model.pressure_compliance`) and, for comparison, with plain P1 (so the
locking is visible). Both run, on the particle mesh itself whatever ``fe.element``,
``fe.refine`` and ``fe.local_refine`` the reference uses, the reference's own work items
(:func:`reference_fe.run.compute_item`: same material, Prony terms, supports, load steps,
time step, indenter, depths and schedules):

* the scene's gravity test (static sag and release);
* with the experiment ``second_support`` asked for too, the second support's test
  (:func:`reference_fe.run.second_support_runs`);
* the indentation and relaxation curves of the held-out test points only (the calibration
  points' would cost more and say the same). A punch holds the particle footprint's vertices,
  as the particle model's punch does; the reference runs each punch on a mesh refined near its
  rim (``fe.local_refine``), the floor on the particle mesh, unrefined.

The report measures them against the reference with the calibrated model's metrics
(:func:`pipelines.report.floor_block`).

The quadrature degree is :data:`QUADRATURE_DEGREE`: on straight P1 tets the deformation
gradient is constant and the pressure and displacement linear, so degree 2 integrates every
term of the residual (the mass term ``u . v`` is the highest, quadratic) exactly.

A run that fails (Newton, an unstable support) is recorded with its reason in place of its
arrays (a held-out point's: NaN rows and the reason); the floor is information, it stops
nothing.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time

import numpy as np

from forcecal.cost import FLOOR_SOLVE_FRACTION, n_held_out
from forcecal.errors import ConvergenceError, SceneError, StabilityError
from forcecal.h5io import FLOOR_ELEMENTS, FloorResult, GravityResult, HeldOutCurves
from forcecal.problem import Problem
from forcecal.scene import FESection, GravitySection, Scene
from forcecal.schedules import indentation_depths, relaxation_schedule
from reference_fe.model import FEModel

log = logging.getLogger(__name__)

#: the floor's elements: the locking-free one (the floor) first, plain P1 next to it
ELEMENTS = FLOOR_ELEMENTS
#: exact for every term of a P1 element's residual on straight tets (module docstring)
QUADRATURE_DEGREE = 2
#: a floor run fails with these and is recorded (anything else stops the reference)
RUN_FAILURES = (ConvergenceError, StabilityError)
#: the held-out curves' experiments, in the order they run at each point
CURVES = ("indentation", "relaxation")


def floor_fe(scene: Scene, element: str) -> FESection:
    """The ``[fe]`` of floor element ``element``: the scene's Newton settings, on the particle
    mesh (no refinement, none near a punch), degree :data:`QUADRATURE_DEGREE`."""
    return dataclasses.replace(scene.fe, element=element, refine=0, local_refine=0,
                               quadrature_degree=QUADRATURE_DEGREE)


def item_cost(scene: Scene, gravity_solves: float, point_solves: float) -> float:
    """Estimated Newton solves of the ``floor`` work item, in the reference's units (those of a
    reference solve: ``FLOOR_SOLVE_FRACTION``), for every element: the gravity test
    (``gravity_solves``), the second support's (as many, when asked for) and the held-out
    points' curves (``point_solves`` each)."""
    tests = 2.0 if "second_support" in scene.experiments else 1.0
    return FLOOR_SOLVE_FRACTION * len(ELEMENTS) * (tests * gravity_solves
                                             + n_held_out(scene) * point_solves)


def held_out_forces(model: FEModel, scene: Scene, problem: Problem) -> dict[str, np.ndarray]:
    """The held-out test points' curves (experiments of :data:`CURVES` the scene runs) as the
    reference computes them (:func:`reference_fe.run.compute_item` with ``scene``'s ``[fe]``,
    which must not refine: ``model`` is on the particle mesh): ``vertices`` (H,) and
    ``<experiment>_force`` (H, S, 3) [N], NaN rows (of every experiment) at a point whose
    curve failed and ``failed`` (JSON {vertex: reason}). A point whose first curve failed skips
    the other.

    Raises:
        SceneError: ``scene.fe.refine`` is not 0.
    """
    from reference_fe.run import WorkItem, compute_item  # run.py runs the floor: no cycle at load

    if scene.fe.refine:
        raise SceneError(f"fe.refine = {scene.fe.refine}: the held-out curves of the floor run "
                         "on the particle mesh")
    first = len(problem.calibration)
    kinds = [k for k in CURVES if k in scene.experiments]
    rows: dict[str, list[np.ndarray | None]] = {k: [] for k in kinds}
    failed: dict[str, str] = {}
    for slot, vertex in enumerate(problem.held_out.tolist(), start=first):
        for kind in kinds:
            force = None
            if str(vertex) not in failed:
                try:
                    force = compute_item(model, scene, problem, WorkItem(kind, slot, 0.0))["force"]
                except RUN_FAILURES as exc:
                    failed[str(vertex)] = f"{kind}: {type(exc).__name__}: {exc}"
                    log.warning("discretisation floor, %s, held-out vertex %d: %s",
                                scene.fe.element, vertex, exc)
            rows[kind].append(force)
    samples = {"indentation": len(indentation_depths(scene.indentation)),
               "relaxation": len(relaxation_schedule(scene.relaxation)[0])}
    out = {"vertices": problem.held_out.astype(np.int64), "failed": np.asarray(json.dumps(failed))}
    for kind, forces in rows.items():
        out[f"{kind}_force"] = np.stack([
            np.full((samples[kind], 3), np.nan) if f is None or str(v) in failed else f
            for v, f in zip(problem.held_out.tolist(), forces)])
    return out


def element_arrays(scene: Scene, problem: Problem, fe: FESection) -> dict[str, np.ndarray]:
    """Every run of one element ``fe`` on the particle mesh (module docstring): the gravity
    test's arrays (:func:`reference_fe.run.gravity_test`) or ``failed`` (the reason), with the
    second support ``second_support_`` + the same (or ``second_support_failed``),
    ``held_out_`` + the arrays of :func:`held_out_forces`, and ``seconds`` (compute time, model
    build included) and ``part_seconds`` (JSON, :data:`~forcecal.h5io.FLOOR_PARTS`)."""
    from reference_fe.run import gravity_test, second_support_runs
    from reference_fe.refine import FEProblem

    run_scene = dataclasses.replace(scene, fe=fe)
    parts: dict[str, float] = {}
    out: dict[str, np.ndarray] = {}
    start = time.perf_counter()
    model = FEModel(problem.mesh, scene.material, fe)
    parts["build"] = time.perf_counter() - start

    def part(name: str, run, prefix: str = "") -> None:
        t0 = time.perf_counter()
        try:
            out.update({prefix + k: np.asarray(v) for k, v in run().items()})
        except RUN_FAILURES as exc:
            log.warning("discretisation floor, %s, %s: %s", fe.element, name, exc)
            out[prefix + "failed"] = np.asarray(f"{type(exc).__name__}: {exc}")
        parts[name] = time.perf_counter() - t0

    try:
        part("gravity", lambda: gravity_test(model, scene, problem.fixed,
                                             np.arange(problem.mesh.n_vertices)))
        if "second_support" in scene.experiments:
            identity = FEProblem(problem, np.arange(problem.mesh.n_vertices), 0)
            part("second_support",
                 lambda: second_support_runs(model, run_scene, problem, identity),
                 "second_support_")
        t0 = time.perf_counter()
        out.update({f"held_out_{k}": v for k, v in held_out_forces(model, run_scene,
                                                                    problem).items()})
        parts["held_out"] = time.perf_counter() - t0
        n_dofs = model.n_dofs
    finally:
        model.destroy()  # its memory now: the rank goes on with other items (FEModel.destroy)
    out["seconds"] = np.asarray(time.perf_counter() - start)
    out["part_seconds"] = np.asarray(json.dumps(parts))
    log.info("discretisation floor, %s: %d dofs, %s", fe.element, n_dofs,
             ", ".join(f"{k} {v:.1f} s" for k, v in parts.items()))
    return out


def floor_arrays(scene: Scene, problem: Problem) -> dict[str, np.ndarray]:
    """The arrays of the ``floor`` work item (one checkpoint part): for each element ``e`` of
    :data:`ELEMENTS`, ``e_`` + its :func:`element_arrays`, and ``second_support_tracked_node``
    when the scene runs the second support."""
    from forcecal.problem import second_support

    out: dict[str, np.ndarray] = {}
    if "second_support" in scene.experiments:
        out["second_support_tracked_node"] = np.asarray(
            second_support(scene, problem).tracked_node)
    for element in ELEMENTS:
        for name, value in element_arrays(scene, problem, floor_fe(scene, element)).items():
            out[f"{element}_{name}"] = value
    return out


def runs_of(arrays: dict[str, np.ndarray], prefix: str, settings: GravitySection
            ) -> GravityResult:
    """The :class:`~forcecal.h5io.GravityResult` of :func:`reference_fe.run.gravity_test`'s
    arrays (keys after ``prefix``), ``settings`` the ``[gravity]`` with the run's tracked
    node."""
    return GravityResult(arrays[f"{prefix}static_displacement"], arrays[f"{prefix}time"],
                         arrays[f"{prefix}displacement"], settings)


def curves_of(arrays: dict[str, np.ndarray], prefix: str = "") -> HeldOutCurves:
    """The :class:`~forcecal.h5io.HeldOutCurves` of :func:`held_out_forces`' arrays (keys
    after ``prefix``)."""
    relaxation = arrays.get(f"{prefix}relaxation_force")
    return HeldOutCurves(np.asarray(arrays[f"{prefix}vertices"], dtype=np.int64),
                         np.asarray(arrays[f"{prefix}indentation_force"], dtype=float),
                         None if relaxation is None else np.asarray(relaxation, dtype=float),
                         {int(v): r for v, r in json.loads(str(arrays[f"{prefix}failed"])).items()})


def result_of(arrays: dict[str, np.ndarray], settings: GravitySection) -> FloorResult:
    """The :class:`~forcecal.h5io.FloorResult` of the work item's arrays (:func:`floor_arrays`);
    ``settings`` the scene's ``[gravity]`` with the reference's tracked node."""
    runs, failed, seconds, parts = {}, {}, {}, {}
    support, support_failed, held_out = {}, {}, {}
    support_settings = None
    if "second_support_tracked_node" in arrays:
        support_settings = dataclasses.replace(
            settings, tracked_node=int(arrays["second_support_tracked_node"]))
    for element in ELEMENTS:
        e = f"{element}_"
        if f"{e}seconds" not in arrays:
            continue
        seconds[element] = float(arrays[f"{e}seconds"])
        parts[element] = json.loads(str(arrays.get(f"{e}part_seconds", "{}")))
        if f"{e}failed" in arrays:
            failed[element] = str(arrays[f"{e}failed"])
        else:
            runs[element] = runs_of(arrays, e, settings)
        if f"{e}second_support_failed" in arrays:
            support_failed[element] = str(arrays[f"{e}second_support_failed"])
        elif f"{e}second_support_time" in arrays:
            support[element] = runs_of(arrays, f"{e}second_support_", support_settings)
        if f"{e}held_out_vertices" in arrays:
            held_out[element] = curves_of(arrays, f"{e}held_out_")
    return FloorResult(runs, failed, seconds, QUADRATURE_DEGREE, support, support_failed,
                       held_out, parts)


def arrays_of(result: FloorResult) -> dict[str, np.ndarray]:
    """A stored :class:`~forcecal.h5io.FloorResult` as the work item's arrays (:func:`result_of`'s
    inverse)."""
    out: dict[str, np.ndarray] = {}
    if result.second_support:
        out["second_support_tracked_node"] = np.asarray(
            next(iter(result.second_support.values())).tracked_node)

    def put_runs(prefix: str, runs: GravityResult) -> None:
        out.update({f"{prefix}static_displacement": runs.static_displacement,
                    f"{prefix}time": runs.time, f"{prefix}displacement": runs.displacement})

    for element in result.elements:
        e = f"{element}_"
        out[f"{e}seconds"] = np.asarray(result.seconds.get(element, 0.0))
        out[f"{e}part_seconds"] = np.asarray(json.dumps(result.part_seconds.get(element, {})))
        if element in result.failed:
            out[f"{e}failed"] = np.asarray(result.failed[element])
        else:
            put_runs(e, result.runs[element])
        if element in result.second_support_failed:
            out[f"{e}second_support_failed"] = np.asarray(result.second_support_failed[element])
        elif element in result.second_support:
            put_runs(f"{e}second_support_", result.second_support[element])
        curves = result.held_out.get(element)
        if curves is not None:
            out.update({f"{e}held_out_vertices": curves.vertices,
                        f"{e}held_out_indentation_force": curves.indentation,
                        f"{e}held_out_failed": np.asarray(json.dumps(
                            {str(v): r for v, r in curves.failed.items()}))})
            if curves.relaxation is not None:
                out[f"{e}held_out_relaxation_force"] = curves.relaxation
    return out
