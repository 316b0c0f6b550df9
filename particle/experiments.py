"""Dynamic experiments with the explicit integrator: gravity release and ramp-and-hold relaxation.

The static experiments (indentation, quasi-static relaxation) are the batch
evaluators of :mod:`particle.evaluators`; the static gravity sag is
:func:`particle.statics.gravity_static`. Conventions as everywhere in forcecal:
SI units; indentation pushes the test particle along its inward unit normal by
d >= 0; the reported force is the force the indenter applies to that particle
(minus the connector forces on it), ``force . normal`` positive when pushing in.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from forcecal.errors import ParameterError
from forcecal.scene import ParticleSection
from particle.guard import energy_bound
from particle.integrator import VerletIntegrator
from particle.stability import (DEFAULT_STRAIN_RANGE, check_time_step, connector_strains,
                                critical_time_step, release_strain_range, release_volume_range,
                                resolve_time_step)
from particle.model import Model, Prescribed
from particle.params import StrainBounds
from particle.statics import check_stiffness, gravity_static, reaching

log = logging.getLogger(__name__)


def sample_steps(times: np.ndarray, dt: float) -> tuple[float, np.ndarray]:
    """Largest step <= ``dt`` that divides the spacing of uniform ``times``, and their step indices.

    Returns (step [s], (S,) int64 step index of each time). Non-uniform times
    are recorded at the nearest step (error <= step/2).
    """
    check_time_step(dt, math.inf)
    times = np.asarray(times, dtype=np.float64)
    if len(times) == 0 or times[0] < 0 or np.any(np.diff(times) <= 0):
        raise ParameterError("record times must be >= 0 and increasing")
    spacing = float(np.diff(times).min()) if len(times) > 1 else max(float(times[0]), dt)
    step = spacing / math.ceil(spacing / dt * (1.0 - 1e-12))
    return step, np.rint(times / step).astype(np.int64)


def gravity_dynamic(model: Model, gravity: np.ndarray, duration: float, dt: float,
                    record_times: np.ndarray, *, damping: float = 0.0, skip: bool = True,
                    strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                    volume_range: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(S, N, 3) displacements [m] at ``record_times`` after release from rest under gravity.

    Explicit Verlet with the paper's arm recursion, fixed particles clamped,
    starting undeformed and at rest at t = 0. The step is the largest one <=
    ``dt`` that divides the record spacing (see :func:`sample_steps`), so
    samples fall exactly on steps; ``dt`` above the stability limit for
    ``strain_range`` (a pair or per-connector arrays, e.g.
    :func:`~particle.stability.strain_range_for_release`) and ``volume_range`` (each
    tet's volume ratios [1], e.g. :func:`~particle.stability.release_volume_range`;
    None: those of the strain range), or a connector or tet leaving its range during the
    run, raises :class:`~forcecal.errors.StabilityError`.
    """
    step, record_steps = sample_steps(record_times, dt)
    if record_times[-1] > duration * (1 + 1e-9):
        raise ParameterError(f"record time {record_times[-1]} s is after the end of the run "
                             f"({duration} s)")
    n_steps = max(int(record_steps[-1]), math.ceil(duration / step - 1e-9))
    state = model.state()
    positions = VerletIntegrator(damping, strain_range=strain_range,
                                 volume_range=volume_range).simulate(
        model, state, step, n_steps, gravity=gravity, record_nodes=np.arange(model.n_particles),
        record_steps=record_steps, skip=skip)
    log.info("gravity: %d steps of %.3g s", n_steps, step)
    return positions - model.rest_positions[None]


@dataclass(frozen=True, eq=False)
class GravityTest:
    """One particle model's gravity test (:func:`gravity_test`).

    Attributes:
        static_displacement: (N, 3) float64, static sag [m].
        displacement: (S, N, 3) float64, dynamic displacements at the record times [m];
            None without the dynamic release.
        dt: explicit time step used [s].
        critical_dt: stability limit of that step [s].
        static_time: wall time of the static solve [s].
        dynamic_time: wall time of the dynamic run [s], kernel compiled beforehand.
        strain_min, strain_max: most compressive / most tensile connector strain reached [1].
    """
    static_displacement: np.ndarray
    displacement: np.ndarray | None
    dt: float
    critical_dt: float
    static_time: float
    dynamic_time: float
    strain_min: float
    strain_max: float


