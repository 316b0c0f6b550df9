"""``report.json``: every error of the run against the FE reference, timings and versions.

Errors (all dimensionless):

* curve errors are the relative RMS error ``RMS(F_sim - F_ref) / max|F_ref|``
  of the normal force of each test point
  (:func:`calibration.metrics.relative_rms_error`), averaged over a point set:
  ``*_global`` and ``*_calibrated`` over the calibration points (global-only and
  global + local models), ``*_held_out`` over the held-out points with the
  calibrated model;
* ``gravity_static``: mean over the free vertices of ``|u_particle - u_FE|``
  divided by the largest FE sag ``max |u_FE|`` (fixed vertices, zero on both
  sides, are left out so they do not dilute the mean);
* ``gravity_dynamic``: RMS over the sample times of ``|u_p(t) - u_FE(t)|`` of the
  tracked vertex divided by ``max_t |u_FE(t)|``.

``force_vector_errors`` measures the whole indenter force, the tangential reaction a
bonded indenter (and a haptic tool) also feels: for the calibrated and the baseline model
the curve keys of ``errors`` with the relative RMS error of the force vector
(``RMS |F_sim - F_ref| / max|F_ref . n|``, the normal curve's scale), and under
``<model>_tangential`` of its tangential part alone
(:func:`calibration.metrics.force_vector_errors`); null (with a warning) for a
``params.h5`` written before it stored the force vectors.

``gravity.dynamic_metrics`` separates the tracked vertex's dynamic error into
period, first-peak displacement and decay rate errors (:mod:`pipelines.dynamics`),
for the calibrated and the baseline model, next to the RMS error, and identifies the
modes that carry the release (``modes``, ``mode_frequency_errors``).

``baseline_errors`` repeats every key with the closed-form (Van Gelder) model,
which is the same model on every point set ("global", "calibrated" and
"held_out" only select the points).

Experiments the scene does not run (its ``experiments`` list) keep their keys
with ``null``; ``not_run`` maps each such experiment to the reason, and
``experiments`` lists those that ran. The gravity timings are ``null`` without
any gravity experiment, and so is the ``gravity`` block.

A particle model that failed a validation experiment (:mod:`calibration.validation`) is
listed in ``failures`` (model, experiment, point, role, what it reached, the reason); its
errors are the means over the points it completed (``null`` when it completed none, and its
``per_point_errors`` are ``null`` at the points it failed), and a model whose static sag
failed has ``null`` gravity errors (its release did not run). ``verdict`` judges the
calibrated model's checks against the scene's ``[verdict]`` goals (:mod:`pipelines.verdict`)
and ``realtime`` its haptic cost on the mesh (:mod:`pipelines.realtime`).
``fe_failures`` and ``mesh_preflight`` repeat what the FE stage recorded in
``reference.h5`` (:mod:`forcecal.fe_failures`: test points replaced or dropped, a failed
FE gravity test, which is then the reason in ``not_run``; :mod:`forcecal.preflight`).

``second_support`` (null unless the scene's experiments include ``second_support``) is the
second held-out body test: the gravity test with the ``[second_support]`` vertices clamped
instead of ``[fixed]``'s, the FE against the calibrated and the baseline model
(:func:`second_support_block`); no fit and no choice sees it. A model that fails it is in
``failures`` (``second_support_static``, ``second_support_dynamic``), a failed FE test in
``fe_failures.second_support`` and ``not_run``.

``discretisation_floor`` (null unless the scene's experiments include ``floor``) is the
discretisation floor (:func:`floor_block`): the gravity test, the second-support test (when the
scene runs it) and the held-out points' force curves computed by FE elements whose only
displacement dofs are the particle mesh's vertices, with the true material (locking-free ANP
and plain P1, :mod:`reference_fe.floor`), measured against the reference with the calibrated
model's metrics, next to the calibrated and the baseline model's. It is information, not a
check: the verdict does not read it.

``strain_ranges`` says where the fitted spring laws hold (:func:`strain_ranges`): the
connector strains the calibration points' curves reached, against those of each held-out
point; a held-out point beyond them is judged on an extrapolated spring law, and the
verdict's held-out checks say so.
"""

from __future__ import annotations

import json
import logging
import platform
from pathlib import Path
from typing import Any

import numpy as np

import forcecal
from calibration.metrics import force_vector_errors, relative_rms_error
from calibration.results import CalibrationResult
from calibration.validation import per_completed_point
from forcecal.errors import DataFileError
from forcecal.h5io import (FLOOR_ELEMENTS, FloorResult, GravityResult, HeldOutCurves, Reference,
                           SecondSupportResult, atomic_path)
from forcecal.problem import Problem
from forcecal.provenance import git_commit
from forcecal.scene import EXPERIMENTS as ALL_EXPERIMENTS, GRAVITY_EXPERIMENTS, VerdictSection
from particle.evaluators import normal_force
from pipelines.dynamics import dynamic_metrics, release_modes
from pipelines.gravity import GravityRuns, GravityTest, SupportRuns
from pipelines.verdict import CHECKS, NOT_ASKED, OPT_IN, STATUSES, judge, measurements

log = logging.getLogger(__name__)

