"""Haptic loop: a tool drags one particle, the tissue's reaction is returned every millisecond.

A haptic device runs at ~1 kHz; each :meth:`HapticSession.step` advances the
model by one device period (1 ms by default) in several explicit substeps with
the tool particle moved linearly from where it was to the new tool position,
and returns the force the tissue exerts on the tool (what the device renders;
equal and opposite to the indenter force of the indentation convention).
Everything that does not change between calls (a :class:`~particle.integrator.Run`
per tool particle, the divergence bound) is prepared once, so a call costs one
kernel dispatch (substeps and reaction force together) plus a few checks.
"""

from __future__ import annotations

import logging
import math
import operator
from collections import OrderedDict

import numpy as np

from forcecal.errors import MeshError, ParameterError, StabilityError
from forcecal.scene import ParticleSection
from particle.envelope import StrainBands
from particle.guard import energy_bound
from particle.integrator import Run, VerletIntegrator, check_threads
from particle.stability import DEFAULT_STRAIN_RANGE, check_time_step, stable_step
from particle.model import Model, Prescribed, check_gravity
from particle.params import StrainBounds

log = logging.getLogger(__name__)

# tool particles whose prepared run is kept (least recently used dropped beyond): a run holds
# a few (E,) and (N, 3) arrays (~1 MB on a 12k-connector mesh) and takes ~1 ms to prepare
TOOL_RUN_CACHE = 16
#: fraction of the stability limit an ``envelope`` session steps at (the scenes' default)
DT_SAFETY = ParticleSection().dt_safety


def substeps_per_period(period: float, dt: float) -> int:
    """The fewest equal steps that cover ``period`` [s] without exceeding ``dt`` [s] (a dt
    within round-off of period / n gives n)."""
    return max(1, math.ceil(period / dt * (1.0 - 1e-12)))


