"""Explicit time integration: position Verlet and its divergence guard.

:class:`VerletIntegrator` advances a :class:`~particle.model.State` in place
with the compiled loop :func:`particle.kernels.run_verlet`. Which force terms
the loop contains is decided once per run (:class:`Terms`): gravity, Maxwell
arms, nonlinear springs and damping are compiled out when a run does not need
them; ``skip=False`` keeps every term (with zero values) so benchmarks and tests
can run the same experiment both ways. The stable step and the strain ranges it
holds on are :mod:`particle.stability`'s.
"""

from __future__ import annotations

import logging
import math
import operator
from dataclasses import dataclass

import numba
import numpy as np

from forcecal.errors import ParameterError, StabilityError
from particle import kernels
from particle.model import ConnectorParams, Model, State, StrainBounds, connector_strain_bounds
from particle.stability import (DEFAULT_STRAIN_RANGE, check_time_step, critical_time_step,
                                inertial_model)
from particle.stability import strain_range_for_release  # noqa: F401  (calibration/ imports it here)
from particle.statics import check_stiffness, check_volumes
from particle.volume import (node_volume_stiffness, signed_volumes, tet_name, volume_energy,
                             volume_ratio_range)

log = logging.getLogger(__name__)

# the kinetic energy may exceed the work the loads can do by this factor before a run is
# declared divergent: a real run stays far below, an unstable one grows exponentially
ENERGY_MARGIN = 100.0


def check_threads(threads: int) -> int:
    """``threads`` as an int, if it is an integer in 1 .. ``numba.config.NUMBA_NUM_THREADS``
    (numba's thread pool, fixed at start-up by the NUMBA_NUM_THREADS environment variable);
    else :class:`ParameterError`."""
    try:
        n = operator.index(threads)
    except TypeError:
        n = None
    limit = numba.config.NUMBA_NUM_THREADS
    if n is None or not 1 <= n <= limit:
        raise ParameterError(f"threads = {threads!r} must be an integer in 1..{limit} (numba's "
                             "thread pool; set NUMBA_NUM_THREADS before start-up for more)")
    return int(n)


def thread_blocks(model: Model, active: np.ndarray, threads: int) -> tuple:
    """Work split and scratch of the ``threads``-thread step (see :class:`Run`).

    Returns (thread_forces (T, N, 3) [N], edge_starts (T+1,) uint64, node_starts
    (T+1,) uint64, outside (T,) int64, energy (T,)): thread t takes the connectors
    ``edge_starts[t] ..`` and the ``active`` nodes (k,) ``node_starts[t] ..``
    (contiguous blocks of equal size); the last two are its strain-check and
    energy results.
    """
    def starts(n: int) -> np.ndarray:  # unsigned, as the index views (kernels.index_view)
        return np.linspace(0, n, threads + 1).round().astype(np.uint64)

    return (np.zeros((threads, model.n_particles, 3)), starts(model.n_connectors),
            starts(len(active)), np.empty(threads, np.int64), np.empty(threads))


@dataclass(frozen=True)
class Terms:
    """Force terms compiled into a run (chosen once per run, never tested in the inner loop)."""
    gravity: bool
    arms: bool
    nonlinear: bool
    damping: bool

    @classmethod
    def select(cls, params: ConnectorParams, *, gravity: np.ndarray | None, arms: bool,
               damping: float, skip: bool = True) -> "Terms":
        """The terms a run needs; with ``skip=False`` every term (zero ones included)."""
        if not skip:
            return cls(gravity=True, arms=True, nonlinear=True, damping=True)
        return cls(gravity=gravity is not None and bool(np.any(gravity)), arms=arms,
                   nonlinear=not params.is_linear, damping=damping > 0.0)