ERROR_KEYS = ("indentation_global", "indentation_calibrated", "indentation_held_out",
              "relaxation_global", "relaxation_calibrated", "relaxation_held_out",
              "gravity_static", "gravity_dynamic")
# the params.h5 variant each point set of a model's errors is evaluated on
CALIBRATED_VARIANTS = {"global": "global", "calibrated": "calibrated", "held_out": "calibrated"}
BASELINE_VARIANTS = dict.fromkeys(("global", "calibrated", "held_out"), "baseline")
CURVE_KEYS = ERROR_KEYS[:6]  # the test points' curves (the force_vector_errors keys)
TIMING_KEYS = ("mesh", "reference", "calibration", "gravity_particle", "gravity_fe")


def curve_errors(reference: Reference, calibration: CalibrationResult, variant: str,
                 experiment: str) -> np.ndarray:
    """(P,) relative RMS error of every test point's normal-force curve for one model variant
    (NaN at a point it failed)."""
    ref = getattr(reference, experiment).force_normal
    sim = calibration.variants[variant].curves[experiment]
    if sim.shape != ref.shape:
        raise DataFileError(f"params.h5 {variant} {experiment} curves have shape {sim.shape}, "
                            f"the reference {ref.shape}; rerun the calibration")
    return per_completed_point(relative_rms_error, sim, ref)


def gravity_static_error(fe: np.ndarray, particle: np.ndarray, free: np.ndarray) -> float:
    """Mean over free vertices of ``|u_p - u_FE|`` / ``max |u_FE|`` (displacements (N, 3) [m])."""
    scale = float(np.linalg.norm(fe, axis=1).max())
    if scale == 0.0:
        raise DataFileError("the FE static sag is zero everywhere; no scale to compare against")
    return float(np.linalg.norm(particle - fe, axis=1)[free].mean() / scale)


def gravity_dynamic_error(fe: np.ndarray, particle: np.ndarray) -> float:
    """RMS over time of ``|u_p(t) - u_FE(t)|`` / ``max_t |u_FE(t)|`` (histories (S, 3) [m])."""
    scale = float(np.linalg.norm(fe, axis=1).max())
    if scale == 0.0:
        raise DataFileError("the FE displacement of the tracked node is zero at every sample")
    return float(np.sqrt(np.mean(np.sum((particle - fe) ** 2, axis=1))) / scale)


def vector_errors(reference: Reference, calibration: CalibrationResult,
                  variants: dict[str, str]) -> tuple[dict[str, float | None],
                                                     dict[str, float | None]] | None:
    """(vector, tangential) errors of one model: the curve keys of :data:`ERROR_KEYS` (None for
    experiments not fitted); ``variants`` as for :func:`model_errors`. None if a variant's
    force vectors are not in ``params.h5``."""
    if any(calibration.variants[v].forces is None for v in variants.values()):
        return None
    cal = calibration.is_calibration
    vector: dict[str, float | None] = dict.fromkeys(CURVE_KEYS)
    tangential: dict[str, float | None] = dict.fromkeys(CURVE_KEYS)
    for experiment in calibration.experiments:
        ref = getattr(reference, experiment).force
        per_variant = {}  # (vector, tangential) (P,) errors of each variant, once
        for variant in set(variants.values()):
            sim = calibration.variants[variant].forces[experiment]
            if sim.shape != ref.shape:
                raise DataFileError(f"params.h5 {variant} {experiment} force vectors have "
                                    f"shape {sim.shape}, the reference {ref.shape}; rerun the "
                                    "calibration")
            per_variant[variant] = per_completed_point(force_vector_errors, sim, ref,
                                                       reference.problem.normals)
        vector.update(point_set_means({v: e[0] for v, e in per_variant.items()}, variants,
                                      cal, experiment))
        tangential.update(point_set_means({v: e[1] for v, e in per_variant.items()}, variants,
                                          cal, experiment))
    return vector, tangential


def point_set_means(errors: dict[str, np.ndarray], variants: dict[str, str],
                    is_calibration: np.ndarray, experiment: str) -> dict[str, float | None]:
    """``<experiment>_global``, ``_calibrated`` and ``_held_out``: the mean over the
    calibration points (global, calibrated) or the held-out points of the (P,) per-point
    ``errors`` of the params.h5 variant ``variants`` maps that key to, over the points it
    completed (None for an empty point set, or one it failed everywhere)."""
    sets = (("global", is_calibration), ("calibrated", is_calibration),
            ("held_out", ~is_calibration))
    return {f"{experiment}_{key}": _mean(errors[variants[key]][points]) for key, points in sets}


def _mean(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]  # a point a model failed has no error
    return float(np.mean(values)) if len(values) else None


