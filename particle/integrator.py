"""Explicit time integration: position Verlet with the paper's Maxwell-arm recursion.

:class:`VerletIntegrator` advances a :class:`~particle.model.State` in place
with the compiled loop :func:`particle.step_kernels.run_verlet`. Which force terms
the loop contains is decided once per run (:class:`Terms`): gravity, Maxwell
arms, nonlinear springs and damping are compiled out when a run does not need
them; ``skip=False`` keeps every term (with zero values) so benchmarks and tests
can run the same experiment both ways.

Each step evaluates, in this order: connector elongations, the arm recursion
``F^t = r F^{t-1} + c (dx^t - dx^{t-1})`` with the paper's coefficients
(:meth:`ConnectorParams.arm_recursion`), spring + arm tension, gravity ``m g``,
and optional mass-proportional damping ``-gamma m v`` with the backward-difference
velocity. What stops a run is :mod:`particle.guard`'s (the errors it stops with,
:func:`exit_error`, are here: they read the :class:`Run`); the stable step and the
strain ranges it holds on are :mod:`particle.stability`'s. The keyframed motion of
prescribed particles is :class:`~particle.model.Prescribed`.

Threads: a :class:`Run` with ``threads`` = T > 1 (opt-in, for large models on a
dedicated core set) splits each step's connector pass into T contiguous connector
blocks, each accumulating into its own force buffer (T, N, 3), preallocated by
:func:`thread_blocks`, and the reduction of the buffers with the position update
into T blocks of nodes (:func:`particle.step_kernels.parallel_forces`,
:func:`~particle.step_kernels.parallel_advance`): two numba parallel regions per step,
with numba's thread count set to T for the call and restored after. The same
physics and checks as the serial loop (T = 1, the default and the reference); the
forces differ from it by the summation order only (round-off). What the threads
exchange every step (positions, force buffer rows) grows with the particles that
two connector blocks share: few when particle ids follow space
(:meth:`Model.renumbered` with :func:`~particle.model.spatial_order`), most of them
in a mesh generator's order (the 12k-connector liver: 116 vs 634 of 2033 particles
for T = 2; measured figures in :mod:`particle.kernels`).
"""

from __future__ import annotations

import logging
import math
import operator
from dataclasses import dataclass

import numba
import numpy as np

from forcecal.errors import ParameterError, StabilityError
from particle import kernels, step_kernels
from particle.model import Model, Prescribed, State, check_gravity
from particle.params import ConnectorParams, StrainBounds, check_count, connector_strain_bounds
from particle.stability import (DEFAULT_STRAIN_RANGE, check_time_step, critical_time_step,
                                inertial_model)
from particle.guard import check_state, energy_bound
from particle.nodal_kernels import nodal_node_volume_force, ring_tets
from particle.nodal_volume import (element_arm_recursion, element_coefficients, element_strains,
                                   is_nodal)
from particle.volume import node_volume_force, signed_volumes, tet_name
from particle.volume_bounds import verified_ratio_range