def gravity_test(model: Model, gravity: np.ndarray, times: np.ndarray | None, *,
                 load_steps: int, particle: ParticleSection,
                 strain_range: tuple[float, float], name: str) -> GravityTest:
    """Static sag and dynamic release of ``model`` under ``gravity`` [m/s^2] (``times`` None:
    the static sag only, with the step the release would take).

    The static sag (:func:`gravity_static_test`) and the release from it
    (:func:`gravity_release`, sampled at ``times`` [s]); see those.
    """
    static = gravity_static_test(model, gravity, load_steps=load_steps, particle=particle,
                                 strain_range=strain_range, name=name)
    if times is None:
        return static
    return gravity_release(model, gravity, times, static, particle=particle,
                           strain_range=strain_range, name=name)


def gravity_static_test(model: Model, gravity: np.ndarray, *, load_steps: int,
                        particle: ParticleSection, strain_range: tuple[float, float],
                        name: str) -> GravityTest:
    """The static sag of ``model`` under ``gravity`` [m/s^2] and the step its release would
    take (a :class:`GravityTest` without ``displacement``).

    The static sag (:func:`~particle.statics.gravity_static`, ``load_steps``) uses the
    long-term springs. ``strain_range`` is where the springs were calibrated (and must be
    positive); the sag is refused (:class:`ParameterError`) if a spring's K(eps) becomes
    <= 0 at a strain it reaches, and the strain extremes are recorded so that leaving the
    calibrated range can be reported. The explicit step is chosen for each connector's
    strain range and each tet's volume ratio range of the release (:func:`release_ranges`
    of the static sag, ``particle.strain_margin``); an explicit ``particle.dt`` must be
    stable over the calibrated range as well. ``name`` names the model in errors and the
    log.
    """
    t0 = time.perf_counter()
    static = gravity_static(model, gravity, load_steps=load_steps, strain_range=strain_range)
    t1 = time.perf_counter()
    eps = connector_strains(model, static)
    with reaching(lambda: 1.0):  # the whole load was carried
        check_stiffness(model, eps, f"static sag of the {name} model")
        strains, volumes = release_ranges(model, static, particle, strain_range)
        critical = critical_time_step(model, strain_range=strains, volume_range=volumes,
                                      damping=particle.damping)
    dt = resolve_time_step(particle, critical)
    log.info("gravity, %s model: max static sag %.3g mm, strains [%.3g, %.3g], static %.2f s",
             name, 1e3 * np.linalg.norm(static, axis=1).max(), eps.min(), eps.max(), t1 - t0)
    return GravityTest(static, None, dt, critical, t1 - t0, 0.0, float(eps.min()),
                       float(eps.max()))