def model_errors(reference: Reference, calibration: CalibrationResult,
                 gravity: GravityTest | None, variants: dict[str, str],
                 ran: tuple[str, ...] = ALL_EXPERIMENTS) -> dict[str, float | None]:
    """The :data:`ERROR_KEYS` for one model; ``variants`` maps global/calibrated/held_out to the
    params.h5 variant evaluated on that point set. The keys of experiments not in ``ran``
    are None, and so are the gravity keys of a run the model failed (``gravity`` None, or
    without ``displacement``)."""
    out: dict[str, float | None] = dict.fromkeys(ERROR_KEYS)
    for experiment in calibration.experiments:
        errors = {v: curve_errors(reference, calibration, v, experiment)
                  for v in set(variants.values())}
        out.update(point_set_means(errors, variants, calibration.is_calibration, experiment))
    fe = reference.gravity
    node = reference.problem.tracked_node
    if "gravity_static" in ran and gravity is not None:
        out["gravity_static"] = gravity_static_error(fe.static_displacement,
                                                     gravity.static_displacement,
                                                     reference.problem.free)
    if "gravity_dynamic" in ran and gravity is not None and gravity.displacement is not None:
        out["gravity_dynamic"] = gravity_dynamic_error(fe.displacement[:, node],
                                                       gravity.displacement[:, node])
    return out


def fe_timings(reference: Reference) -> dict[str, float]:
    """The FE stage timings stored in ``reference.h5`` (attribute ``timings_s``, JSON) [s]."""
    raw = reference.meta.get("timings_s")
    try:
        t = json.loads(raw)
        return {k: float(t[k]) for k in ("mesh", "total", "gravity_static", "gravity_dynamic")}
    except (TypeError, ValueError, KeyError) as exc:
        raise DataFileError(f"reference.h5 attribute timings_s = {raw!r} is not the JSON object "
                            f"of stage timings the FE stage writes ({exc})") from None


def versions(reference: Reference) -> dict[str, str | None]:
    """Software versions of the run (dolfinx from the reference file that used it)."""
    import gmsh
    import h5py
    import matplotlib
    import meshio
    import numba
    import scipy
    return {"forcecal": forcecal.__version__, "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "numba": numba.__version__,
            "dolfinx": str(reference.meta.get("dolfinx_version")), "gmsh": gmsh.__version__,
            "h5py": h5py.__version__, "meshio": meshio.__version__,
            "matplotlib": matplotlib.__version__,
            "git_commit": git_commit()}


def experiments_run(experiments: tuple[str, ...], calibration: CalibrationResult,
                    gravity: GravityRuns | None, reference_only: tuple[str, ...] = ()
                    ) -> tuple[tuple[str, ...], dict[str, str]]:
    """(the experiments compared in the report, {experiment not compared: why});
    ``reference_only``: the experiments of the reference that no particle stage runs
    (``floor``)."""
    done = (set(calibration.experiments) | set(() if gravity is None else gravity.experiments)
            | set(reference_only))
    if calibration.body:  # the whole-body record (its errors, fitted or not)
        done.add("body")
    ran = tuple(e for e in ALL_EXPERIMENTS if e in done and e in experiments)
    why = {}
    for e in ALL_EXPERIMENTS:
        if e not in experiments:
            why[e] = (f"{NOT_ASKED} {list(experiments)}: not computed "
                      "(FE or particle), not compared")
        elif e not in done:  # a stage that did not produce what the scene asks for
            why[e] = "in the scene's experiments but its stage produced no results"
    return ran, why