@dataclass(frozen=True, eq=False)
class Prescribed:
    """Particles whose positions follow piecewise-linear keyframes (held after the last).

    Attributes:
        nodes: (k,) int64, prescribed particle ids.
        times: (K,) float64, increasing keyframe times [s].
        positions: (K, k, 3) float64, positions at the keyframes [m].
    """
    nodes: np.ndarray
    times: np.ndarray
    positions: np.ndarray

    def __post_init__(self) -> None:
        nodes = np.atleast_1d(np.asarray(self.nodes, dtype=np.int64))
        times = np.atleast_1d(np.asarray(self.times, dtype=np.float64))
        pos = np.asarray(self.positions, dtype=np.float64).reshape(len(times), len(nodes), 3)
        if len(times) == 0 or np.any(np.diff(times) <= 0) or not np.all(np.isfinite(pos)):
            raise ParameterError("prescribed motion needs increasing keyframe times and finite "
                                 "positions")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", pos)

    @classmethod
    def hold(cls, nodes, positions) -> "Prescribed":
        """Nodes held at fixed positions (k, 3) [m]."""
        return cls(nodes, [0.0], np.asarray(positions, dtype=np.float64)[None])


def energy_bound(model: Model, state: State, dt: float, n_steps: int,
                 gravity: np.ndarray | None, prescribed: Prescribed | None) -> float:
    """Kinetic energy [J] above which a run is declared divergent.

    ``ENERGY_MARGIN`` x (present kinetic + elastic energy + the work gravity can
    do in the run (falling the model's size, or freely for the run's duration)
    + the work prescribed motion can do (moving each prescribed node its
    largest keyframe distance against its connectors, plus dragging the whole
    mass at the keyframes' fastest speed)), plus a floor for runs at rest. The
    elastic energy is ``K(eps) dx^2/2`` at the state's strains; a state where
    a spring's K(eps) <= 0 raises :class:`ParameterError`.
    """
    m = model.masses
    p = model.params
    size = float(np.linalg.norm(np.ptp(model.rest_positions, axis=0)))
    total_mass = float(m.sum())
    duration = n_steps * dt
    v_prev = (state.x - state.x_prev) / (state.dt or dt)
    energy = 0.5 * float(np.sum(m[:, None] * v_prev ** 2))
    lengths = np.linalg.norm(state.x[model.edges[:, 1]] - state.x[model.edges[:, 0]], axis=1)
    dx = lengths - model.rest_lengths
    strain = np.clip(dx / model.rest_lengths, -0.99, None)
    # prepare() refused springs that go soft in the run's strain range; a state outside it
    # (an unmonitored run) where one does is refused too, not bounded with |K|
    check_stiffness(model, strain, f"explicit run from t = {state.t:.6g} s")
    energy += float(np.sum(0.5 * p.stiffness(strain) * dx ** 2))
    if p.kv is not None:
        check_volumes(model, state.x, f"explicit run from t = {state.t:.6g} s")
        energy += volume_energy(state.x, model.tets, model.rest_volumes, p.kv)
    energy += float(np.sum(state.arm_force ** 2 / (2.0 * p.arm_stiffness)))
    if gravity is not None:
        g = float(np.linalg.norm(gravity))
        energy += total_mass * g * (size + 0.5 * g * duration ** 2)
    if prescribed is not None:
        stiff = np.bincount(model.edges.ravel(), np.repeat(p.K0 + p.k1 + p.k2, 2),
                            model.n_particles)
        if p.kv is not None:
            stiff = stiff + node_volume_stiffness(model)
        stiff = stiff[prescribed.nodes]
        reach = np.linalg.norm(prescribed.positions - state.x[prescribed.nodes][None], axis=2)
        energy += float(np.sum(stiff * (reach.max(axis=0) + size) ** 2))
        if len(prescribed.times) > 1:
            speed = (np.linalg.norm(np.diff(prescribed.positions, axis=0), axis=2)
                     / np.diff(prescribed.times)[:, None]).max()
            energy += total_mass * float(speed) ** 2
    floor = 0.5 * total_mass * (1e-6 * size / dt) ** 2
    return ENERGY_MARGIN * energy + floor