log = logging.getLogger(__name__)


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
    (T+1,) uint64): thread t takes the connectors ``edge_starts[t] ..`` and the ``active``
    nodes (k,) ``node_starts[t] ..`` (contiguous blocks of equal size).
    """
    def starts(n: int) -> np.ndarray:  # unsigned, as the index views (kernels.index_view)
        return np.linspace(0, n, threads + 1).round().astype(np.uint64)

    return (np.zeros((threads, model.n_particles, 3)), starts(model.n_connectors),
            starts(len(active)))


def recording(model: Model, nodes: np.ndarray | None, steps: np.ndarray | None,
              n_steps: int) -> tuple:
    """(nodes (R,), steps (S,), buffer (S, R, 3) [m]) of a run that records the positions of
    particles ``nodes`` after each of ``steps`` (increasing, in 0..``n_steps``); three Nones
    without ``nodes``."""
    if nodes is None:
        return None, None, None
    nodes = model.check_nodes(nodes, "record_nodes", movable=False)
    steps = np.asarray(steps, dtype=np.int64)
    if np.any(steps < 0) or np.any(steps > n_steps) or np.any(np.diff(steps) < 0):
        raise ParameterError(f"record_steps must be increasing within 0..{n_steps}")
    return nodes, steps, np.empty((len(steps), len(nodes), 3))


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


class VerletIntegrator:
    """Position (Stoermer) Verlet: ``x^{t+dt} = 2 x^t - x^{t-dt} + dt^2 f(x^t)/m``.

    On free, non-prescribed particles, second order. Start-up from rest: a State that has never been
    stepped (``state.dt is None``, ``x_prev = x``, v = 0) takes
    ``x^{dt} = x^0 + dt^2/2 a^0`` (the Taylor step) instead of the plain
    formula's ``x^0 + dt^2 a^0``. If the step changes between runs, ``x_prev``
    is rescaled to keep the velocity ``(x - x_prev)/dt``.

    Each step's terms: module docstring. A step is accepted only below
    :func:`critical_time_step` for ``strain_range``, and that bound holds only
    while the strains stay in the range: every run with a checked step verifies
    it, at each divergence check, and stops with :class:`StabilityError` naming
    the first connector outside it.

    Args:
        damping: gamma [1/s], global mass-proportional viscous damping (0 = off).
        check_every: steps between two divergence checks (non-finite positions,
            kinetic energy beyond the bound the loads allow, connector strains
            outside ``strain_range``).
        strain_range: connector strains the runs stay in [1]: one (lo, hi) pair or
            per-connector (lo (E,), hi (E,)) arrays; the stability limit is the one of
            this range.
        limit: the stability limit [s] of ``strain_range`` when the caller bounds it
            itself (the haptic session's strain bands,
            :class:`particle.envelope.StrainBands`; it may set the attribute again as the
            range moves), None: :func:`critical_time_step`.
        volume_range: with the volume term, each tet's volume ratios V/V0 the runs stay in
            [1] (J_lo (T,), J_hi (T,)), verified and bounded with ``strain_range``
            (:func:`particle.volume_bounds.verified_ratio_range`; None: those of
            ``strain_range``).
    """

    def __init__(self, damping: float = 0.0, *, check_every: int = 64,
                 strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                 limit: float | None = None,
                 volume_range: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        if not (math.isfinite(damping) and damping >= 0.0):
            raise ParameterError(f"damping = {damping} 1/s must be >= 0")
        if check_every < 1:
            raise ParameterError(f"check_every = {check_every} must be >= 1")
        self.damping = float(damping)
        self.check_every = int(check_every)
        self.strain_range = strain_range
        self.volume_range = volume_range
        self.limit = limit
        self._critical: tuple[Model, float] | None = None
        self._inertial: tuple[Model, np.ndarray, Model] | None = None

    def critical_time_step(self, model: Model) -> float:
        """:func:`critical_time_step` of ``model`` (cached for the last model seen), or the
        ``limit`` the caller set."""
        if self.limit is not None:
            return self.limit
        if self._critical is None or self._critical[0] is not model:
            value = critical_time_step(model, strain_range=self.strain_range,
                                       damping=self.damping, volume_range=self.volume_range)
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
        n_steps = check_steps(n_steps)
        run = self.prepare(model, dt, gravity=gravity, arms=arms, skip=skip, threads=threads,
                           inertia=inertia, _check_dt=_check_dt,
                           prescribed_nodes=None if prescribed is None else prescribed.nodes)
        record = recording(model, record_nodes, record_steps, n_steps)
        keyframes = None if prescribed is None else (prescribed.times, prescribed.positions)
        check_state(model, state, finite=True)
        bound = energy_bound(model, state, run.dt, n_steps, run.gravity, prescribed)
        run(state, n_steps, keyframes, bound, record)
        return record[2]


class Run:
    """One prepared configuration of the compiled Verlet loop (model, dt, terms, prescribed set).

    Built by :meth:`VerletIntegrator.prepare`; calling it advances a state.
    Preparing once and calling many times keeps per-call overhead to one
    kernel dispatch (the haptic loop relies on this). ``monitored`` (lo (E,),
    hi (E,)) is the strain range the step was verified for (None: not checked).

    ``threads`` = T > 1 splits each step over T threads (module docstring).
    """

    def __init__(self, integrator: VerletIntegrator, model: Model, dt: float,
                 gravity: np.ndarray | None, prescribed_nodes: np.ndarray | None, arms: bool,
                 skip: bool, monitored: tuple[np.ndarray, np.ndarray] | None = None,
                 threads: int = 1, stability: Model | None = None) -> None:
        p = model.params
        g = check_gravity(gravity)
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
        self._edges = kernels.index_view(model.edges)
        self._springs = step_kernels.spring_group(
            edges=self._edges, rest_lengths=model.rest_lengths, K0=p.K0,
            a=p.a if t.nonlinear else None, b=p.b if t.nonlinear else None,
            arm_r=self.arm_r if t.arms else None, arm_c=self.arm_c if t.arms else None)
        self._loads = step_kernels.load_group(
            gravity=(np.zeros(3) if g is None else g) if t.gravity else None,
            damping_rate=integrator.damping / dt if t.damping else None)
        self.monitored = monitored
        # compared with the elongations the force kernel stores anyway: no extra sqrt
        self._elongation_limits = ((np.zeros(0), np.zeros(0)) if monitored is None else
                                   tuple(b * model.rest_lengths for b in monitored))
        self._volume = self._volume_checks = None
        if p.kv is not None:
            self.volume_ratio_range, self._volume, self._volume_checks = volume_limits(
                model, monitored, integrator.volume_range)
        # the nodal term's scratch (particle volumes and pressures), None: per tet
        self._volume_nodes = ((np.empty(model.n_particles), np.empty(model.n_particles))
                              if is_nodal(model) else None)
        # the volume term's arms, with the paper's recursion like the connectors' (None: an
        # elastic volume term, or a run without arms)
        self.volume_arm_r = self.volume_arm_c = None
        if p.has_volume_arms and arms:
            self.volume_arm_r, self.volume_arm_c = element_arm_recursion(model, dt)
        self._active = kernels.index_view(self.active)
        self._particles = step_kernels.particle_group(
            masses=model.masses, inv_masses=self.inv_masses, active=self._active)
        self._prescribed = kernels.index_view(self.prescribed)
        self._no_keyframes = (np.zeros(1), np.zeros((1, 0, 3)))
        self.threads = threads  # checked by VerletIntegrator.prepare, which builds every Run
        self._blocks = None if self.threads == 1 else thread_blocks(model, self.active,
                                                                     self.threads)
        self._scratch = (self._forces, self._blocks)
        self._node_edges: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # (keyframes, run_verlet's compiled entry point or None: seen once) by (keyframes
        # object, no probe) (:meth:`_kernel`)
        self._entries: dict[tuple[int, bool], tuple[tuple, object | None]] = {}
        # the kernel's probe group without a probe: empty arrays of a probe's types (its tets
        # None without the volume term, which is compiled out then anyway)
        self._no_probe = (-1, kernels.index_view(model.incidence_edge[:0]), np.empty(0),
                          None if self._volume is None
                          else kernels.index_view(np.zeros(0, np.int64)))

    def __call__(self, state: State, n_steps: int, keyframes: tuple | None, energy_bound: float,
                 record: tuple = (None, None, None), probe: int | None = None
                 ) -> np.ndarray | None:
        """Advance ``state`` by ``n_steps``; ``keyframes`` = (times (K,), positions (K, k, 3)).

        Returns the (3,) connector force [N] on particle ``probe`` at the final
        state (what :meth:`force_on` gives, in the same kernel call), or None
        without ``probe``. Raises :class:`StabilityError` if the run diverges or
        leaves the monitored strain range (the state is then invalid).
        """
        dt = self.dt
        keyframes = start_call(self, state, n_steps, keyframes)
        if probe is None:
            probe_group, out = self._no_probe, None
        else:
            (node_edges, node_tets), out = self._incident(probe), np.empty(3)
            probe_group = (probe, node_edges, out, node_tets)
        pool = None if self._blocks is None else numba.get_num_threads()
        if pool is not None:
            numba.set_num_threads(self.threads)  # the caller's pool size is restored below
        try:
            args = self.arguments(state, n_steps, keyframes, energy_bound, record, probe_group)
            status = self._kernel(args, keyframes, probe is None, record)
        finally:
            if pool is not None:
                numba.set_num_threads(pool)
        code, step, node = status.tolist()
        if code != step_kernels.OK:
            error = exit_error(self, state, code, step, node, energy_bound)
            error.reached = state.t + max(step - 1, 0) * dt  # the last step completed
            raise error
        state.t += n_steps * dt
        if n_steps:
            state.dt = dt
        return out

    def retarget(self, strain_range: tuple[np.ndarray, np.ndarray],
                 elongation_limits: tuple[np.ndarray, np.ndarray],
                 ratio_range: tuple[np.ndarray, np.ndarray] | None = None,
                 volume_limits: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Verify the strain range (lo (E,), hi (E,)) [1], as ``elongation_limits`` (E,) x 2
        [m], and with the volume term the volume ratio range (lo (T,), hi (T,)) [1], as
        ``volume_limits`` (T,) x 2 [m^3], from the next call on; the step is not checked
        again (the caller bounds its stability on them, and may update the arrays in place
        between calls, which the run then verifies: :class:`particle.envelope.StrainBands`).
        """
        self.monitored, self._elongation_limits = strain_range, elongation_limits
        if self._volume is not None:
            self.volume_ratio_range = ratio_range
            self._volume_checks = (*volume_limits, self._volume_checks[2])

    def arguments(self, state: State, n_steps: int, keyframes: tuple, energy_bound: float,
                  record: tuple, probe: tuple) -> tuple:
        """:func:`~particle.step_kernels.run_verlet`'s argument groups (its docstring), in its
        order, for a call advancing ``state`` by ``n_steps`` (``probe``: the probe group)."""
        return ((state.x, state.x_prev, state.arm_force, state.dx_prev), *self._springs,
                self._particles, self._loads,
                (self.dt, int(n_steps), state.dt is None, float(state.t)),
                (self._prescribed, *keyframes), record,
                (self.integrator.check_every, float(energy_bound), *self._elongation_limits),
                probe, self._scratch, self._volume, self._volume_checks, self.volume_arms(state),
                self._volume_nodes)

    def _kernel(self, args: tuple, keyframes: tuple, no_probe: bool, record: tuple):
        """``run_verlet(*args)``; from the third call with the same ``keyframes`` object (the
        haptic session's), the same kind of probe and no recording, the compiled entry point
        the second found, directly.

        Every other argument has the types it had then: the run's own arrays, the
        state's (checked by :func:`check_state` on every call: C-contiguous, writeable
        float64 of the model's shapes), Python scalars; the keyframes are held, so their
        identity stands for their types. Numba's dispatch re-derives the types of every
        argument on each call from their fingerprints (every group fits them,
        :mod:`particle.dispatch`): about 2 us of a call on the default liver that the
        entry point saves.
        """
        fast = all(r is None for r in record)
        key = (id(keyframes), no_probe)
        held = self._entries.get(key) if fast else None
        if held is not None and held[0] is keyframes and held[1] is not None:
            return held[1](*args)
        status = step_kernels.run_verlet(*args)
        if fast:  # typing the arguments costs ~0.4 ms: only for a run called again
            entry = None
            if held is not None and held[0] is keyframes:
                signature = tuple(numba.typeof(a) for a in args)
                entry = step_kernels.run_verlet.overloads[signature].entry_point
            self._entries[key] = (keyframes, entry)
        return status

    def volume_arms(self, state: State) -> tuple | None:
        """The volume arms of ``state`` as the kernels take them from Python: (r, c, its
        pressures, its volume strains) (:mod:`particle.volume`'s tuple without the outputs:
        read only, or written in place by :func:`~particle.step_kernels.run_verlet`), None
        without arms."""
        if self.volume_arm_r is None:
            return None
        return (self.volume_arm_r, self.volume_arm_c, state.volume_arm, state.volume_prev)

    def _incident(self, node: int) -> tuple[np.ndarray, np.ndarray | None]:
        """:func:`incident` of ``node`` (cached)."""
        found = self._node_edges.get(node)
        if found is None:
            found = self._node_edges[node] = incident(self.model, node, self._volume is not None,
                                                      self._volume_nodes is not None)
        return found

    def force_on(self, state: State, node: int) -> np.ndarray:
        """(3,) internal force on particle ``node`` at ``state`` [N], arm step not committed.

        What the next step will apply to that particle: its connectors (and its
        tets' volume term when on) only,
        the arms advanced by this run's recursion into scratch (state unchanged).
        """
        out = np.empty(3)
        edges, tets = self._incident(node)
        kernels.node_force(state.x, node, edges, *self._springs[0], *self._springs[1],
                           state.arm_force, state.dx_prev, out)
        if self._volume_nodes is not None:
            nodal_node_volume_force(state.x, node, tets, *self._volume,
                                    self.volume_arms(state), self._volume_nodes[0], out)
        elif self._volume is not None:
            node_volume_force(state.x, node, tets, *self._volume, self.volume_arms(state),
                              out)
        return out