def gravity_release(model: Model, gravity: np.ndarray, times: np.ndarray, static: GravityTest,
                    *, particle: ParticleSection, strain_range: tuple[float, float],
                    name: str) -> GravityTest:
    """``static`` (:func:`gravity_static_test` of the same model) completed by the release
    from rest in the undeformed shape at t = 0, sampled at ``times`` [s], at its step.

    The step was chosen for each connector's strain range and each tet's volume ratio range
    of the release (:func:`release_ranges`), which the run verifies
    (:class:`~forcecal.errors.StabilityError` if a connector or tet leaves its range); a
    spring whose K(eps) <= 0 at a sample is refused (:class:`ParameterError`). Either error
    records in ``reached`` the time [s] the release had reached.
    """
    strains, volumes = release_ranges(model, static.static_displacement, particle,
                                      strain_range)
    # a few steps first so that dynamic_time measures the simulation, not numba compiling
    # (or loading from its cache) this model's kernel specialisation
    gravity_dynamic(model, gravity, float(times[1]), static.dt, times[:2],
                    damping=particle.damping, strain_range=strains, volume_range=volumes)
    t2 = time.perf_counter()
    dynamic = gravity_dynamic(model, gravity, float(times[-1]), static.dt, times,
                              damping=particle.damping, strain_range=strains,
                              volume_range=volumes)
    t3 = time.perf_counter()
    strain = np.vstack([connector_strains(model, static.static_displacement)[None],
                        connector_strains(model, dynamic)])
    for t, sample in zip(times, strain[1:]):
        with reaching(lambda: t):
            check_stiffness(model, sample, f"gravity dynamics of the {name} model at "
                            f"t = {t:.4g} s")
    log.info("gravity, %s model: dt %.3g s (limit %.3g s), strains [%.3g, %.3g], dynamic "
             "%.2f s (%d samples)", name, static.dt, static.critical_dt, strain.min(),
             strain.max(), t3 - t2, len(times))
    return dataclasses.replace(static, displacement=dynamic, dynamic_time=t3 - t2,
                               strain_min=float(strain.min()), strain_max=float(strain.max()))


def release_ranges(model: Model, static: np.ndarray, particle: ParticleSection,
                   strain_range: tuple[float, float]
                   ) -> tuple[StrainBounds, tuple[np.ndarray, np.ndarray] | None]:
    """(each connector's strain range (lo (E,), hi (E,)) [1], each tet's volume ratio range
    (J_lo (T,), J_hi (T,)) [1] or None without the volume term) of the release from the
    static sag ``static`` (N, 3) [m], the ranges its step is chosen for and the run verifies:
    :func:`release_strain_range` (``particle.strain_margin``), widened to the calibrated
    ``strain_range`` for an explicit ``particle.dt``, which must be stable there too, and
    :func:`release_volume_range` of the static sag on that strain range."""
    strains = release_strain_range(model, static, particle.strain_margin)
    if particle.dt != "auto":
        strains = (np.minimum(strains[0], strain_range[0]),
                   np.maximum(strains[1], strain_range[1]))
    return strains, release_volume_range(model, static, particle.strain_margin, strains)


def relaxation_dynamic(model: Model, node: int, normal: np.ndarray, times: np.ndarray,
                       depths: np.ndarray, dt: float, *, damping: float = 0.0,
                       progress: bool = True) -> np.ndarray:
    """(S, 3) indenter force [N] at ``times`` of a ramp-and-hold test run with explicit Verlet.

    The particle follows ``depths`` along ``normal`` piecewise linearly in time
    (from rest at t = 0); the arms use the paper's recursion at the explicit
    step. Each interval between samples is split into equal steps <= ``dt``,
    so the force is evaluated exactly at the sample times. A progress bar
    over the samples shows on a terminal unless ``progress`` is False.
    """
    node = int(model.check_nodes([node], "relaxation test particle")[0])
    check_time_step(dt, math.inf)
    times = np.asarray(times, dtype=np.float64)
    depths = np.asarray(depths, dtype=np.float64)
    if times.shape != depths.shape or np.any(np.diff(np.r_[0.0, times]) <= 0):
        raise ParameterError("relaxation times must be increasing, > 0 and match the depths")
    path = model.rest_positions[node] + np.r_[0.0, depths][:, None] * np.reshape(normal, 3)
    motion = Prescribed([node], np.r_[0.0, times], path[:, None, :])
    integrator = VerletIntegrator(damping)
    state = model.state()
    forces = np.empty((len(times), 3))
    for s, t1 in enumerate(tqdm(times, desc=f"relaxation of particle {node}", unit="sample",
                                disable=None if progress else True, leave=False)):
        n = math.ceil((t1 - state.t) / dt * (1.0 - 1e-12))
        step = (t1 - state.t) / n
        run = integrator.prepare(model, step, prescribed_nodes=motion.nodes)
        run(state, n, (motion.times, motion.positions),
            energy_bound(model, state, step, n, None, motion))
        state.t = t1  # remove the round-off of n x step
        forces[s] = -run.force_on(state, node)
    return forces
