"""Benchmarks of the particle engine: functions that return JSON-ready dicts.

``pipelines.bench`` calls them for ``make bench`` (-> ``runs/bench/bench.json``);
every function can also be called alone. Timings are wall-clock
(``time.perf_counter``) *and* CPU time of this process (``time.process_time``):
on a shared machine the CPU time is the better measure of the code. The
numbers are single-core, except :func:`haptic_latency` with ``threads`` > 1.
Nothing here asserts a timing; the goals are reported next to the measurements.

Parameters are uniform (the scene's Prony split of a spring stiffness ``K0``,
30 N/m on the default liver, scaled with the mean edge length on other meshes
so that every mesh models the same material); ``a = b = 0`` unless stated.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from typing import Callable

import numpy as np

from forcecal.errors import ParameterError
from forcecal.mesh import TetMesh
from forcecal.point_selection import fixed_nodes
from forcecal.problem import Problem, build_problem
from forcecal.scene import ParticleSection, Scene
from forcecal.schedules import indentation_depths, relaxation_schedule
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.experiments import gravity_dynamic
from particle.haptics import HapticSession
from particle.integrator import VerletIntegrator
from particle.stability import DEFAULT_STRAIN_RANGE, critical_time_step
from particle.model import Model, build_model, spatial_order
from particle.params import PARAM_NAMES, ConnectorParams, StrainBounds, viscoelastic_params
from particle.reference_numpy import step_numpy

log = logging.getLogger(__name__)

LIVER_K0 = 30.0  # N/m, on the default liver (mean edge 20.5 mm)
LIVER_MEAN_EDGE = 0.0205  # m
LARGE_MESH_LENGTH = 0.008  # m: generate_liver(0.008) has 12062 connectors
DT_SAFETY = ParticleSection().dt_safety  # the scene default: fraction of the limit used as step
# strains the throughput run (a release from rest under gravity) is verified for: the uniform
# parameters are not fitted to the organ's weight, and on the >= 10k-connector liver the
# release compresses a connector by 0.53, beyond the default +-0.5
THROUGHPUT_STRAIN_RANGE = (-0.8, 1.0)
SKIP_STIFFNESS = 4.0  # x K0 in the term-skipping runs: their undamped release stays in +-0.5


def _timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(wall, cpu) seconds of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - wall, time.process_time() - cpu


def scene_model(scene: Scene, mesh: TetMesh | None = None,
                fixed: np.ndarray | None = None) -> Model:
    """Particle model of ``mesh`` (default: the scene's) with the uniform benchmark parameters."""
    mesh = build_problem(scene).mesh if mesh is None else mesh
    fixed = fixed_nodes(mesh, scene.fixed.axis, scene.fixed.side,
                        scene.fixed.tolerance) if fixed is None else fixed
    m = scene.material
    K0 = LIVER_K0 * float(mesh.edge_lengths.mean()) / LIVER_MEAN_EDGE
    params = viscoelastic_params(len(mesh.edges), K0, g=m.prony_g, tau=m.prony_tau)
    return build_model(mesh, m.density, params, fixed=fixed)


def step_throughput(model: Model, *, steps: int = 2000, numpy_steps: int = 50) -> dict:
    """Connector updates per second of the compiled loop vs the numpy step (gravity + arms)."""
    gravity = np.array([0.0, 0.0, -9.81])
    dt = 0.5 * critical_time_step(model, strain_range=THROUGHPUT_STRAIN_RANGE)
    integrator = VerletIntegrator(strain_range=THROUGHPUT_STRAIN_RANGE)
    integrator.simulate(model, model.state(), dt, 1, gravity=gravity)  # compile outside the clock
    compiled = _timed(lambda: integrator.simulate(model, model.state(), dt, steps,
                                                  gravity=gravity))
    state = model.state()

    def numpy_run():
        for _ in range(numpy_steps):
            step_numpy(model, state, dt, gravity=gravity)

    reference = _timed(numpy_run)
    rate = model.n_connectors * steps / compiled[1]
    numpy_rate = model.n_connectors * numpy_steps / reference[1]
    return {"connectors": model.n_connectors, "particles": model.n_particles,
            "compiled_updates_per_s": rate, "numpy_updates_per_s": numpy_rate,
            "speedup": rate / numpy_rate, "compiled_wall_s": compiled[0],
            "compiled_cpu_s": compiled[1], "steps": steps, "goal_speedup": 20.0}


def gravity_realtime(model: Model, gravity: np.ndarray, *, duration: float = 3.0,
                     record_interval: float = 0.005, safety: float = DT_SAFETY,
                     skip: bool = True,
                     strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                     volume_range: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Wall/CPU time and real-time factor of ``duration`` s of gravity dynamics.

    Every particle is recorded at ``record_interval``, as the gravity stage does; the
    step is ``safety`` x the stability limit over ``strain_range`` and ``volume_range``
    (each tet's volume ratios [1], None: those of the strain range), which the run verifies.
    """
    ranges = {"strain_range": strain_range, "volume_range": volume_range}
    dt = safety * critical_time_step(model, **ranges)
    times = np.arange(0.0, duration + 0.5 * record_interval, record_interval)
    gravity_dynamic(model, gravity, 2 * record_interval, dt, times[:3], skip=skip,
                    **ranges)  # compile
    wall, cpu = _timed(lambda: gravity_dynamic(model, gravity, duration, dt, times, skip=skip,
                                               **ranges))
    return {"duration_s": duration, "dt_s": dt, "steps": int(np.ceil(duration / dt)),
            "wall_s": wall, "cpu_s": cpu, "realtime_factor_wall": duration / wall,
            "realtime_factor_cpu": duration / cpu, "goal_wall_s": 0.05, "paper_wall_s": 1.3}


def skip_timings(model: Model, gravity: np.ndarray, *, duration: float = 3.0) -> dict:
    """The same runs with unneeded terms compiled out (skip) and kept at zero (no skip).

    ``viscoelastic``: gravity + arms, linear springs (the nonlinear term skipped);
    ``elastic``: gravity, no arms, linear springs (arms and nonlinear term skipped);
    ``free``: no gravity, no arms (gravity, arms, nonlinear term and damping skipped).

    The springs are :data:`SKIP_STIFFNESS` times stiffer than the model's, so that the
    undamped elastic release stays in the default strain range its step is verified for.
    """
    linear = model.with_params(dataclasses.replace(
        model.params, K0=SKIP_STIFFNESS * model.params.K0, a=0 * model.params.a,
        b=0 * model.params.b))
    dt = 0.5 * critical_time_step(linear)
    steps = int(np.ceil(duration / dt))
    out = {"dt_s": dt, "steps": steps}
    for name, g, arms in (("viscoelastic", gravity, True), ("elastic", gravity, False),
                          ("free", None, False)):
        row = {}
        for skip in (True, False):
            integrator = VerletIntegrator()
            integrator.simulate(linear, linear.state(), dt, 1, gravity=g, arms=arms, skip=skip)
            state = linear.state()
            if g is None:  # something to move: the state of a short gravity run
                integrator.simulate(linear, state, dt, 100, gravity=gravity, arms=arms)
            wall, cpu = _timed(lambda: integrator.simulate(linear, state, dt, steps, gravity=g,
                                                           arms=arms, skip=skip))
            row["skip" if skip else "no_skip"] = {"wall_s": wall, "cpu_s": cpu}
        row["cpu_ratio"] = row["no_skip"]["cpu_s"] / row["skip"]["cpu_s"]
        out[name] = row
    return out


def haptic_drag(model: Model, node: int, normal: np.ndarray, dt: float, *, calls: int = 1000,
                depth: float = 0.005, threads: int = 1, inertia: np.ndarray | None = None,
                strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                envelope: float | None = None, ramp_calls: int | None = None) -> dict:
    """``calls`` periods (1 ms each) of :class:`HapticSession` dragging ``node`` ``depth`` [m]
    along ``normal`` (linearly over the first ``ramp_calls``, default a quarter of the
    calls, then held), timed call by call.

    ``dt`` is the session's largest step [s], ``threads``, ``inertia`` and
    ``strain_range`` (verified by the session) and ``envelope`` (bands that follow the
    state) go to the session. Returns the session's ``substeps`` and ``dt_s`` (with
    ``envelope``: the most substeps of any call and its step; ``recentred``, how often
    the bands were re-centred), ``latencies_us`` (calls,) [us] of wall time per call,
    ``cpu_us`` [us] the process CPU time per call (less sensitive to a busy machine than
    wall time: time spent waiting for a core is not counted), ``forces`` (calls, 3)
    [N], the force on the tool after each call, ``recentring`` (calls,) bool, the calls that
    re-centred the bands (their time included), and ``max_abs_strain`` [1], the largest
    connector |strain| at the end of a call (outside the clock). One call before the
    clock compiles the kernels.
    """
    session = HapticSession(model, dt, threads=threads, inertia=inertia,
                            strain_range=strain_range, envelope=envelope)
    start = model.rest_positions[node]
    session.step(node, start)  # compile outside the clock (the tissue stays at rest)
    latencies = np.empty(calls)
    forces = np.empty((calls, 3))
    strain = np.empty(calls)
    recentring = np.zeros(calls, dtype=bool)
    cpu = 0.0
    substeps = session.substeps
    ramp = calls / 4 if ramp_calls is None else ramp_calls
    for k in range(calls):
        target = start + depth * min(1.0, k / ramp) * normal
        recentred = session.recentred
        c0, t0 = time.process_time(), time.perf_counter()
        forces[k] = session.step(node, target)
        latencies[k] = time.perf_counter() - t0
        cpu += time.process_time() - c0
        recentring[k] = session.recentred > recentred
        strain[k] = np.max(np.abs(session.state.dx_prev / model.rest_lengths))
        substeps = max(substeps, session.substeps)
    return {"substeps": substeps, "dt_s": session.period / substeps,
            "latencies_us": 1e6 * latencies, "recentring": recentring,
            "recentred": session.recentred,
            "cpu_us": 1e6 * cpu / calls, "forces": forces, "max_abs_strain": float(strain.max())}


def haptic_latency(model: Model, node: int, normal: np.ndarray, *, calls: int = 2000,
                   depth: float = 0.005, safety: float = DT_SAFETY, threads: int = 1,
                   renumber: bool = False) -> dict:
    """Per-call latency [us] of :meth:`HapticSession.step` (1 ms of simulated time per call).

    The largest step is ``safety`` x the stability limit over the default strain range
    (+-0.5), which the session monitors. ``threads`` > 1: the session's multi-threaded
    step (numba's thread count is set for each call and restored), whose latency depends
    on every thread's core being free; ``load_average`` (1 min, from os.getloadavg) is
    reported next to it. ``renumber``: measure the model with its particles renumbered
    along its longest axis (:func:`~particle.model.spatial_order`, the tool node mapped), the
    numbering in which the threads' connector blocks share the fewest particles.
    """
    if renumber:
        order = spatial_order(model)
        model, _ = model.renumbered(order)
        node = int(np.nonzero(order == node)[0][0])
    drag = haptic_drag(model, node, normal, safety * critical_time_step(model), calls=calls,
                       depth=depth, threads=threads)
    us = drag["latencies_us"]
    return {"connectors": model.n_connectors, "substeps": drag["substeps"],
            "dt_s": drag["dt_s"], "threads": threads, "renumbered": renumber,
            "load_average": os.getloadavg()[0],
            "median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
            "max_us": float(us.max()), "goal_us": 100.0}


def release_history(model: Model, gravity: np.ndarray, dt: float, node: int, *,
                    duration: float = 3.0, record_interval: float = 0.005,
                    strain_range: StrainBounds = THROUGHPUT_STRAIN_RANGE,
                    inertia: np.ndarray | None = None, checked: bool = True) -> np.ndarray:
    """(S, 3) displacement [m] of particle ``node`` every ``record_interval`` over
    ``duration`` s of release from rest under ``gravity`` (explicit steps of at most ``dt``
    that divide the interval; strains verified in ``strain_range``; optional mass
    scaling ``inertia``; ``checked`` False: ``dt`` is not checked against the limit of
    ``strain_range`` nor the strains monitored, for a step verified elsewhere, e.g. on bands
    that follow the state)."""
    steps_per_record = math.ceil(record_interval / dt * (1.0 - 1e-12))
    step = record_interval / steps_per_record
    samples = int(round(duration / record_interval))
    record_steps = steps_per_record * np.arange(samples + 1)
    history = VerletIntegrator(strain_range=strain_range).simulate(
        model, model.state(), step, int(record_steps[-1]), gravity=gravity,
        record_nodes=np.array([node]), record_steps=record_steps, inertia=inertia,
        _check_dt=checked)
    return history[:, 0] - model.rest_positions[node]


def relative_history_error(history: np.ndarray, reference: np.ndarray) -> float:
    """RMS over samples of ``|history - reference|`` over ``max |reference|`` [1]; inputs (S, 3)
    (the dynamic-error definition of docs/results.md, applied to a variant against the float64 run)."""
    scale = float(np.max(np.linalg.norm(reference, axis=1)))
    if not scale > 0.0:
        raise ParameterError("the reference history is identically zero: no scale to compare "
                             "against (a fixed particle?)")
    return float(np.sqrt(np.mean(np.sum((history - reference) ** 2, axis=1)))) / scale


def _perturbed(params: ConnectorParams, rng: np.random.Generator, rel: float) -> ConnectorParams:
    """Every connector's parameters scaled by 1 + rel N(0, 1): a calibration-like step."""
    return dataclasses.replace(params, **{n: getattr(params, n) * (
        1.0 + rel * rng.standard_normal(params.n_connectors)) for n in PARAM_NAMES})


def evaluator_timings(model: Model, problem: Problem, scene: Scene, *, points: int = 4,
                      calls: int = 3, nonlinear: tuple[float, float] = (10.0, 50.0),
                      perturbation: float = 0.01) -> dict:
    """Warm per-point time [ms] of the indentation and relaxation evaluators.

    Parameters: the model's, with ``a, b = nonlinear`` [N/m]; each timed call
    perturbs every connector's seven parameters by ``perturbation`` (relative,
    random), as calibration's local steps do.
    """
    rng = np.random.default_rng(0)
    base = dataclasses.replace(model.params, a=np.full(model.n_connectors, nonlinear[0]),
                               b=np.full(model.n_connectors, nonlinear[1]))
    selected = np.arange(points)
    times, depths = relaxation_schedule(scene.relaxation)
    out = {}
    for name, ev, target in (
            ("indentation", IndentationEvaluator(model, problem.test_points, problem.normals,
                                                 indentation_depths(scene.indentation)), 10.0),
            ("relaxation", RelaxationEvaluator(model, problem.test_points, problem.normals,
                                               times, depths), 30.0)):
        cold = _timed(lambda: ev(base, selected))
        samples = []
        for _ in range(calls):
            params = _perturbed(base, rng, perturbation)
            samples.append(_timed(lambda: ev(params, selected)))
        wall, cpu = np.array(samples).T / points * 1e3
        out[name] = {"samples": len(ev.depths), "cold_ms_per_point": 1e3 * cold[1] / points,
                     "warm_ms_per_point_wall": float(np.median(wall)),
                     "warm_ms_per_point_cpu": float(np.median(cpu)),
                     "factorizations": sum(s.factorizations for s in ev._solvers.values()),
                     "goal_ms": target}
    return out
