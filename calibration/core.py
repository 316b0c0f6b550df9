"""``calibrate``: initial guess -> global tuning -> local tuning -> validation -> params.h5.

Phases, one function each returning a small frozen dataclass, each fit checkpointed
(:mod:`calibration.checkpoint`, keyed by :func:`calibration.provenance.checkpoint_inputs`)
so an interrupted run resumes where it stopped and ends with the same result:

1. inputs and reach (:func:`prepare_fit`): the checked reference, the experiments' strain
   range and the closed-form initial guess (:func:`calibration.global_fit.initial_guess`);
2. global static fit, 3. global relaxation fit (:func:`fit_global_phase`,
   :mod:`calibration.global_fit`; Nelder-Mead as the paper, the gradient method's
   relaxation fit by Gauss-Newton);
4. local static sweeps, 5. local relaxation sweeps (:mod:`calibration.local`), unless
   ``calibration.local = false``, or the gradient fit (:mod:`calibration.gradient`), on
   the whole-body data too when the scene has them (:func:`tune`, :func:`whole_body_data`);
6. gravity check (:func:`check_gravity`): with gravity experiments in the scene, the
   calibrated model must complete the particle side of the gravity test, or it is pulled
   back towards the global fit until it does (:mod:`calibration.gravity_check`; only
   completion is used, never the FE's sag);
7. whole-body record (:func:`record_body`): every model against every whole-body item;
8. validation (:func:`validate`): the Van Gelder baseline (:mod:`calibration.baseline`), the
   global-only and the calibrated (global + local, or gradient) models are evaluated at every
   test point; held-out points, never used by any fit, give the honest accuracy. A model
   that does not complete a point's curve is a result, not a crash: its failure is recorded
   (:mod:`calibration.validation`; NaN rows in ``params.h5``) and the others go on;
9. writing (:func:`calibration_warnings`, :func:`write_calibration`): ``params.h5``.

Only the experiments of the scene's ``experiments`` list are fitted and
evaluated: without ``relaxation`` the relaxation phases (3, 5) are skipped, the
springs alone are fitted, and the result says (a warning in ``params.h5``) that
the Maxwell arms keep their closed-form initial guess, uncalibrated.

The reference must match the scene: same mesh, fixed nodes, test points,
material and sample schedules; a mismatch, a corrupt file or a non-physical
curve raises :class:`~forcecal.errors.DataFileError` before any fitting (a
scene whose test points are fixed or off the surface is refused by
:func:`forcecal.problem.build_problem` with a :class:`~forcecal.errors.MeshError`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.baseline import van_gelder_params
from calibration.body import BodyData, body_kinds, body_record
from calibration.checkpoint import Checkpoint
from calibration.gradient import GradientResult, Validity, fit_gradient, gradient_backend
from calibration.gravity_check import GravityCheck, carry_gravity, gravity_failure
from calibration.global_fit import (GAUSS_NEWTON, NELDER_MEAD, fe_initial_slopes, fit_relaxation,
                                   fit_static, initial_guess)
from calibration.local import LocalParametrisation, Sweep, run_local_phase
from calibration.metrics import relative_rms_error
from calibration.optimize import Fit
from calibration.parametrisation import (RELAXATION_DIM, STATIC_DIM, GlobalParams, Rings,
                                         StrainRange, build_rings, connector_floor, global_shape)
from calibration.pool import Backend, Experiments, Pool, particle_backend
from calibration.reach import experiment_reach
from calibration.provenance import checkpoint_inputs, fit_settings, versions
from calibration.results import (EXPERIMENTS, CalibrationResult, VariantCurves, write_params)
from calibration.validation import per_completed_point, validate_points
from forcecal.errors import DataFileError
from forcecal.h5io import (Reference, check_reference_settings, read_reference, reference_digest,
                          section_differences)
from forcecal.indenter import indenter_footprints
from forcecal.fe_failures import apply_fe_failures
from forcecal.problem import Problem, build_problem
from forcecal.scene import GRAVITY_EXPERIMENTS, CalibrationSection, Scene, load_scene
from forcecal.schedules import indentation_depths, relaxation_schedule
from particle.body import LOAD_KINDS
from particle.params import ConnectorParams

log = logging.getLogger(__name__)

#: the warning of a calibration without relaxation data (params.h5, report.json)
ARMS_NOT_CALIBRATED = ("the Maxwell arms are not calibrated (the scene's experiments do not "
                       "include 'relaxation'): only the springs were fitted; the arms keep the "
                       "closed-form initial guess (k_i = g_i / g_inf K0, tau_i the Prony times)")


def fitted_experiments(scene: Scene) -> tuple[str, ...]:
    """The experiments of ``scene`` a calibration fits (some of :data:`EXPERIMENTS`)."""
    return tuple(e for e in EXPERIMENTS if scene.runs(e))


def load_checked_reference(scene: Scene, reference_path: str | Path) -> Reference:
    """Read the reference and check it belongs to ``scene`` (module docstring)."""
    problem = build_problem(scene)
    ref = read_reference(reference_path, expect_mesh=problem.mesh.fingerprint())
    for e in fitted_experiments(scene):
        ref.require(e, reference_path)
    check_reference_settings(ref, scene, reference_path)  # [fe], [gravity], indenter
    rp = ref.problem
    # test points whose FE runs failed were replaced or dropped (recorded in the reference)
    problem = apply_fe_failures(problem, ref.fe_failures)
    for what in ("fixed", "calibration", "held_out"):
        if not np.array_equal(np.sort(getattr(rp, what)), np.sort(getattr(problem, what))):
            raise DataFileError(f"{reference_path}: its {what} nodes differ from the scene's; "
                                "recompute the reference for this scene")
    differ = section_differences("material", ref.material, scene.material, ("reference",))
    if differ:
        raise DataFileError(f"{reference_path}: computed with another material than the "
                            f"scene's: {'; '.join(differ)}; recompute the reference")
    times, depths = relaxation_schedule(scene.relaxation)
    relax = scene.runs("relaxation")
    for name, got, want in (
            ("indentation/displacement", ref.indentation.displacement,
             indentation_depths(scene.indentation)),
            *((("relaxation/time", ref.relaxation.time, times),
               ("relaxation/displacement", ref.relaxation.displacement, depths)) if relax
              else ())):
        if got.shape != want.shape or not np.allclose(got, want, rtol=1e-9, atol=0.0):
            raise DataFileError(f"{reference_path}:/{name} does not match the scene's schedule")
    for name, curves in (("indentation", ref.indentation.force_normal),
                         *((("relaxation", ref.relaxation.force_normal),) if relax else ())):
        bad = np.nonzero(np.max(curves, axis=1) <= 0.0)[0]
        if len(bad):
            raise DataFileError(f"{reference_path}: {name} force of test point(s) "
                                f"{rp.test_points[bad].tolist()} never pushes back (<= 0 N); "
                                "is the force signed along the inward normal?")
    return ref


def checkpoint_path(out_path: Path) -> Path:
    """Where the checkpoint of a calibration writing ``out_path`` lives."""
    return out_path.parent / "checkpoints" / f"{out_path.name}.json"


#: the global and local phases: name -> (global fit, the experiment whose curves it fits)
PHASES = {"static": (fit_static, "indentation"), "relaxation": (fit_relaxation, "relaxation")}


@dataclass(frozen=True, eq=False)
class FitSetup:
    """What every phase reads, known before any fit: the scene, its checked reference, the
    experiments' reach and the closed-form initial guess.

    Attributes:
        scene: the scene calibrated.
        ref: its FE reference (checked by :func:`load_checked_reference`).
        fitted: the experiments fitted (:func:`fitted_experiments`).
        ref_curves: experiment -> (P, S) FE normal force [N] at every test point.
        experiments: the particle experiments the pool's workers run.
        shape: the global set's spread over the connectors, (E,) (None: uniform).
        strain: the experiments' strain range (:func:`calibration.reach.experiment_reach`).
        unit_slope: (P,) initial slope of the unit network's indentation curves [N/m].
        fe_slope: (Pc,) initial slope of the FE indentation curves of the calibration points
            [N/m].
        initial: the closed-form initial guess.
        rings: the connectors each calibration point's local offsets act on.
        validity: where every spring must stay stiff (:func:`spring_validity`), with the
            floor of the initial guess.
        feasible: the overall range of ``validity`` the global fits keep the springs on.
        whole_body: the scene runs the whole-body experiment and the reference holds it.
        gravity: the scene runs a gravity experiment and the reference holds the FE run.
    """

    scene: Scene
    ref: Reference
    fitted: tuple[str, ...]
    ref_curves: dict[str, np.ndarray]
    experiments: Experiments
    shape: np.ndarray | None
    strain: StrainRange
    unit_slope: np.ndarray
    fe_slope: np.ndarray
    initial: GlobalParams
    rings: Rings
    validity: Validity
    feasible: StrainRange
    whole_body: bool
    gravity: bool

    @property
    def settings(self) -> CalibrationSection:
        return self.scene.calibration

    @property
    def gradient(self) -> bool:
        """The gradient method (else the paper's: global fits, then local tuning)."""
        return self.settings.method == "gradient"

    @property
    def problem(self) -> Problem:
        return self.ref.problem

    @property
    def n_connectors(self) -> int:
        return len(self.problem.mesh.edges)

    @property
    def n_calibration(self) -> int:
        return len(self.problem.calibration)

    def calibration_curves(self, experiment: str) -> np.ndarray:
        """(Pc, S) FE normal force [N] of the calibration points in ``experiment``."""
        return self.ref_curves[experiment][:self.n_calibration]

    def connector_params(self, glob: GlobalParams) -> ConnectorParams:
        """``glob`` on every connector, spread by the global shape."""
        return glob.connector_params(self.n_connectors, self.shape)


def prepare_fit(scene: Scene, reference_path: str | Path) -> FitSetup:
    """Inputs and reach: check the reference against ``scene``, measure the experiments'
    strain range on the unit network, the closed-form initial guess and the springs'
    validity range (:class:`FitSetup`)."""
    settings = scene.calibration
    ref = load_checked_reference(scene, reference_path)
    fitted = fitted_experiments(scene)
    problem, material = ref.problem, ref.material
    mesh = problem.mesh
    n_cal = len(problem.calibration)
    ref_curves = {e: getattr(ref, e).force_normal for e in fitted}
    # without relaxation data the evaluators still get the scene's schedule (never run)
    times, relax_depths = ((ref.relaxation.time, ref.relaxation.displacement)
                           if "relaxation" in fitted else relaxation_schedule(scene.relaxation))
    footprints = (None if scene.indentation.indenter == "vertex" else indenter_footprints(
        mesh, problem.fixed, problem.test_points, problem.normals, scene.indentation.indenter,
        scene.indentation.radius))
    # the global set's spread over the connectors (None: uniform); its unit network gives the
    # initial guess and the experiments' strain range
    shape = global_shape(mesh, settings.global_shape)
    # the scene's depths are the reference's (load_checked_reference compared the schedules)
    reach = experiment_reach(scene, problem, shape, footprints)
    linear, strain = reach.linear, reach.strain
    experiments = Experiments(problem, material.density, ref.indentation.displacement,
                              times, relax_depths, strain.bounds, footprints,
                              scene.particle.volume_element)
    fe_slope = fe_initial_slopes(experiments.depths, ref_curves["indentation"][:n_cal])
    initial = initial_guess(material, fe_slope, linear.slope[:n_cal],
                            mesh if scene.particle.volume else None, shape,
                            volume_arms=scene.particle.volume_arms)
    log.info("initial guess: %s; strain range [%.3g, %.3g]", initial, strain.low, strain.high)
    rings = build_rings(mesh, problem.calibration,
                        None if footprints is None else footprints[:n_cal])
    # where every spring must stay stiff, known before any fit (the FE sag's release range
    # is geometric); the global springs share one K(eps)/K0, so they must hold on all of it
    # (only for a scene that runs gravity: a reference holding more experiments than the
    # scene lists does not change its fit)
    gravity = ref.gravity is not None and any(scene.runs(e) for e in GRAVITY_EXPERIMENTS)
    validity = spring_validity(ref, initial, strain, settings.stiffness_floor,
                               scene.particle.strain_margin, shape, gravity=gravity,
                               loads=fitted_loads(scene, ref))
    return FitSetup(
        scene=scene, ref=ref, fitted=fitted, ref_curves=ref_curves, experiments=experiments,
        shape=shape, strain=strain, unit_slope=linear.slope, fe_slope=fe_slope,
        initial=initial, rings=rings, validity=validity,
        feasible=StrainRange(float(validity.low.min()), float(validity.high.max())),
        whole_body=scene.runs("body") and ref.body is not None, gravity=gravity)


@dataclass(frozen=True, eq=False)
class GlobalPhase:
    """One global fit: the parameters it ends at, its :class:`~calibration.optimize.Fit`
    and its wall time [s]."""

    params: GlobalParams
    fit: Fit
    seconds: float


def fit_global_phase(pool: Pool, setup: FitSetup, checkpoint: Checkpoint, phase: str,
                     start: GlobalParams, *, progress: bool, verbose: bool) -> GlobalPhase:
    """Global static or relaxation fit (``phase``, one of :data:`PHASES`) from ``start``,
    or its checkpointed result. Nelder-Mead as the paper; the gradient method's relaxation
    fit by Gauss-Newton."""
    fit_fn, experiment = PHASES[phase]
    key = f"global_{phase}"
    saved = checkpoint.get(key)
    t = time.perf_counter()
    if saved is None:
        pool.forget_warm_starts()  # as a resumed run starts (identical resumes)
        optimizer = GAUSS_NEWTON if setup.gradient and phase == "relaxation" else NELDER_MEAD
        glob, fit = fit_fn(pool, start, setup.strain, setup.calibration_curves(experiment),
                           setup.n_connectors, setup.settings, optimizer=optimizer,
                           feasible=setup.feasible, shape=setup.shape, progress=progress,
                           verbose=verbose)
        checkpoint.put(key, {"params": glob.as_dict(), "fit": fit.as_dict()})
    else:
        glob, fit = GlobalParams(**saved["params"]), Fit.from_dict(saved["fit"])
    seconds = time.perf_counter() - t
    log.info("global %s fit: cost %.6g -> %.6g in %d evaluations", phase, fit.initial_cost,
             fit.cost, fit.evaluations)
    return GlobalPhase(glob, fit, seconds)


@dataclass(frozen=True, eq=False)
class BodyFitData:
    """The whole-body data of a calibration.

    Attributes:
        kinds: the kinds the scene asks the gradient fit to use (``calibration.body_data``;
            empty for the paper's method or a scene without the experiment).
        every: every whole-body item, against the global fit (None: no whole-body data).
        fitted: the kinds the global fit has a response to (None: none is fitted).
        failure: why some asked-for kinds are not fitted from the start (None: all are).
    """

    kinds: tuple[str, ...]
    every: BodyData | None
    fitted: BodyData | None
    failure: str | None


def whole_body_data(setup: FitSetup, glob: GlobalParams) -> BodyFitData:
    """The whole-body data against the global fit ``glob``; the fit starts from it, so only
    the kinds it has a response to are fitted from the start."""
    kinds = (body_kinds(setup.settings.body_data) if setup.whole_body and setup.gradient
             else ())
    every, fitted, failures = None, None, []
    # kinds the FE could not compute (its static body loads failed): never fitted
    lost = tuple(k for k in kinds if k in LOAD_KINDS) if (
        setup.whole_body and setup.ref.body.load_failure is not None) else ()
    if lost:
        failures.append(f"the FE has no {'+'.join(lost)} data: {setup.ref.body.load_failure}")
        log.warning("whole-body data: %s", failures[-1])
    if setup.whole_body:
        every = BodyData.of(setup.ref, tuple(k for k in kinds if k not in lost),
                            setup.connector_params(glob), setup.scene.body.load_steps)
    if every is not None and every.kinds:
        missing = {k: why for k, why in every.carried(setup.connector_params(glob)).items()
                   if why is not None}
        if missing:
            failures.append("the global fit has no response to the whole-body data "
                            + "; ".join(f"{k} ({why})" for k, why in missing.items())
                            + "; they join the fit once it carries them")
            log.warning("%s", failures[-1])
        carried = tuple(k for k in every.kinds if k not in missing)
        fitted = every.with_kinds(carried) if carried else None
    return BodyFitData(kinds, every, fitted, "; ".join(failures) or None)


@dataclass(frozen=True, eq=False)
class Tuning:
    """Local or gradient tuning from the global fit.

    Attributes:
        local: the paper's local offsets (zero for the gradient method or without local
            tuning).
        local_sweeps: phase -> its local sweeps (empty lists when not run).
        gradient: the gradient fit (None: the paper's method).
        evaluations: counts recorded in ``params.h5`` (cost evaluations or Jacobians).
        stage_times: phase -> wall time [s].
    """

    local: LocalParametrisation
    local_sweeps: dict[str, list[Sweep]]
    gradient: GradientResult | None
    evaluations: dict[str, int]
    stage_times: dict[str, float]

    def params_at(self, fraction: float) -> ConnectorParams:
        """The fit, or ``fraction`` of it over the global fit (the gravity check's
        pull-back)."""
        if self.gradient is not None:
            return self.gradient.pulled_back(fraction)
        return self.local.scaled(fraction).params()


def tune(pool: Pool, setup: FitSetup, glob: GlobalParams, body: BodyFitData,
         checkpoint: Checkpoint, *, progress: bool, verbose: bool) -> Tuning:
    """From the global fit ``glob``: the gradient fit (:func:`calibration.gradient.fit_gradient`)
    or the paper's local sweeps (:func:`calibration.local.run_local_phase`, unless
    ``calibration.local = false``); each checkpointed."""
    settings, mesh = setup.settings, setup.problem.mesh
    validity = dataclasses.replace(
        setup.validity, floor=connector_floor(settings.stiffness_floor, glob.K0, setup.shape),
        K0_global=glob.K0)
    local = LocalParametrisation(glob, setup.rings, setup.strain, validity.floor,
                                 np.zeros((setup.n_calibration, STATIC_DIM)),
                                 np.zeros((setup.n_calibration, RELAXATION_DIM)),
                                 local_validity(validity, setup.connector_params(glob),
                                                settings.stiffness_ceiling),
                                 setup.shape)
    local_sweeps: dict[str, list[Sweep]] = {"static": [], "relaxation": []}
    evaluations: dict[str, int] = {}
    stage_times: dict[str, float] = {}
    gfit = None
    if setup.gradient:
        t = time.perf_counter()
        vectors = ({e: getattr(setup.ref, e).force[:setup.n_calibration] for e in setup.fitted}
                   if settings.force_components == "vector" else None)
        gfit = fit_gradient(pool, glob, setup.strain,
                            {e: setup.calibration_curves(e) for e in setup.fitted},
                            validity, mesh.edges, mesh.n_vertices, folds=settings.cv_folds,
                            # per-tet kv too when the global fit carries the volume term
                            tets=mesh.tets if glob.has_volume else None,
                            global_shape=setup.shape,
                            kv_per_tet=settings.kv_per_tet,
                            prior_ratio=settings.prior_ratio,
                            shape_smoothness=settings.shape_smoothness,
                            split_prior=settings.split_prior,
                            force_vectors=vectors,
                            max_iterations=settings.gradient_max_iterations,
                            body=body.fitted,
                            body_upgrade=body.every if body.fitted is not None else None,
                            body_weight=(None if settings.body_weight == "cv"
                                         else float(settings.body_weight)),
                            body_candidates_report=settings.body_candidates,
                            checkpoint_get=checkpoint.get, checkpoint_put=checkpoint.put)
        evaluations["gradient_jacobians"] = gfit.jacobians
        stage_times["gradient"] = time.perf_counter() - t
    elif settings.local:
        for phase, (_, experiment) in PHASES.items():
            if experiment not in setup.fitted:
                continue
            key = f"local_{phase}"
            t = time.perf_counter()
            local, local_sweeps[phase] = run_local_phase(
                pool, local, phase, setup.calibration_curves(experiment), settings,
                checkpoint.get(key), lambda record, key=key: checkpoint.put(key, record),
                progress=progress, verbose=verbose)
            evaluations[f"{key}_cost_evaluations"] = sum(
                f.evaluations for s in local_sweeps[phase] for f in s.fits)
            stage_times[key] = time.perf_counter() - t
    return Tuning(local, local_sweeps, gfit, evaluations, stage_times)


@dataclass(frozen=True, eq=False)
class GravityCarry:
    """The calibrated connectors after the gravity check.

    Attributes:
        calibrated: the fit, or the fraction of it the gravity test completes with.
        check: the check's outcome (None: the scene runs no gravity experiment).
        local: the paper's offsets at that fraction (``params.h5`` stores them).
        seconds: the check's wall time [s] (None: not run).
    """

    calibrated: ConnectorParams
    check: GravityCheck | None
    local: LocalParametrisation
    seconds: float | None


def check_gravity(setup: FitSetup, tuning: Tuning) -> GravityCarry:
    """With gravity experiments in the scene, pull the fit back towards the global fit
    until the model completes the particle side of the gravity test
    (:func:`calibration.gravity_check.carry_gravity`); only completion is used, never the
    FE comparison."""
    if not setup.gravity:
        return GravityCarry(tuning.params_at(1.0), None, tuning.local, None)
    t = time.perf_counter()
    scene, strain = setup.scene, setup.strain
    times = setup.ref.gravity.time if scene.runs("gravity_dynamic") else None
    calibrated, check = carry_gravity(
        tuning.params_at,
        lambda p: gravity_failure(scene, setup.problem, p, times, strain.bounds))
    local = tuning.local
    if tuning.gradient is None and check.scale is not None:
        local = local.scaled(check.scale)  # the offsets params.h5 stores
    return GravityCarry(calibrated, check, local, time.perf_counter() - t)


@dataclass(frozen=True, eq=False)
class BodySummary:
    """The whole-body record of ``params.h5`` (:func:`calibration.body.body_record`; empty
    without whole-body data) and its wall time [s] (None: not run)."""

    record: dict
    seconds: float | None


def record_body(setup: FitSetup, body: BodyFitData, tuning: Tuning,
                connectors: dict[str, ConnectorParams]) -> BodySummary:
    """Every variant against every whole-body item, fitted or not."""
    if not setup.whole_body:
        return BodySummary({}, None)
    t = time.perf_counter()
    fit = tuning.gradient if body.fitted is not None else None
    fitted_data = body.every if fit is None else fit.body_data
    record = body_record(fitted_data, fit.body_weight if fit is not None else None, connectors,
                         body.failure if fitted_data.kinds != body.kinds else None,
                         fit.body_candidates if fit is not None else None)
    return BodySummary(record, time.perf_counter() - t)


@dataclass(frozen=True, eq=False)
class Validation:
    """Every variant's curves at every test point.

    Attributes:
        variants: variant -> its curves and errors.
        failures: the points a variant did not complete (NaN rows in ``params.h5``).
        point_curves: point curves the pool evaluated over the whole calibration.
        seconds: the validation's wall time [s].
    """

    variants: dict[str, VariantCurves]
    failures: tuple
    point_curves: int
    seconds: float


def validate(pool: Pool, setup: FitSetup, connectors: dict[str, ConnectorParams]
             ) -> Validation:
    """Evaluate every variant in ``connectors`` at every test point in every fitted
    experiment; a point the model fails is a result (NaN rows), not a crash."""
    t = time.perf_counter()
    fitted, problem = setup.fitted, setup.problem
    pool.forget_warm_starts()  # the phases before may have been loaded (identical resumes)
    variants, failures = {}, []
    for variant, params in connectors.items():
        done = {e: validate_points(pool, problem, variant, params, e) for e in fitted}
        failures += [f for e in fitted for f in done[e].failures]
        errors = {e: per_completed_point(relative_rms_error, done[e].curves, setup.ref_curves[e])
                  for e in fitted}

        def every(name: str) -> dict[str, np.ndarray] | None:
            values = {e: getattr(done[e], name) for e in fitted}
            return None if any(v is None for v in values.values()) else values
        variants[variant] = VariantCurves({e: done[e].curves for e in fitted}, errors,
                                          every("forces"), every("strains"))
    return Validation(variants, tuple(failures), pool.evaluations(), time.perf_counter() - t)


def calibration_warnings(setup: FitSetup, global_fits: dict[str, Fit], tuning: Tuning,
                         glob: GlobalParams, gravity: GravityCarry, body: BodyFitData,
                         body_summary: dict) -> tuple[str, ...]:
    """The warnings ``params.h5`` records: the global fits', uncalibrated arms, the local
    sweeps', settings that act on nothing (also logged here), the gravity pull-back and a
    failed whole-body record."""
    warnings = [w for fit in global_fits.values() for w in fit.warnings]
    if "relaxation" not in setup.fitted:
        warnings.append(ARMS_NOT_CALIBRATED)
    warnings += _local_warnings(tuning.local_sweeps, setup.settings.local_max_evaluations)
    for unused in unused_settings(setup.settings, glob.has_volume, setup.whole_body):
        log.warning(unused)
        warnings.append(unused)
    if gravity.check is not None and gravity.check.warning() is not None:
        warnings.append(gravity.check.warning())
    if body_summary.get("status") == "failed" or body.failure is not None:
        warnings.append(f"whole-body data: {body_summary['failure']}")
    return tuple(warnings)


def calibrate(scene: Scene | str | Path, reference_path: str | Path, out_path: str | Path, *,
              progress: bool = True, verbose: bool = False, workers: int | None = None,
              backend: Backend = particle_backend) -> CalibrationResult:
    """Fit the connector parameters of ``scene`` to the FE reference; write ``params.h5``.

    Args:
        scene: the scene (or its TOML path); its ``[calibration]`` table holds the settings.
            The sections the fit reads are recorded in ``params.h5`` and key the checkpoint
            (:mod:`calibration.provenance`).
        reference_path: ``reference.h5`` of that scene.
        out_path: the ``params.h5`` to write (atomically); the checkpoint lives in
            ``<out dir>/checkpoints/`` and is removed at the end.
        progress: tqdm bars (only on a terminal).
        verbose: log every optimiser iteration (INFO) and every infeasible point.
        workers: parallel workers; None = ``calibration.workers`` of the scene.
        backend: builds the evaluators of a worker's points (tests substitute it).

    Returns:
        the :class:`CalibrationResult` (also readable with :func:`read_params`).

    Under ``mpirun`` with several ranks, call this on rank 0 only; the other
    ranks serve as its workers with :func:`calibration.pool.serve_mpi`.
    """
    t0 = time.perf_counter()
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    out_path = Path(out_path)
    setup = prepare_fit(scene, reference_path)
    checkpoint = Checkpoint(checkpoint_path(out_path), checkpoint_inputs(
        scene, reference_path, setup.fitted, setup.whole_body))
    if setup.gradient and backend is particle_backend:
        backend = gradient_backend
    evaluations: dict[str, int] = {}
    stage_times: dict[str, float] = {}
    with Pool(setup.experiments, setup.connector_params(setup.initial), backend=backend,
              workers=setup.settings.workers if workers is None else workers) as pool:
        glob = setup.initial
        global_fits: dict[str, Fit] = {}
        for phase, (_, experiment) in PHASES.items():
            if experiment not in setup.fitted:
                continue
            done = fit_global_phase(pool, setup, checkpoint, phase, glob, progress=progress,
                                    verbose=verbose)
            glob, global_fits[phase] = done.params, done.fit
            stage_times[f"global_{phase}"] = done.seconds
            evaluations[f"global_{phase}_cost_evaluations"] = done.fit.evaluations
        log.info("global parameters: %s", glob)

        body = whole_body_data(setup, glob)
        tuning = tune(pool, setup, glob, body, checkpoint, progress=progress, verbose=verbose)
        evaluations.update(tuning.evaluations)
        stage_times.update(tuning.stage_times)
        gravity = check_gravity(setup, tuning)
        if gravity.seconds is not None:
            stage_times["gravity_check"] = gravity.seconds
        connectors = {"baseline": van_gelder_params(setup.problem.mesh, setup.ref.material),
                      "global": setup.connector_params(glob), "calibrated": gravity.calibrated}
        body_summary = record_body(setup, body, tuning, connectors)
        if body_summary.seconds is not None:
            stage_times["body"] = body_summary.seconds
        validation = validate(pool, setup, connectors)
        evaluations["point_curves"] = validation.point_curves
        stage_times["validation"] = validation.seconds

    warnings = calibration_warnings(setup, global_fits, tuning, glob, gravity, body,
                                    body_summary.record)
    result = CalibrationResult(
        problem=setup.problem, initial=setup.initial, global_params=glob,
        connectors=connectors, variants=validation.variants,
        z_static=gravity.local.z_static, z_relaxation=gravity.local.z_relaxation,
        strain=setup.strain, fe_slope=setup.fe_slope, unit_slope=setup.unit_slope,
        global_fits=global_fits, local_sweeps=tuning.local_sweeps, settings=fit_settings(scene),
        reference_fingerprint=reference_digest(reference_path, setup.fitted),
        experiments=setup.fitted, reference_path=str(reference_path), evaluations=evaluations,
        stage_times=stage_times, wall_time=time.perf_counter() - t0, warnings=warnings,
        versions=versions(), gradient=tuning.gradient.summary() if setup.gradient else {},
        body=body_summary.record, failures=validation.failures)
    write_calibration(out_path, result, checkpoint)
    return result


def write_calibration(out_path: Path, result: CalibrationResult, checkpoint: Checkpoint
                      ) -> None:
    """Write ``params.h5`` (atomically), then remove the checkpoint and log the warnings."""
    write_params(out_path, result)
    checkpoint.remove()
    for w in result.warnings:
        log.warning(w)
    log.info("calibration done in %.1f s; wrote %s", result.wall_time, out_path)


def unused_settings(settings: CalibrationSection, volume: bool, body: bool = False
                    ) -> list[str]:
    """A warning for each gradient-method setting that acts on nothing: a
    ``calibration.split_prior`` > 0 (it needs the gradient method with the volume term and
    per-tet kv), ``calibration.force_components = "vector"`` (the gradient method's cost),
    whole-body data (``body``: the scene runs the experiment) with the paper's method."""
    out = []
    if body and settings.body_data != "none" and settings.method != "gradient":
        out.append(f"calibration.body_data = \"{settings.body_data}\" has no effect: the "
                   "whole-body data are fitted by calibration.method = \"gradient\" (the "
                   "paper's method fits the surface curves only; their errors are reported)")
    if settings.split_prior > 0 and not (settings.method == "gradient" and volume
                                         and settings.kv_per_tet):
        out.append(f"calibration.split_prior = {settings.split_prior:g} has no effect: it "
                   "acts between springs and per-tet kv, which needs calibration.method = "
                   "\"gradient\", particle.volume = true and calibration.kv_per_tet = true")
    if settings.force_components != "normal" and settings.method != "gradient":
        out.append(f"calibration.force_components = \"{settings.force_components}\" has no "
                   "effect: the paper's method fits the normal force; the force vector is "
                   "fitted by calibration.method = \"gradient\"")
    return out


def _local_warnings(local_sweeps: dict[str, list[Sweep]], budget: int) -> list[str]:
    """At most one line per local phase and kind of problem, counting the sweeps' fits.

    The per-point warnings stay with each fit in ``params.h5``. After the first
    sweep, a fit that met the tolerances without lowering its cost was already
    at its optimum, so only unconverged ones count as "did not reduce".
    """
    out = []
    for phase, sweeps in local_sweeps.items():
        budgeted, stuck = [], []
        for k, sweep in enumerate(sweeps):
            n = len(sweep.fits)
            at_budget = [j for j, f in enumerate(sweep.fits) if not f.converged]
            no_gain = [j for j, f in enumerate(sweep.fits)
                       if f.cost >= f.initial_cost > 0 and (k == 0 or not f.converged)]
            budgeted += [f"sweep {k + 1} {_count(at_budget, n)}"] if at_budget else []
            stuck += [f"sweep {k + 1} {_count(no_gain, n)}"] if no_gain else []
        if budgeted:
            out.append(f"local {phase} phase: fits that stopped at their budget of {budget} "
                       "evaluations without meeting the tolerances: " + ", ".join(budgeted))
        if stuck:
            out.append(f"local {phase} phase: fits that did not reduce their cost: "
                       + ", ".join(stuck))
        if sweeps and not sweeps[0].accepted:  # later rejections just mean converged
            out.append(f"local {phase} sweep 1: no damped Jacobi update lowered the total cost; "
                       "the phase stopped there")
    return out


def _count(points: list[int], n: int) -> str:
    """``"3/31 (points [0, 4, 7])"``; the points are named only when few."""
    named = f" (points {points})" if len(points) <= 8 and len(points) < n else ""
    return f"{len(points)}/{n}{named}"


def local_validity(validity: Validity, glob: ConnectorParams, ceiling: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What local tuning keeps on each connector's validity range (the experiments' strains
    and the gravity release range): (low, high, floor, ceiling), each (E,). Every spring's
    tangent stays above the floor, or above the global spring's own minimum there where that
    one is lower (local tuning starts from the global fit and cannot make it valid; it must
    not make it worse), and at most ``ceiling`` (``calibration.stiffness_ceiling``) times the
    global spring's largest tangent there.

    Why a ceiling: a point's curve constrains its ring's spring law only on the few strains
    the ring reaches, and where the model's curve bends away from the FE's (a short connector
    of the ring nearly collapsing) the fit trades a little cost for ever steeper quadratics:
    on a 181-vertex liver one ring reached b = 4.2e6 N/m (the global fit: 610), a tangent
    6,250 times the global spring's largest, and the model needed 166 substeps per 1 ms.
    Bounded so, no connector outgrows the stiffest global spring by more than the factor,
    so the rigorous stable step (a bound linear in the connectors' tangents over the masses)
    shortens by at most its square root against the global model's."""
    bounds = (validity.low, validity.high)
    global_min, global_max = glob.extreme_tangent_stiffness(bounds)
    return (validity.low, validity.high, np.minimum(validity.floor, global_min),
            ceiling * global_max)


def fitted_loads(scene: Scene, ref: Reference) -> np.ndarray | None:
    """(L, N, 3) [m] the FE's displacements under the whole-body loads the scene's calibration
    fits about (``calibration.body_data`` with ``loads`` or ``loaded_modes``, the gradient
    method, the reference's experiment ``body`` holding them), else None."""
    if not (scene.calibration.method == "gradient" and scene.runs("body")
            and ref.body is not None and len(ref.body.load_accelerations)):
        return None
    if not set(body_kinds(scene.calibration.body_data)) & set(LOAD_KINDS):
        return None
    return ref.body.load_displacement


def spring_validity(ref: Reference, glob: GlobalParams, strain: StrainRange, floor: float,
                    gravity_margin: float, shape: np.ndarray | None = None, *,
                    gravity: bool = True, loads: np.ndarray | None = None) -> Validity:
    """Where a calibration keeps every spring stiff (the global fits on the overall range,
    the gradient fit per connector, local tuning as :func:`local_validity` says): the
    experiments' strain range united, per connector, with the gravity release range of the
    FE static sag (:func:`particle.stability.strain_range_for_release` with
    ``gravity_margin``; not if the reference has no gravity run or ``gravity`` is False: a
    scene without gravity experiments) and with the strains of the FE's states under the
    whole-body loads the fit uses, ``loads`` (L, N, 3) [m] displacements or None
    (:func:`particle.stability.strain_range_of_states` with ``gravity_margin``): a model
    fitted about a loaded state is used there, and a spring law left free beyond the other
    strains softens there until the model no longer carries the load (the fit then ends
    against that refusal instead of at its objective's least).
    The range depends on the geometry only; the floor is
    :func:`calibration.parametrisation.connector_floor`."""
    from particle.stability import strain_range_for_release, strain_range_of_states
    from particle.model import build_model

    n = len(ref.problem.mesh.edges)
    low, high = np.full(n, strain.low), np.full(n, strain.high)
    with_sag = gravity and ref.gravity is not None
    if with_sag or loads is not None:
        model = build_model(ref.problem, ref.material.density, glob.connector_params(n, shape))
    if with_sag:
        lo, hi = strain_range_for_release(model, ref.gravity.static_displacement, gravity_margin)
        low, high = np.minimum(low, lo), np.maximum(high, hi)
        log.info("springs kept stiff on the experiments' strains and the gravity "
                 "release range of the FE sag, [%.3g, %.3g] overall", low.min(), high.max())
    if loads is not None:
        lo, hi = strain_range_of_states(model, loads, gravity_margin)
        low, high = np.minimum(low, lo), np.maximum(high, hi)
        log.info("and on the strains of the FE's states under the %d fitted body loads: "
                 "[%.3g, %.3g] overall", len(loads), low.min(), high.max())
    return Validity(low, high, connector_floor(floor, glob.K0, shape), glob.K0, strain.scale)