class VerletIntegrator:
    """Position (Stoermer) Verlet with the paper's Maxwell-arm recursion.

    ``x^{t+dt} = 2 x^t - x^{t-dt} + dt^2 f(x^t)/m`` on free, non-prescribed
    particles, second order. Start-up from rest: a State that has never been
    stepped (``state.dt is None``, ``x_prev = x``, v = 0) takes
    ``x^{dt} = x^0 + dt^2/2 a^0`` (the Taylor step) instead of the plain
    formula's ``x^0 + dt^2 a^0``. If the step changes between runs, ``x_prev``
    is rescaled to keep the velocity ``(x - x_prev)/dt``.

    Each step evaluates, in this order: connector elongations, the arm
    recursion ``F^t = r F^{t-1} + c (dx^t - dx^{t-1})`` with the paper's
    coefficients (:meth:`ConnectorParams.arm_recursion`), spring + arm tension,
    gravity ``m g``, and optional mass-proportional damping ``-gamma m v`` with
    the backward-difference velocity.

    A step is accepted only below :func:`critical_time_step` for ``strain_range``,
    and that bound holds only while the strains stay in the range: every run
    with a checked step verifies it, at each divergence check, and stops with
    :class:`StabilityError` naming the first connector outside it.

    Args:
        damping: gamma [1/s], global mass-proportional viscous damping (0 = off).
        check_every: steps between two divergence checks (non-finite positions,
            kinetic energy beyond the bound the loads allow, connector strains
            outside ``strain_range``).
        strain_range: connector strains the runs stay in [1]: one (lo, hi) pair or
            per-connector (lo (E,), hi (E,)) arrays; the stability limit is the one of
            this range.
    """

    def __init__(self, damping: float = 0.0, *, check_every: int = 64,
                 strain_range: StrainBounds = DEFAULT_STRAIN_RANGE) -> None:
        if not (math.isfinite(damping) and damping >= 0.0):
            raise ParameterError(f"damping = {damping} 1/s must be >= 0")
        if check_every < 1:
            raise ParameterError(f"check_every = {check_every} must be >= 1")
        self.damping = float(damping)
        self.check_every = int(check_every)
        self.strain_range = strain_range
        self._critical: tuple[Model, float] | None = None
        self._inertial: tuple[Model, np.ndarray, Model] | None = None

    def critical_time_step(self, model: Model) -> float:
        """:func:`critical_time_step` of ``model`` (cached for the last model seen)."""
        if self._critical is None or self._critical[0] is not model:
            value = critical_time_step(model, strain_range=self.strain_range,
                                       damping=self.damping)
            self._critical = (model, value)
        return self._critical[1]

    def stability_model(self, model: Model, inertia: np.ndarray | None) -> Model:
        """The model whose stability limit bounds a run of ``model`` with ``inertia`` (N,) [kg]:
        ``model`` itself without mass scaling, else :func:`inertial_model` (cached for the
        last pair seen, so that :meth:`critical_time_step` is computed once per pair)."""
        if inertia is None:
            return model
        cached = self._inertial
        if cached is None or cached[0] is not model or cached[1] is not inertia:
            cached = (model, inertia, inertial_model(model, inertia))
            self._inertial = cached
        return cached[2]

    def prepare(self, model: Model, dt: float, *, gravity: np.ndarray | None = None,
                prescribed_nodes: np.ndarray | None = None, arms: bool = True,
                skip: bool = True, threads: int = 1, inertia: np.ndarray | None = None,
                _check_dt: bool = True) -> "Run":
        """A :class:`Run`: everything fixed between calls of the compiled loop, set up once.

        ``threads`` > 1 splits each step over that many threads (see :class:`Run`).
        ``inertia`` (N,) [kg]: mass scaling, the inertial mass of each particle (at
        least its mass, e.g. :func:`particle.mass_scaling.scaled_inertia`); the loads
        keep the physical masses and the step is checked against the limit of
        :func:`inertial_model`. Raises :class:`ParameterError` if the model's
        connector parameters are non-physical on this integrator's strain range (see
        :meth:`ConnectorParams.validate`) or ``threads`` is not in 1 ..
        ``numba.config.NUMBA_NUM_THREADS``, :class:`StabilityError` if ``dt`` is
        above the stability limit (``_check_dt=False`` bypasses the step check
        and the strain-range monitoring, not the parameter check; tests use it
        to provoke divergence).
        """
        dt = float(dt)
        threads = check_threads(threads)
        model.params.validate(self.strain_range, model.edges, model.tets)
        stability = self.stability_model(model, inertia)
        monitored = None
        if _check_dt:
            check_time_step(dt, self.critical_time_step(stability))
            monitored = connector_strain_bounds(self.strain_range, model.n_connectors,
                                                model.edges)
        return Run(self, model, dt, gravity, prescribed_nodes, arms, skip, monitored, threads,
                   stability)

    def simulate(self, model: Model, state: State, dt: float, n_steps: int, *,
                 gravity: np.ndarray | None = None, prescribed: Prescribed | None = None,
                 record_nodes: np.ndarray | None = None, record_steps: np.ndarray | None = None,
                 arms: bool = True, skip: bool = True, threads: int = 1,
                 inertia: np.ndarray | None = None, _check_dt: bool = True
                 ) -> np.ndarray | None:
        """Advance ``state`` by ``n_steps`` steps of ``dt`` [s] in place.

        Args:
            gravity: (3,) gravitational acceleration [m/s^2] or None.
            prescribed: particles moved along keyframes (times absolute, like ``state.t``).
            record_nodes: (R,) particles whose positions are recorded.
            record_steps: (S,) increasing step indices to record after (0 = now).
            arms: False runs the purely elastic model (arm forces held at zero).
            skip: compile out the terms the run does not need (False: keep all).
            threads: threads per step (1: the serial loop; see :class:`Run`).
            inertia: (N,) inertial masses [kg] of a mass-scaled run (see :meth:`prepare`).
        Returns:
            (S, R, 3) recorded positions [m], or None without ``record_nodes``.
        Raises:
            StabilityError: dt above the stability limit, the run diverged, or a
                connector left the strain range the step was verified for.
        """
        run = self.prepare(model, dt, gravity=gravity, arms=arms, skip=skip, threads=threads,
                           inertia=inertia, _check_dt=_check_dt,
                           prescribed_nodes=None if prescribed is None else prescribed.nodes)
        record = None
        if record_nodes is not None:
            record_nodes = model.check_nodes(record_nodes, "record_nodes", movable=False)
            record_steps = np.asarray(record_steps, dtype=np.int64)
            if np.any(record_steps < 0) or np.any(record_steps > n_steps) or np.any(
                    np.diff(record_steps) < 0):
                raise ParameterError(f"record_steps must be increasing within 0..{n_steps}")
            record = np.empty((len(record_steps), len(record_nodes), 3))
        keyframes = None if prescribed is None else (prescribed.times, prescribed.positions)
        run.check_state(state)
        bound = energy_bound(model, state, run.dt, n_steps, run.gravity, prescribed)
        run(state, n_steps, keyframes, bound, (record_nodes, record_steps, record))
        return record