class HapticSession:
    """Real-time session on one model.

    Args:
        model: the particle model (fixed particles stay clamped).
        dt: largest explicit step [s]; the period is split into ``ceil(period/dt)``
            equal substeps (checked against the stability limit).
        period: simulated time per :meth:`step` [s] (the device period).
        gravity: (3,) gravitational acceleration [m/s^2], or None.
        damping: mass-proportional damping [1/s].
        threads: threads per step (default 1: the serial loop). ``threads`` > 1
            splits every substep over that many threads (:class:`Run`), for
            large models on a machine whose cores are dedicated to the haptic
            loop, as a device loop has: each substep opens two numba parallel
            regions, and a region waits for every thread of the pool, so on a
            core that another process keeps busy a call can take milliseconds
            instead of microseconds. It must not exceed
            ``numba.config.NUMBA_NUM_THREADS``; on small models the serial
            loop is faster (the regions' launch cost exceeds the gain), and it
            pays only on a model whose particle ids follow space
            (:meth:`Model.renumbered`, :func:`~particle.model.spatial_order`).
        inertia: (N,) inertial masses [kg] for mass scaling (default None: the
            physical masses), e.g. :func:`particle.mass_scaling.scaled_inertia`
            for ``dt`` = the period: one substep per call on a model whose
            limit is below the period, at the cost of a slower transient
            (measured in ``runs/bench/BENCH.md``, "Haptic variants"); ``dt`` is
            checked against the limit with this inertia.
        strain_range: the connector strains the session is verified for [1] (one
            (lo, hi) pair or per-connector arrays, default +-0.5): ``dt`` is checked
            against the stability limit over this range, and every call checks that
            the strains stay in it (StabilityError naming the connector otherwise).
            A narrower range is a tighter operating envelope and a larger stable
            step: with the volume term, whose bound grows with the faces' and
            volumes' possible growth ((1 + hi)^2, (1 + hi)^3), much larger.
        envelope: None (default: the fixed ``strain_range``), or the half-width w [1]
            of per-connector strain bands that follow the state
            (:class:`~particle.envelope.StrainBands`): each connector is verified on
            ``[eps - w, eps + w]`` around its strain ``eps`` when the bands were last
            centred (at rest to start with), each tet on a volume ratio range around its
            ratio then, and the step is the smaller of ``dt`` and ``dt_safety`` x the
            stability limit of those bands (a rigorous bound, the arms' memory included,
            within 10 % of the eigensolved one). After each call, a connector
            whose strain (or a tet whose volume) has left the inner half of its band
            re-centres the bands that have drifted on the state and refreshes the step
            without an eigensolve (``recentred`` counts them; 0.25-0.8 ms on a
            12k-connector mesh with the volume term; the tool's prepared runs are kept
            unless the substeps change). Most of the mesh stays near rest while the tool
            drags, and the limit of a narrow band is well below the fixed range's with
            the volume term (whose bound grows with the faces' and volumes' possible
            growth). The kernel verifies the bands and ranges as it verifies
            ``strain_range`` (StabilityError if a state leaves them).
        dt_safety: with ``envelope``, the fraction of the stability limit stepped at.

    Attributes:
        state: the model's State (starts undeformed, at rest).
        substeps: explicit steps per call; ``dt`` the step actually used [s].
        recentred: how often the ``envelope`` bands were re-centred.

    Raises :class:`~forcecal.errors.StabilityError` for a ``dt`` that is not a
    finite number > 0 or is above the stability limit,
    :class:`~forcecal.errors.ParameterError` for a bad period, a bad ``threads``
    or non-physical connector parameters.
    """

    def __init__(self, model: Model, dt: float, *, period: float = 1e-3,
                 gravity: np.ndarray | None = None, damping: float = 0.0,
                 threads: int = 1, inertia: np.ndarray | None = None,
                 strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                 envelope: float | None = None, dt_safety: float = DT_SAFETY) -> None:
        if not (math.isfinite(period) and period > 0):
            raise ParameterError(f"haptic period = {period} s must be > 0")
        check_time_step(dt, math.inf)  # a finite step > 0; the limit is checked below
        if envelope is not None and not (math.isfinite(envelope) and 0.0 < envelope < 1.0):
            raise ParameterError(f"strain envelope half-width = {envelope} must be in (0, 1)")
        if not (math.isfinite(dt_safety) and 0.0 < dt_safety <= 1.0):
            raise ParameterError(f"dt_safety = {dt_safety} must be in (0, 1]")
        self.threads = check_threads(threads)
        self.model = model
        self.period = float(period)
        self.gravity = check_gravity(gravity)
        self.damping = float(damping)
        self.inertia = None if inertia is None else np.asarray(inertia, dtype=np.float64)
        self.state = model.state()
        self._runs: OrderedDict[int, tuple[Run, float]] = OrderedDict()
        self._keyframes = (np.zeros(2), np.zeros((2, 1, 3)))
        self.envelope, self.dt_safety, self._largest_dt = envelope, float(dt_safety), float(dt)
        self.recentred = 0
        self.integrator = VerletIntegrator(damping, strain_range=strain_range)
        self._bands: StrainBands | None = None
        self.substeps = 0  # set by _set_step or _take_bands_step below
        if envelope is None:
            self._set_step(dt)
        else:
            bands = self._bands = StrainBands(
                self.integrator.stability_model(model, self.inertia), envelope)
            self.integrator.strain_range = (bands.lo, bands.hi)
            self._take_bands_step()
        # refuse an unstable dt (or a bad inertia) now, not mid-session
        self.integrator.prepare(model, self.dt, inertia=self.inertia)

    def _set_step(self, dt: float) -> None:
        self.substeps = substeps_per_period(self.period, dt)
        self.dt = self.period / self.substeps

    def _bands_dt(self, limit: float) -> float:
        """The step [s] an ``envelope`` session takes under the stability ``limit`` [s]."""
        return min(self._largest_dt, self.dt_safety * limit)

    def _keeps_substeps(self, omega2: float) -> bool:
        """True if the bound ``omega2`` [1/s^2] needs no more substeps than the session takes."""
        return self.period / self.substeps <= self._bands_dt(stable_step(omega2, self.damping))

    def _take_bands_step(self) -> None:
        """Step at ``dt_safety`` x the ``envelope`` bands' limit (at most the largest ``dt``);
        the prepared runs are kept (verifying the bands as they move) unless the step
        changes."""
        limit = stable_step(self._bands.omega2, self.damping)
        self.integrator.limit = limit
        substeps = self.substeps
        self._set_step(self._bands_dt(limit))
        if self.substeps != substeps:
            self._runs.clear()

    def _run(self, node: int) -> tuple[Run, float]:
        """The prepared run and divergence bound of tool particle ``node`` (LRU cached)."""
        if node in self._runs:
            self._runs.move_to_end(node)
            return self._runs[node]
        run = self.integrator.prepare(self.model, self.dt, gravity=self.gravity,
                                      prescribed_nodes=[node], threads=self.threads,
                                      inertia=self.inertia)
        bands = self._bands
        if bands is not None:  # the arrays the bands move in place
            run.retarget((bands.lo, bands.hi), (bands.elongation_lo, bands.elongation_hi),
                         *((bands.ratio_lo, bands.ratio_hi), (bands.volume_lo, bands.volume_hi))
                         if bands.volume else ())
        # divergence bound for the worst drag: the tool crossing the whole organ in one period
        x0 = self.model.rest_positions[node]
        size = float(np.linalg.norm(np.ptp(self.model.rest_positions, axis=0)))
        sweep = Prescribed([node], [0.0, self.period], [[x0], [x0 + size]])
        bound = energy_bound(self.model, self.model.state(), self.dt, self.substeps,
                             run.gravity, sweep)
        self._runs[node] = (run, bound)
        if len(self._runs) > TOOL_RUN_CACHE:
            self._runs.popitem(last=False)
        return run, bound

    def step(self, tool_node: int, tool_position: np.ndarray) -> np.ndarray:
        """Advance one period with ``tool_node`` moved to ``tool_position`` (3,) [m].

        Returns the (3,) force the tissue exerts on the tool at the end of the
        period [N]. Raises MeshError for a tool node that is not an integer id
        of a free particle, ParameterError for a tool position that is not 3
        finite coordinates, StabilityError on divergence or when the state at the
        end of the period (or at a substep) leaves the session's ``strain_range``
        (or a tet its volume range), naming the connector (tet) and the tool's
        move; no force is returned then, and the session's state is invalid
        (start a new session).
        """
        try:
            node = operator.index(tool_node)
        except TypeError:
            raise MeshError(f"tool node {tool_node!r} must be an integer particle id") from None
        try:
            position = np.asarray(tool_position, dtype=np.float64)
        except (TypeError, ValueError):
            position = None
        if position is None or position.shape != (3,):
            raise ParameterError(f"tool position {tool_position!r} must be 3 coordinates [m]")
        x, y, z = position.tolist()
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise ParameterError(f"tool position {tool_position} is not finite")
        run, bound = self._run(node)
        times, positions = self._keyframes
        state = self.state
        times[0], times[1] = state.t, state.t + self.period
        positions[0, 0] = state.x[node]
        positions[1, 0] = x, y, z
        try:
            force = run(state, self.substeps, self._keyframes, bound, probe=node)
        except StabilityError as exc:  # the tool's move is the usual cause: say which one
            move = float(np.linalg.norm(positions[1, 0] - positions[0, 0]))
            raise StabilityError(
                f"haptic step moving tool particle {node} by {move:.4g} m in {self.period:g} s "
                f"(to [{x:.4g}, {y:.4g}, {z:.4g}] m): {exc}") from None
        # the elongations the last substep started from, left by the kernel's force pass
        if self._bands is not None and not self._bands.holds(state):
            self.recentred += 1
            self._bands.centre(state.x, enough=self._keeps_substeps)
            self._take_bands_step()
        return force