def build_report(scene_name: str, reference: Reference, calibration: CalibrationResult,
                 gravity: GravityRuns | None,
                 experiments: tuple[str, ...] = ALL_EXPERIMENTS, *,
                 goals: VerdictSection = VerdictSection(),
                 realtime: dict[str, Any] | None = None) -> dict[str, Any]:
    """The report dictionary (the keys docs/data-files.md lists) of the scene's
    ``experiments``; ``gravity`` is None when they include no gravity experiment. ``goals``
    are the scene's ``[verdict]``, ``realtime`` the :func:`pipelines.realtime.realtime_block`
    (None: not measured)."""
    p = reference.problem
    fe_t = fe_timings(reference)
    ran, not_run = experiments_run(experiments, calibration, gravity,
                                   ("floor",) if reference.floor is not None else ())
    fe_failures = reference.fe_failures
    for failed, kinds, test in ((fe_failures.gravity, GRAVITY_EXPERIMENTS, "gravity"),
                                (fe_failures.second_support, ("second_support",),
                                 "second-support")):
        if failed is not None:  # why the scene's experiments of that test did not run
            not_run.update({e: f"the FE {test} test failed ({failed['experiment']}: "
                            f"{failed['reason']}): no FE {test} reference"
                            for e in kinds if e in not_run})
    models = {m: None if gravity is None else gravity.models.get(m)
              for m in ("calibrated", "baseline")}
    calibrated = model_errors(reference, calibration, models["calibrated"], CALIBRATED_VARIANTS,
                              ran)
    baseline = model_errors(reference, calibration, models["baseline"], BASELINE_VARIANTS, ran)
    held = ~calibration.is_calibration
    per_point = {f"{v}_{e}": _json_list(curve_errors(reference, calibration, v, e))
                 for v in ("baseline", "global", "calibrated") for e in calibration.experiments}
    failures = [f.as_dict() for f in calibration.failures + (
        () if gravity is None else gravity.failures)]
    warnings = list(calibration.warnings)
    by_model = {"calibrated": vector_errors(reference, calibration, CALIBRATED_VARIANTS),
                "baseline": vector_errors(reference, calibration, BASELINE_VARIANTS)}
    vector_block = None if None in by_model.values() else {
        f"{m}{suffix}": errs[i] for m, errs in by_model.items()
        for i, suffix in enumerate(("", "_tangential"))}
    if vector_block is None:
        warnings.append("params.h5 has no force vectors (written before they were stored): "
                        "force_vector_errors is null; rerun the calibration")
    if not held.any():
        warnings.append("the scene has no held-out points: the *_held_out errors are null")
    lo, hi = calibration.strain.bounds
    run = models["calibrated"]  # the baseline's linear springs have no such range
    if run is not None and (run.strain_min < lo or run.strain_max > hi):
        warnings.append(f"gravity test, calibrated model: connector strains [{run.strain_min:.3g}, "
                        f"{run.strain_max:.3g}] leave the calibrated range [{lo:.3g}, {hi:.3g}] "
                        "(the springs are extrapolated there)")
    node = p.tracked_node
    released = {m: r for m, r in gravity.models.items()
                if r.displacement is not None} if gravity is not None else {}
    gravity_ran = any(e in ran for e in GRAVITY_EXPERIMENTS)
    gravity_block = None if not gravity_ran else {
        "tracked_node": int(node),
        "duration_s": None if gravity.time is None else float(gravity.time[-1]),
        "fe_max_static_sag_m": (None if reference.gravity.static_displacement is None
                                or "gravity_static" not in ran else float(np.linalg.norm(
                                    reference.gravity.static_displacement, axis=1).max())),
        # null for a model whose static sag failed (failures)
        **{f"{m}_max_static_sag_m": None if r is None else float(np.linalg.norm(
            r.static_displacement, axis=1).max()) for m, r in models.items()},
        **{f"{m}_dt_s": None if r is None else r.dt for m, r in models.items()},
        **{f"{m}_critical_dt_s": None if r is None else r.critical_dt
           for m, r in models.items()},
        **{f"{m}_strain_range": None if r is None else [r.strain_min, r.strain_max]
           for m, r in models.items()},
        # where the calibrated springs were required to stay positive (the
        # runs' own extremes are the *_strain_range keys above)
        "calibration_strain_bounds": [lo, hi],
        **({"particle_dynamic_s": None if "calibrated" not in released
            else run.dynamic_time, "fe_dynamic_s": fe_t["gravity_dynamic"]}
           if "gravity_dynamic" in ran else {}),
        # period, first peak and decay need the release and the static sag it swings about
        "dynamic_metrics": dynamic_metrics(
            gravity.time, reference.gravity.displacement[:, node],
            reference.gravity.static_displacement[node],
            {m: (r.displacement[:, node], r.static_displacement[node])
             for m, r in released.items()},
            {"calibrated": calibrated["gravity_dynamic"], "baseline": baseline["gravity_dynamic"]},
            {"fe": release_modes(gravity.time, reference.gravity.displacement, node),
             **{m: release_modes(gravity.time, r.displacement, node)
                for m, r in released.items()}})
        if {"gravity_dynamic", "gravity_static"} <= set(ran) else None}
    support_block = (second_support_block(reference, gravity.second_support)
                     if "second_support" in ran else None)
    report = {
        "scene": scene_name,
        "experiments": list(ran),
        "not_run": not_run,
        "mesh": {"nodes": int(p.mesh.n_vertices), "tets": int(p.mesh.n_tets),
                 "connectors": int(len(p.mesh.edges))},
        "test_points": {"calibration": p.calibration.tolist(), "held_out": p.held_out.tolist(),
                        "coverage": p.coverage},
        "errors": calibrated,
        "baseline_errors": baseline,
        "force_vector_errors": vector_block,
        "timings_s": {"mesh": fe_t["mesh"], "reference": fe_t["total"],
                      "calibration": float(calibration.wall_time),
                      "gravity_particle": None if run is None else (run.static_time
                                                                    + run.dynamic_time),
                      "gravity_fe": None if gravity is None else sum(
                          fe_t[e] for e in ("gravity_static", "gravity_dynamic") if e in ran)},
        "versions": versions(reference),
        "held_out_global": {e: (_mean(curve_errors(reference, calibration, "global", e)[held])
                                if e in calibration.experiments else None)
                            for e in ("indentation", "relaxation")},
        "per_point_errors": {"test_points": p.test_points.tolist(),
                             "is_calibration": calibration.is_calibration.tolist(), **per_point},
        "gravity": gravity_block,
        # the whole-body data (experiment "body"): whether they were fitted, and every
        # variant's errors against them (calibration.body.body_record); null without them
        "body": calibration.body or None,
        "second_support": support_block,
        "discretisation_floor": (floor_block(
            p, reference.gravity, reference.floor, calibrated, baseline,
            None if gravity_block is None else gravity_block["dynamic_metrics"],
            held_out=held_out_curves(reference) if held.any() else None,
            second_support=reference.second_support if "second_support" in ran else None,
            support_block=support_block, reference_mesh=reference_mesh(reference))
            if "floor" in ran and gravity_ran else None),
        "global_parameters": calibration.global_params.as_dict(),
        # how those values spread over the connectors (calibration.global_shape); files written
        # before the key had the paper's uniform set
        "global_shape": calibration.settings.get("calibration", {}).get("global_shape",
                                                                        "uniform"),
        "warnings": warnings,
        "failures": failures,
        "realtime": realtime,
        # FE test points replaced or dropped, a failed FE gravity test (forcecal.fe_failures)
        "fe_failures": fe_failures.to_json(),
        # the mesh as the FE stage saw it (forcecal.preflight; null for an older reference)
        "mesh_preflight": reference.mesh_preflight,
        "strain_ranges": strain_ranges(calibration),
    }
    # judged from what the report measured, nothing else
    report["verdict"] = judge(measurements(report), goals)
    return report