def close_arm_step(run: "Run", state: State) -> None:
    """Let this run's first arm update close the previous run's last step exactly.

    The loop updates the arms at the start of each step for the step before
    it, which had the state's old length ``state.dt``: that update is done
    here with ``state.dt``'s coefficients, and stored so that the loop's
    first update (with this run's r, c) reproduces it: ``dx_prev = dx``,
    ``arm_force = F / r``; the volume term's arms likewise (``volume_prev = j``,
    ``volume_arm = P / r``).
    """
    model = run.model
    r_old, c_old = model.params.arm_recursion(state.dt)
    d = state.x[model.edges[:, 1]] - state.x[model.edges[:, 0]]
    dx = np.sqrt(np.einsum("ij,ij->i", d, d)) - model.rest_lengths
    force = r_old * state.arm_force + c_old * (dx - state.dx_prev)[:, None]
    state.dx_prev[:] = dx
    state.arm_force[:] = force / run.arm_r
    if run.volume_arm_r is not None:
        r_old, c_old = element_arm_recursion(model, state.dt)
        strain = element_strains(model, state.x)
        pressure = r_old * state.volume_arm + c_old * (strain - state.volume_prev)[:, None]
        state.volume_prev[:] = strain
        state.volume_arm[:] = pressure / run.volume_arm_r