class Run:
    """One prepared configuration of the compiled Verlet loop (model, dt, terms, prescribed set).

    Built by :meth:`VerletIntegrator.prepare`; calling it advances a state.
    Preparing once and calling many times keeps per-call overhead to one
    kernel dispatch (the haptic loop relies on this). ``monitored`` (lo (E,),
    hi (E,)) is the strain range the step was verified for (None: not checked).

    ``threads`` = T > 1 (opt-in, for large models on a dedicated core set):
    each step's connector pass is split into T contiguous connector blocks,
    each accumulating into its own force buffer (T, N, 3), preallocated here,
    and the reduction of the buffers with the position update is split into T
    blocks of nodes (:func:`particle.kernels.parallel_forces`,
    :func:`~particle.kernels.parallel_advance`): two numba parallel regions per
    step, with numba's thread count set to T for the call and restored after.
    The same physics and checks as the serial loop (T = 1, the default and the
    reference); the forces differ from it by the summation order only (round-off).
    What the threads exchange every step (positions, force buffer rows) grows
    with the particles that two connector blocks share: few when particle ids
    follow space (:meth:`Model.renumbered` with :func:`~particle.model.spatial_order`),
    most of them in a mesh generator's order (the 12k-connector liver: 116 vs 634
    of 2033 particles for T = 2; measured figures in :mod:`particle.kernels`).
    """

    def __init__(self, integrator: VerletIntegrator, model: Model, dt: float,
                 gravity: np.ndarray | None, prescribed_nodes: np.ndarray | None, arms: bool,
                 skip: bool, monitored: tuple[np.ndarray, np.ndarray] | None = None,
                 threads: int = 1, stability: Model | None = None) -> None:
        p = model.params
        g = None if gravity is None else np.asarray(gravity, dtype=np.float64).reshape(3)
        if g is not None and not np.all(np.isfinite(g)):
            raise ParameterError(f"gravity {g} m/s^2 is not finite")
        self.terms = Terms.select(p, gravity=g, arms=arms, damping=integrator.damping, skip=skip)
        self.integrator, self.model, self.dt, self.gravity, self.arms = (
            integrator, model, dt, g, arms)
        self.arm_r, self.arm_c = (p.arm_recursion(dt) if arms
                                  else (np.zeros((model.n_connectors, 2)),) * 2)
        if prescribed_nodes is None:
            self.prescribed = np.zeros(0, np.int64)
        else:
            self.prescribed = model.check_nodes(prescribed_nodes, "prescribed motion")
        self.active = np.setdiff1d(model.free_nodes, self.prescribed)
        # mass scaling: the stability model's masses are the inertia (the update divides by
        # them); gravity and damping act on the physical masses, and so does the divergence
        # check's kinetic energy (at most the inertial one: no false alarm; a divergence
        # grows exponentially and trips it all the same)
        self.stability_model = model if stability is None else stability
        self.inv_masses = 1.0 / self.stability_model.masses
        self._forces = np.empty((model.n_particles, 3))
        t = self.terms
        self._springs = (p.K0, p.a if t.nonlinear else None, p.b if t.nonlinear else None,
                         self.arm_r if t.arms else None, self.arm_c if t.arms else None)
        self._loads = ((np.zeros(3) if g is None else g) if t.gravity else None,
                       integrator.damping / dt if t.damping else None)
        self.monitored = monitored
        # compared with the elongations the force kernel stores anyway: no extra sqrt
        self._elongation_limits = ((None, None) if monitored is None else
                                   tuple(b * model.rest_lengths for b in monitored))
        self._edges = kernels.index_view(model.edges)
        self._volume = None
        if p.kv is not None:  # volumes outside (v_lo, v_hi] stop the run (v_lo >= 0: inverted)
            if monitored is None:
                ratio = (np.zeros(model.n_tets), np.full(model.n_tets, np.inf))
            else:
                ratio = volume_ratio_range(model, *monitored)
            self.volume_ratio_range = ratio
            self._volume = (kernels.index_view(model.tets), model.rest_volumes, p.kv,
                            ratio[0] * model.rest_volumes, ratio[1] * model.rest_volumes)
        self._active = kernels.index_view(self.active)
        self._prescribed = kernels.index_view(self.prescribed)
        self._no_keyframes = (np.zeros(1), np.zeros((1, 0, 3)))
        self.threads = threads  # checked by VerletIntegrator.prepare, which builds every Run
        self._blocks = None if self.threads == 1 else thread_blocks(model, self.active,
                                                                     self.threads)
        self._node_edges: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._state_shapes = (("x", (model.n_particles, 3)), ("x_prev", (model.n_particles, 3)),
                              ("arm_force", (model.n_connectors, 2)),
                              ("dx_prev", (model.n_connectors,)))

    def __call__(self, state: State, n_steps: int, keyframes: tuple | None, energy_bound: float,
                 record: tuple = (None, None, None), probe: int | None = None
                 ) -> np.ndarray | None:
        """Advance ``state`` by ``n_steps``; ``keyframes`` = (times (K,), positions (K, k, 3)).

        Returns the (3,) connector force [N] on particle ``probe`` at the final
        state (what :meth:`force_on` gives, in the same kernel call), or None
        without ``probe``. Raises :class:`StabilityError` if the run diverges or
        leaves the monitored strain range (the state is then invalid).
        """
        model, dt = self.model, self.dt
        if n_steps < 0:
            raise ParameterError(f"n_steps = {n_steps} must be >= 0")
        self.check_state(state)
        if keyframes is None:
            keyframes = self._no_keyframes
        if keyframes[1].shape[1:] != (len(self.prescribed), 3):
            raise ParameterError(f"keyframe positions of shape {keyframes[1].shape} do not match "
                                 f"the {len(self.prescribed)} prescribed particles")
        if state.dt is not None and state.dt != dt:
            state.x_prev[:] = state.x - (state.x - state.x_prev) * (dt / state.dt)
            if self.arms and n_steps:
                self._close_arm_step(state)
        if not self.arms:
            state.arm_force[:] = 0.0
        out = node_edges = node_tets = None
        if probe is not None:
            (node_edges, node_tets), out = self._incident(probe), np.empty(3)
        pool = None if self._blocks is None else numba.get_num_threads()
        if pool is not None:
            numba.set_num_threads(self.threads)  # the caller's pool size is restored below
        try:
            status = kernels.run_verlet(
                state.x, state.x_prev, state.arm_force, state.dx_prev, self._edges,
                model.rest_lengths, *self._springs, model.masses, self.inv_masses, self._active,
                *self._loads, dt, int(n_steps), state.dt is None, self._prescribed, *keyframes,
                float(state.t), *record, self.integrator.check_every, float(energy_bound),
                *self._elongation_limits, self._forces, probe, node_edges, out, self._blocks,
                self._volume, node_tets)
        finally:
            if pool is not None:
                numba.set_num_threads(pool)
        code, step, node = status.tolist()
        if code == kernels.VOLUME:
            self._raise_volume_exit(state, node, step)
        if code == kernels.STRAIN:
            self._raise_strain_exit(state, node, state.t + (step - 1) * dt)
        if code != kernels.OK:
            what = ("has a non-finite position" if code == kernels.NONFINITE else
                    f"is the fastest particle; the kinetic energy exceeds {energy_bound:.3g} J")
            raise StabilityError(
                f"explicit run diverged at step {step} (t = {state.t + step * dt:.6g} s): "
                f"particle {node} {what}; dt = {dt:.4g} s, stability limit "
                f"{self.integrator.critical_time_step(self.stability_model):.4g} s")
        state.t += n_steps * dt
        if n_steps:
            state.dt = dt
        return out

    def _raise_volume_exit(self, state: State, t: int, step: int) -> None:
        """StabilityError for tet ``t`` found outside its volume range at step ``step`` (the
        kernel stopped right after advancing the free particles: their positions then are
        the state's ``x_prev``, the prescribed ones' still ``x``)."""
        model, dt = self.model, self.dt
        x = state.x_prev.copy()
        x[self.prescribed] = state.x[self.prescribed]
        ratio = float(signed_volumes(x, model.tets[t:t + 1])[0] / model.rest_volumes[t])
        where = (f"at step {step} (t = {state.t + step * dt:.6g} s) of the explicit run; dt = "
                 f"{dt:.4g} s, stability limit {self.integrator.critical_time_step(model):.4g} s")
        if not ratio > 0.0:
            raise StabilityError(f"{tet_name(t, model.tets)} inverted (volume ratio V/V0 = "
                                 f"{ratio:.3g} <= 0) {where}; the run stopped (the volume term "
                                 "is not meant for inverted tets)")
        lo, hi = self.volume_ratio_range
        raise StabilityError(f"{tet_name(t, model.tets)} reached volume ratio V/V0 = {ratio:.4g} "
                             f"{where}, outside [{lo[t]:.4g}, {hi[t]:.4g}], the range the step "
                             "was verified stable for; the run stopped rather than continue with "
                             "an unverified step (widen the strain range: it sets this one)")

    def _raise_strain_exit(self, state: State, e: int, t: float) -> None:
        """StabilityError for connector ``e`` found outside its monitored range at time ``t``."""
        lo, hi = self.monitored
        i, j = self.model.edges[e]
        strain = state.dx_prev[e] / self.model.rest_lengths[e]
        raise StabilityError(
            f"connector {e} (particles {i}-{j}) reached strain {strain:.4g} at t = {t:.6g} s, "
            f"outside [{lo[e]:.4g}, {hi[e]:.4g}], the range the step dt = {self.dt:.4g} s was "
            f"verified stable for (limit "
            f"{self.integrator.critical_time_step(self.stability_model):.4g} "
            "s); the run stopped rather than continue with an unverified step. Widen the "
            "range (in a scene: a larger particle.strain_margin) or use a smaller explicit "
            "step verified for a wider range (particle.dt)")

    def _close_arm_step(self, state: State) -> None:
        """Let this run's first arm update close the previous run's last step exactly.

        The loop updates the arms at the start of each step for the step before
        it, which had the state's old length ``state.dt``: that update is done
        here with ``state.dt``'s coefficients, and stored so that the loop's
        first update (with this run's r, c) reproduces it: ``dx_prev = dx``,
        ``arm_force = F / r``.
        """
        model = self.model
        r_old, c_old = model.params.arm_recursion(state.dt)
        d = state.x[model.edges[:, 1]] - state.x[model.edges[:, 0]]
        dx = np.sqrt(np.einsum("ij,ij->i", d, d)) - model.rest_lengths
        force = r_old * state.arm_force + c_old * (dx - state.dx_prev)[:, None]
        state.dx_prev[:] = dx
        state.arm_force[:] = force / self.arm_r

    def check_state(self, state: State) -> None:
        """Raise :class:`ParameterError` unless ``state`` fits this run's model and kernels.

        Its arrays must have the model's shapes and be C-contiguous, writeable
        float64 (another dtype would be truncated to it or compile another kernel
        specialisation), and its time finite.
        """
        for name, shape in self._state_shapes:
            arr = getattr(state, name)
            if not (isinstance(arr, np.ndarray) and arr.shape == shape
                    and arr.dtype == np.float64 and arr.flags.carray):
                what = (f"{arr.dtype} array of shape {arr.shape}" if isinstance(arr, np.ndarray)
                        else type(arr).__name__)
                raise ParameterError(
                    f"the state's {name} ({what}) does not belong to this model of "
                    f"{self.model.n_particles} particles and {self.model.n_connectors} connectors:"
                    f" expected a writeable, C-contiguous float64 array of shape {shape}")
        if not math.isfinite(state.t):
            raise ParameterError(f"the state's time t = {state.t} s is not finite")

    def _incident(self, node: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The connectors and tets (None without the volume term) touching particle ``node``
        (index views for the kernels; cached)."""
        found = self._node_edges.get(node)
        if found is None:
            node = int(self.model.check_nodes([node], "force_on", movable=False)[0])
            ptr = self.model.incidence_ptr
            edges = kernels.index_view(self.model.incidence_edge[ptr[node]:ptr[node + 1]])
            tets = (None if self._volume is None else kernels.index_view(
                np.nonzero(np.any(self.model.tets == node, axis=1))[0]))
            found = self._node_edges[node] = (edges, tets)
        return found

    def force_on(self, state: State, node: int) -> np.ndarray:
        """(3,) internal force on particle ``node`` at ``state`` [N], arm step not committed.

        What the next step will apply to that particle: its connectors (and its
        tets' volume term when on) only,
        the arms advanced by this run's recursion into scratch (state unchanged).
        """
        out = np.empty(3)
        edges, tets = self._incident(node)
        kernels.node_force(state.x, node, edges, self._edges, self.model.rest_lengths,
                           *self._springs, state.arm_force, state.dx_prev, out)
        if self._volume is not None:
            kernels.node_volume_force(state.x, node, tets, *self._volume, out)
        return out