def second_support_block(reference: Reference, runs: SupportRuns) -> dict[str, Any]:
    """``report.json``'s ``second_support``: the gravity test with the second support's clamp,
    held out like it (module docstring), each model against the FE: ``errors`` and
    ``baseline_errors`` (``static_sag``: :func:`gravity_static_error` over the vertices this
    support leaves free; ``release_rms``: :func:`gravity_dynamic_error` of its tracked
    vertex; null for a run the model failed), the sags, the support and the release's
    ``dynamic_metrics`` (:func:`pipelines.dynamics.dynamic_metrics`, as the gravity block's),
    and ``fe_seconds``, the FE's compute time of the test."""
    ref = reference.second_support
    fe, node = ref.runs, runs.tracked_node
    free = support_free(reference.problem, ref)
    errors = {m: {"static_sag": None, "release_rms": None} for m in ("calibrated", "baseline")}
    for m, r in runs.models.items():
        errors[m] = body_test_errors(fe, r, free, node)
    released = {m: r for m, r in runs.models.items() if r.displacement is not None}
    timings = json.loads(reference.meta.get("timings_s", "{}"))

    def sag(u: np.ndarray) -> float:
        return float(np.linalg.norm(u, axis=1).max())

    return {
        "axis": ref.section.axis, "side": ref.section.side,
        "tolerance_m": ref.section.tolerance, "fixed_vertices": int(len(ref.fixed)),
        "tracked_node": int(node), "duration_s": float(fe.time[-1]),
        "fe_max_static_sag_m": sag(fe.static_displacement),
        **{f"{m}_max_static_sag_m": None if m not in runs.models else sag(
            runs.models[m].static_displacement) for m in ("calibrated", "baseline")},
        "errors": errors["calibrated"], "baseline_errors": errors["baseline"],
        "fe_seconds": timings.get("second_support"),
        "dynamic_metrics": dynamic_metrics(
            fe.time, fe.displacement[:, node], fe.static_displacement[node],
            {m: (r.displacement[:, node], r.static_displacement[node])
             for m, r in released.items()},
            {m: e["release_rms"] for m, e in errors.items()},
            {"fe": release_modes(fe.time, fe.displacement, node),
             **{m: release_modes(fe.time, r.displacement, node) for m, r in released.items()}}),
    }


def support_free(problem: Problem, second: SecondSupportResult) -> np.ndarray:
    """(N,) bool: the vertices the second support leaves free."""
    free = np.ones(problem.mesh.n_vertices, dtype=bool)
    free[second.fixed] = False
    return free


def body_test_errors(fe: GravityResult, run: Any, free: np.ndarray, node: int
                     ) -> dict[str, float | None]:
    """A held-out body test's errors of one model's ``run`` (its ``static_displacement`` and
    ``displacement``, None if its release did not run) against the FE's ``fe``:
    ``static_sag`` (:func:`gravity_static_error` over the ``free`` vertices) and
    ``release_rms`` (:func:`gravity_dynamic_error` of vertex ``node``; None without a
    release)."""
    return {"static_sag": gravity_static_error(fe.static_displacement, run.static_displacement,
                                               free),
            "release_rms": None if run.displacement is None else gravity_dynamic_error(
                fe.displacement[:, node], run.displacement[:, node])}


#: the gravity metrics of the discretisation floor, as report.json names them elsewhere
FLOOR_METRICS = ("static_sag", "release_rms", "period_error", "first_peak_error")
#: the second-support test's metrics of the floor (the second_support block's, prefixed)
FLOOR_SUPPORT_METRICS = tuple(f"second_support_{m}" for m in FLOOR_METRICS)
#: the held-out forces' metrics of the floor (the errors' keys)
FLOOR_HELD_OUT_METRICS = ("indentation_held_out", "relaxation_held_out")


def floor_test_metrics(fe: GravityResult, runs: dict[str, GravityResult], free: np.ndarray,
                       node: int) -> dict[str, dict[str, float]]:
    """Each run's :data:`FLOOR_METRICS` in a body test (both runs present) against the FE's
    ``fe``: :func:`body_test_errors` and the release's ``period_error`` and
    ``first_peak_error`` (:func:`pipelines.dynamics.dynamic_metrics`), and
    ``max_static_sag_m``."""
    if not runs:
        return {}
    metrics = dynamic_metrics(fe.time, fe.displacement[:, node], fe.static_displacement[node],
                              {e: (r.displacement[:, node], r.static_displacement[node])
                               for e, r in runs.items()})
    return {e: {**body_test_errors(fe, r, free, node),
                "period_error": metrics[e]["period_error"],
                "first_peak_error": metrics[e]["first_peak_error"],
                "max_static_sag_m": float(np.linalg.norm(r.static_displacement, axis=1).max())}
            for e, r in runs.items()}