def volume_limits(model: Model, monitored: tuple[np.ndarray, np.ndarray] | None,
                  volume_range: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> tuple[tuple[np.ndarray, np.ndarray], tuple, tuple]:
    """(volume ratio range (lo (T,), hi (T,)), the volume term's kernel arguments
    ``volume_term``, ``volume_checks`` (:func:`particle.step_kernels.run_verlet`)) of a run:
    volumes outside (v_lo, v_hi] stop it (v_lo >= 0: inverted), the range is
    :func:`~particle.volume_bounds.verified_ratio_range` of the ``monitored`` strain range
    and ``volume_range`` (without a monitored range: any positive volume); the term's rest
    volumes and kv are the tets', or the particles' for the nodal term (the tets' volume
    range is checked for both). The checks end
    with the run's scratch for the volumes of its last force pass (T,) [m^3]
    (:func:`particle.step_kernels.final_volume_check`)."""
    if monitored is None:
        ratio = (np.zeros(model.n_tets), np.full(model.n_tets, np.inf))
    else:
        ratio = verified_ratio_range(model, *monitored, volume_range)
    return ratio, (kernels.index_view(model.tets), *element_coefficients(model)), (
        ratio[0] * model.rest_volumes, ratio[1] * model.rest_volumes, np.empty(model.n_tets))


def check_steps(n_steps: int) -> int:
    """``n_steps`` as an int if it is an integer >= 0 (a step count), else
    :class:`ParameterError` (a fractional count would be truncated)."""
    return check_count(n_steps, "n_steps", "a number of steps")


def start_call(run: Run, state: State, n_steps: int, keyframes: tuple | None) -> tuple:
    """Check a call of ``run`` and bring ``state`` to its step; the keyframes to pass on.

    A state last advanced with another step keeps its velocity (``x_prev`` rescaled)
    and its arms' last update (:func:`close_arm_step`); a run without arms holds
    their forces (and the volume arms' pressures) at zero.
    """
    check_steps(n_steps)
    check_state(run.model, state)
    if keyframes is None:
        keyframes = run._no_keyframes
    if keyframes[1].shape[1:] != (len(run.prescribed), 3):
        raise ParameterError(f"keyframe positions of shape {keyframes[1].shape} do not match "
                             f"the {len(run.prescribed)} prescribed particles")
    if state.dt is not None and state.dt != run.dt:
        state.x_prev[:] = state.x - (state.x - state.x_prev) * (run.dt / state.dt)
        if run.arms and n_steps:
            close_arm_step(run, state)
    if not run.arms:
        state.arm_force[:] = 0.0
        if state.volume_arm is not None:
            state.volume_arm[:] = 0.0
    return keyframes


def incident(model: Model, node: int, tets: bool, ring: bool = False
             ) -> tuple[np.ndarray, np.ndarray | None]:
    """The connectors and (with ``tets``, else None) tets touching particle ``node`` (with
    ``ring``, its two-ring of tets: the nodal term's, :func:`particle.nodal_kernels.ring_tets`),
    as index views for the kernels."""
    node = int(model.check_nodes([node], "force_on", movable=False)[0])
    ptr = model.incidence_ptr
    edges = kernels.index_view(model.incidence_edge[ptr[node]:ptr[node + 1]])
    if not tets:
        return edges, None
    if ring:
        return edges, kernels.index_view(ring_tets(model.tets, node))
    return edges, kernels.index_view(np.nonzero(np.any(model.tets == node, axis=1))[0])


def exit_error(run: Run, state: State, code: int, step: int, index: int,
               energy_bound: float) -> StabilityError:
    """The error for the kernel's exit ``code`` != OK at ``step`` (``index``: the tet,
    connector or particle it names; ``energy_bound`` [J] the run's divergence bound)."""
    if code == step_kernels.VOLUME:
        return volume_exit(run, state, index, step)
    if code == step_kernels.VOLUME_END:
        return volume_exit(run, state, index, step, final=True)
    if code == step_kernels.STRAIN:
        return strain_exit(run, state, index, state.t + (step - 1) * run.dt)
    if code == step_kernels.STRAIN_END:
        return strain_exit(run, state, index, state.t + step * run.dt, final=True)
    what = ("has a non-finite position" if code == step_kernels.NONFINITE else
            f"is the fastest particle; the kinetic energy exceeds {energy_bound:.3g} J")
    return StabilityError(
        f"explicit run diverged at step {step} (t = {state.t + step * run.dt:.6g} s): "
        f"particle {index} {what}; dt = {run.dt:.4g} s, stability limit "
        f"{run.integrator.critical_time_step(run.stability_model):.4g} s")


def volume_exit(run: Run, state: State, t: int, step: int, final: bool = False
                ) -> StabilityError:
    """The error for tet ``t`` found outside its volume range at step ``step`` (the
    kernel stopped right after advancing the free particles: their positions then are
    the state's ``x_prev``, the prescribed ones' still ``x``), or with ``final`` in the
    run's final state (``state.x``, after its last step ``step``)."""
    model, dt = run.model, run.dt
    if final:
        x = state.x
    else:
        x = state.x_prev.copy()
        x[run.prescribed] = state.x[run.prescribed]
    ratio = float(signed_volumes(x, model.tets[t:t + 1])[0] / model.rest_volumes[t])
    where = (f"{'after' if final else 'at'} step {step} (t = {state.t + step * dt:.6g} s) "
             f"of the explicit run; dt = {dt:.4g} s, stability limit "
             f"{run.integrator.critical_time_step(run.stability_model):.4g} s")
    if not ratio > 0.0:
        return StabilityError(f"{tet_name(t, model.tets)} inverted (volume ratio V/V0 = "
                              f"{ratio:.3g} <= 0) {where}; the run stopped (the volume term "
                              "is not meant for inverted tets)")
    lo, hi = run.volume_ratio_range
    return StabilityError(f"{tet_name(t, model.tets)} reached volume ratio V/V0 = {ratio:.4g} "
                          f"{where}, outside [{lo[t]:.4g}, {hi[t]:.4g}], the range the step "
                          "was verified stable for; the run stopped rather than continue with "
                          "an unverified step (a wider strain range widens it; in a scene's "
                          "gravity release, so does a larger particle.strain_margin)")


def strain_exit(run: Run, state: State, e: int, t: float, final: bool = False
                ) -> StabilityError:
    """The error for connector ``e`` found outside its monitored range at time ``t`` [s]:
    at a checked step's start (its elongation is the state's ``dx_prev``) or, with
    ``final``, in the run's final state ``state.x``."""
    lo, hi = run.monitored
    i, j = run.model.edges[e]
    if final:
        strain = float(np.linalg.norm(state.x[j] - state.x[i])) / run.model.rest_lengths[e] - 1.0
    else:
        strain = state.dx_prev[e] / run.model.rest_lengths[e]
    when = f"{'at the end of the run, ' if final else 'at '}t = {t:.6g} s"
    return StabilityError(
        f"connector {e} (particles {i}-{j}) reached strain {strain:.4g} {when}, "
        f"outside [{lo[e]:.4g}, {hi[e]:.4g}], the range the step dt = {run.dt:.4g} s was "
        f"verified stable for (limit "
        f"{run.integrator.critical_time_step(run.stability_model):.4g} "
        "s); the run stopped rather than continue with an unverified step. Widen the "
        "range (in a scene: a larger particle.strain_margin) or use a smaller explicit "
        "step verified for a wider range (particle.dt)")