def held_out_curves(reference: Reference) -> HeldOutCurves:
    """The reference's held-out test points' curves (the rows after the calibration points)."""
    first = len(reference.problem.calibration)
    return HeldOutCurves(reference.problem.held_out, reference.indentation.force[first:],
                         None if reference.relaxation is None
                         else reference.relaxation.force[first:])


def held_out_force_errors(problem: Problem, reference: HeldOutCurves, floor: HeldOutCurves
                          ) -> dict[str, Any]:
    """The floor's :data:`FLOOR_HELD_OUT_METRICS` against the ``reference``'s curves: the mean
    over the held-out points of the relative RMS error of the normal force
    (:func:`calibration.metrics.relative_rms_error`, the report's held-out metric; normals of
    ``problem``'s test points), over the points both computed (``held_out_points``; a floor
    point the reference does not hold, one it replaced, in ``held_out_not_in_reference``)."""
    index = {int(v): k for k, v in enumerate(reference.vertices.tolist())}
    rows = [(k, index[v]) for k, v in enumerate(floor.vertices.tolist())
            if v in index and v not in floor.failed]
    points = {int(v): k for k, v in enumerate(problem.test_points.tolist())}
    normals = problem.normals[[points[int(floor.vertices[k])] for k, _ in rows]]
    out: dict[str, Any] = dict.fromkeys(FLOOR_HELD_OUT_METRICS)
    for key, sim, ref in (("indentation_held_out", floor.indentation, reference.indentation),
                          ("relaxation_held_out", floor.relaxation, reference.relaxation)):
        if rows and sim is not None and ref is not None:
            out[key] = _mean(per_completed_point(
                relative_rms_error, normal_force(sim[[k for k, _ in rows]], normals),
                normal_force(ref[[r for _, r in rows]], normals)))
    out["held_out_points"] = len(rows)
    out["held_out_not_in_reference"] = [int(v) for v in floor.vertices.tolist()
                                        if int(v) not in index]
    return out


def floor_block(problem: Problem, g: GravityResult, floor: FloorResult,
                calibrated: dict[str, float | None], baseline: dict[str, float | None],
                dynamic: dict[str, Any] | None, *, held_out: HeldOutCurves | None = None,
                second_support: SecondSupportResult | None = None,
                support_block: dict[str, Any] | None = None,
                reference_mesh: str | None = None) -> dict[str, Any]:
    """``report.json``'s ``discretisation_floor``: for each floor element
    (:class:`~forcecal.h5io.FloorResult`) its errors against the reference, measured as the
    calibrated model's: the gravity test's :data:`FLOOR_METRICS` (:func:`floor_test_metrics`
    over the free vertices and of the tracked vertex), the second-support test's
    :data:`FLOOR_SUPPORT_METRICS` (the same, as :func:`second_support_block` measures it,
    against ``second_support``, the reference's test) and the held-out forces'
    :data:`FLOOR_HELD_OUT_METRICS` (:func:`held_out_force_errors` against ``held_out``, the
    reference's curves); its largest static sag and compute times; null errors and the
    reason for a run that failed (or that the floor or the reference did not compute).
    ``calibrated`` and ``baseline`` repeat the models' values of the same metrics next to it
    (their ``errors``; ``dynamic``: the gravity block's ``dynamic_metrics``, None without it;
    ``support_block``: the report's ``second_support`` block), and ``floor_element`` names the
    locking-free element, the floor itself. ``g`` is the reference's gravity test (both runs)
    on ``problem``; ``reference_mesh`` says what mesh the reference's curves ran on."""
    node = problem.tracked_node
    gravity = (floor_test_metrics(g, floor.runs, problem.free, node)
               if g.displacement is not None and g.static_displacement is not None else {})
    support = {}
    if second_support is not None:
        support = floor_test_metrics(second_support.runs, floor.second_support,
                                     support_free(problem, second_support),
                                     second_support.runs.tracked_node)
    elements = {}
    for element in floor.elements:
        row: dict[str, Any] = dict.fromkeys(FLOOR_METRICS + FLOOR_SUPPORT_METRICS
                                            + FLOOR_HELD_OUT_METRICS)
        row.update(max_static_sag_m=None, fe_seconds=floor.seconds.get(element),
                   part_seconds=floor.part_seconds.get(element, {}),
                   failed=floor.failed.get(element),
                   second_support_failed=floor.second_support_failed.get(element),
                   held_out_points=0, held_out_failed=None)
        row.update(gravity.get(element, {}))
        if element in support:
            metrics = support[element]
            row.update({f"second_support_{m}": metrics[m] for m in FLOOR_METRICS})
        elif element in floor.second_support and second_support is None:
            row["second_support_failed"] = "the reference has no second-support test"
        curves = floor.held_out.get(element)
        if curves is not None:
            row["held_out_failed"] = {str(v): r for v, r in curves.failed.items()}
            if held_out is not None:
                row.update(held_out_force_errors(problem, held_out, curves))
        elements[element] = row

    def model_row(errors: dict[str, float | None], name: str) -> dict[str, float | None]:
        m = (dynamic or {}).get(name) or {}
        b = support_block or {}
        s_errors = b.get("errors" if name == "calibrated" else "baseline_errors") or {}
        s_dynamic = (b.get("dynamic_metrics") or {}).get(name) or {}
        return {"static_sag": errors["gravity_static"], "release_rms": errors["gravity_dynamic"],
                "period_error": m.get("period_error"),
                "first_peak_error": m.get("first_peak_error"),
                "second_support_static_sag": s_errors.get("static_sag"),
                "second_support_release_rms": s_errors.get("release_rms"),
                "second_support_period_error": s_dynamic.get("period_error"),
                "second_support_first_peak_error": s_dynamic.get("first_peak_error"),
                **{k: errors.get(k) for k in FLOOR_HELD_OUT_METRICS}}

    return {"floor_element": FLOOR_ELEMENTS[0], "mesh": "particle mesh",
            "held_out_mesh": "particle mesh, unrefined",
            "reference_mesh": reference_mesh,
            "quadrature_degree": floor.quadrature_degree, "tracked_node": int(node),
            "fe_max_static_sag_m": float(np.linalg.norm(g.static_displacement, axis=1).max()),
            "second_support_fe_max_static_sag_m": None if second_support is None else float(
                np.linalg.norm(second_support.runs.static_displacement, axis=1).max()),
            "elements": elements, "calibrated": model_row(calibrated, "calibrated"),
            "baseline": model_row(baseline, "baseline")}


def reference_mesh(reference: Reference) -> str | None:
    """What mesh the reference's test point curves ran on (the floor's run on the particle
    mesh, unrefined): its element, uniform refinements and a punch's rim refinements."""
    fe = reference.fe
    if fe is None:
        return None
    rim = (f", each punch's mesh refined {fe.local_refine} x near its rim"
           if reference.indentation.indenter == "punch" and fe.local_refine else "")
    refined = f" refined {fe.refine} x" if fe.refine else ""
    return f"{fe.element} on the particle mesh{refined}{rim}"


def strain_ranges(calibration: CalibrationResult) -> dict[str, Any] | None:
    """Where the fitted spring laws were evaluated, and where the validation took them:
    experiment -> model (``global``, ``calibrated``) -> ``{"calibration": [lo, hi],
    "held_out": {"<vertex>": [lo, hi] or null}}``, the smallest and largest connector strain
    over the calibration points' curves (the range the fit saw) and over each held-out
    point's (null: the model failed it). None for a ``params.h5`` written before it stored
    the strains."""
    out: dict[str, Any] = {}
    points = calibration.problem.test_points
    cal = calibration.is_calibration
    for model in ("global", "calibrated"):
        strains = calibration.variants[model].strains
        if strains is None:
            return None
        for e, values in strains.items():
            done = cal & np.all(np.isfinite(values), axis=1)
            fitted = ([float(values[done, 0].min()), float(values[done, 1].max())]
                      if done.any() else None)
            out.setdefault(e, {})[model] = {
                "calibration": fitted,
                "held_out": {str(int(points[k])): (values[k].tolist() if np.all(
                    np.isfinite(values[k])) else None) for k in np.nonzero(~cal)[0]}}
    return out


def _json_list(values: np.ndarray) -> list[float | None]:
    """``values`` as a JSON list, NaN (a point a model failed) as null."""
    return [float(v) if np.isfinite(v) else None for v in values]


def check_report(report: dict[str, Any]) -> None:
    """Raise :class:`DataFileError` if a fixed key is missing or a number is not finite (or
    null without a reason: an experiment in ``not_run``, no held-out points, a model's
    recorded failure of the experiment, a failed FE gravity test), or the ``verdict`` (when
    there is one: reports written before it have none) is not the block of every check."""
    if not isinstance(report, dict):
        raise DataFileError(f"report.json is a JSON {type(report).__name__}, not the report's "
                            "object of keys")
    for group in ("not_run", "force_vector_errors"):
        if not isinstance(report.get(group) or {}, dict):
            raise DataFileError(f"report.json: {group} = {report[group]!r:.80} is not an object "
                                "of keys")
    not_run = report.get("not_run", {})
    no_gravity = {"gravity_static", "gravity_dynamic"} <= set(not_run)
    # "indentation", "relaxation", "gravity": experiments some model failed (or the FE)
    failed = {f["experiment"].split("_")[0] for f in report.get("failures") or []}
    if (report.get("fe_failures") or {}).get("gravity"):
        failed.add("gravity")
    groups = [("errors", report.get("errors", {}), ERROR_KEYS),
              ("baseline_errors", report.get("baseline_errors", {}), ERROR_KEYS),
              ("timings_s", report.get("timings_s", {}), TIMING_KEYS)]
    # reports written before the force vector errors have no such key; null: not stored
    vector = report.get("force_vector_errors") or {}
    groups += [(f"force_vector_errors.{m}", values, CURVE_KEYS) for m, values in vector.items()]
    for group, values, keys in groups:
        if not isinstance(values, dict):
            raise DataFileError(f"report.json: {group} = {values!r:.80} is not an object of keys")
        for k in keys:
            if k not in values:
                raise DataFileError(f"report.json: {group}.{k} is missing")
            v = values[k]
            explained = v is None and (k.endswith("held_out") or any(
                k.startswith(e) for e in not_run) or (no_gravity and k.startswith("gravity"))
                or k.split("_")[0] in failed)
            if not explained and not _finite(v):
                raise DataFileError(f"report.json: {group}.{k} = {v!r} is not a finite number")
    _check_second_support(report.get("second_support"), report.get("failures") or [])
    if "verdict" in report:
        check_verdict(report["verdict"])


def _check_second_support(block: Any, failures: list[dict]) -> None:
    """Raise :class:`DataFileError` unless ``block`` is null or its errors are finite numbers
    (null only for a model with a recorded failure of the second support's test)."""
    if block is None:
        return
    if not isinstance(block, dict):
        raise DataFileError(f"report.json: second_support = {block!r:.80} is not an object")
    for model, group in (("calibrated", "errors"), ("baseline", "baseline_errors")):
        values = block.get(group)
        if not isinstance(values, dict):
            raise DataFileError(f"report.json: second_support.{group} is missing")
        failed = any(f.get("model") == model and str(f.get("experiment", "")).startswith(
            "second_support") for f in failures)
        for k in ("static_sag", "release_rms"):
            v = values.get(k)
            if not (v is None and failed) and not _finite(v):
                raise DataFileError(f"report.json: second_support.{group}.{k} = {v!r} is not "
                                    "a finite number")


def _finite(v: Any) -> bool:
    """Whether ``v`` is a finite JSON number (not a boolean)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def check_verdict(verdict: Any) -> None:
    """Raise :class:`DataFileError` unless ``verdict`` is the block :func:`pipelines.verdict.judge`
    writes: every check with a known status (an opt-in experiment's only when asked for),
    ``passed`` iff every check passed."""
    checks = verdict.get("checks") if isinstance(verdict, dict) else None
    if not isinstance(checks, dict) or set(CHECKS) - set(OPT_IN) - set(checks):
        raise DataFileError(f"report.json: verdict = {verdict!r:.80} is not the block of the "
                            f"checks {list(CHECKS)}")
    for name, c in checks.items():
        if not isinstance(c, dict) or c.get("status") not in STATUSES:
            raise DataFileError(f"report.json: verdict.checks.{name} = {c!r:.80} has no status "
                                f"of {list(STATUSES)}")
    if verdict.get("passed") is not all(c["status"] == "passed" for c in checks.values()):
        raise DataFileError("report.json: verdict.passed does not say whether every check "
                            "passed")


def read_report(path: str | Path) -> dict[str, Any]:
    """Read and check a ``report.json``."""
    try:
        report = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise DataFileError(f"{path} is not a readable report.json: {exc}") from None
    check_report(report)
    return report


def write_report(path: str | Path, report: dict[str, Any]) -> None:
    """Check and write ``report.json`` atomically."""
    check_report(report)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(report, indent=2) + "\n")


ERROR_ROWS = (("indentation_global", "static indentation, calibration points, global model"),
              ("indentation_calibrated", "static indentation, calibration points, calibrated"),
              ("indentation_held_out", "static indentation, held-out points, calibrated"),
              ("relaxation_global", "relaxation, calibration points, global model"),
              ("relaxation_calibrated", "relaxation, calibration points, calibrated"),
              ("relaxation_held_out", "relaxation, held-out points, calibrated"),
              ("gravity_static", "gravity, static sag (all free vertices)"),
              ("gravity_dynamic", "gravity, dynamic release, tracked node"))
TIMING_ROWS = (("mesh", "mesh, test points, FE model set-up"),
               ("reference", "FE reference, everything (wall)"),
               ("gravity_fe", "FE gravity: static + dynamic (compute)"),
               ("calibration", "calibration (wall)"),
               ("gravity_particle", "particle gravity: static + dynamic (wall)"))


def _percent(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.2f} %"


def results_markdown(report: dict[str, Any]) -> str:
    """A report's results tables (errors and timings), as docs/results.md shows them."""
    rows = ["| error vs FE (relative, see definitions) | particle, tuned | particle, baseline |",
            "|---|---|---|"]
    rows += [f"| {label} | {_percent(report['errors'][k])} | "
             f"{_percent(report['baseline_errors'][k])} |" for k, label in ERROR_ROWS]
    rows += ["", "| step | time [s] |", "|---|---|"]
    rows += [f"| {label} | "
             f"{'n/a' if report['timings_s'][k] is None else format(report['timings_s'][k], '.1f')}"
             " |" for k, label in TIMING_ROWS]
    g = report.get("gravity") or {}
    if "particle_dynamic_s" in g:
        rows.append(f"| particle gravity dynamics alone ({g['duration_s']:g} s simulated) | "
                    f"{g['particle_dynamic_s']:.2f} |")
    return "\n".join(rows)
