"""Explicit time integration: position Verlet, stability limit, divergence guard.

:class:`VerletIntegrator` advances a :class:`~particle.model.State` in place
with the compiled loop :func:`particle.step_kernels.run_verlet`. Which force terms
the loop contains is decided once per run (:class:`Terms`): gravity, Maxwell
arms, nonlinear springs and damping are compiled out when a run does not need
them; ``skip=False`` keeps every term (with zero values) so benchmarks and tests
can run the same experiment both ways.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import operator
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import ArpackNoConvergence, eigsh

from forcecal.errors import ParameterError, StabilityError
from forcecal.scene import ParticleSection
from particle import kernels, step_kernels
from particle.model import (ConnectorParams, Model, State, StrainBounds,
                            connector_strain_bounds)
from particle.statics import check_stiffness, check_volumes
from particle.volume import (node_volume_force, node_volume_stiffness, signed_volumes, tet_name,
                             volume_energy, volume_frequency_bound, volume_ratio_range)

log = logging.getLogger(__name__)

DEFAULT_STRAIN_RANGE = (-0.5, 0.5)
# the kinetic energy may exceed the work the loads can do by this factor before a run is
# declared divergent: a real run stays far below, an unstable one grows exponentially
ENERGY_MARGIN = 100.0
# the computed lambda_max is multiplied by this: it covers the eigensolver's tolerance (1e-10
# relative) and rounding with a wide margin, at a cost of 0.05 % of the step
EIGENVALUE_MARGIN = 1.001
# free particles up to which the dense eigensolver is used: Lanczos is faster beyond (measured
# on Kuhn boxes: 294 free particles 6.6 ms dense, 1.2 ms Lanczos; 1089: 227 ms, 2.9 ms)
DENSE_EIGEN_LIMIT = 100


def connector_stiffness_bound(params: ConnectorParams, lo: np.ndarray, hi: np.ndarray
                              ) -> np.ndarray:
    """(E,) kappa_e >= the largest eigenvalue of connector e's 3x3 tangent block [N/m].

    The block ``s e e^T + (F/l)(I - e e^T)`` has the eigenvalues ``s`` (axial)
    and ``F/l`` (twice, transverse); kappa bounds both over strains in
    ``[lo, hi]`` (any ordered range above -1):

    * axial: the spring's tangent ``K0 + 2 a eps + 3 b eps^2`` (its maximum,
      analytic) plus the arms' instantaneous stiffness ``k_i b_i/(k_i dt + b_i)
      <= k_i``;
    * transverse: ``F/l = K(eps) eps/(1 + eps) + F_arm/l``. The spring part is
      positive only in tension with K > 0 (at most ``K_max hi/(1 + hi)``) or in
      compression with K < 0 (at most ``-K_min |lo|/(1 + lo)``). An arm's force
      is ``k_i`` times the elongation minus a weighted mean of its past values
      (the Maxwell convolution), so ``|F_arm| <= k_i (hi - lo) L0``, and ``l >=
      (1 + lo) L0``.

    kappa is at least 0, so that ``kappa``-weighted graph Laplacians are positive
    semidefinite.
    """
    _, tangent = params.extreme_tangent_stiffness((lo, hi))
    kmin, kmax = params.extreme_stiffness((lo, hi))
    arms = params.k1 + params.k2
    spring = np.maximum(np.maximum(kmax, 0.0) * hi / (1.0 + hi),
                        np.maximum(-kmin, 0.0) * -lo / (1.0 + lo))
    transverse = spring + arms * (hi - lo) / (1.0 + lo)
    return np.maximum(np.maximum(tangent + arms, transverse), 0.0)


def mass_scaled_laplacian(model: Model, kappa: np.ndarray) -> sp.csr_matrix:
    """(Nf, Nf) ``M^{-1/2} L_kappa M^{-1/2}`` on the free particles [1/s^2].

    ``L_kappa`` is the graph Laplacian with connector weights ``kappa`` (E,)
    [N/m]; a connector to a fixed particle keeps its diagonal term (the rows and
    columns of fixed particles are dropped).
    """
    free = ~model.fixed
    index = np.full(model.n_particles, -1, dtype=np.int64)
    index[free] = np.arange(int(free.sum()))
    i, j = model.edges[:, 0], model.edges[:, 1]
    kappa = np.asarray(kappa, dtype=np.float64)
    m = model.masses
    both = free[i] & free[j]
    rows = np.concatenate([index[i], index[j], index[i][both], index[j][both]])
    cols = np.concatenate([index[i], index[j], index[j][both], index[i][both]])
    coupling = -kappa[both] / np.sqrt(m[i][both] * m[j][both])
    values = np.concatenate([kappa / m[i], kappa / m[j], coupling, coupling])
    keep = rows >= 0  # drops the diagonal terms of the fixed ends
    n = int(free.sum())
    return sp.csr_matrix((values[keep], (rows[keep], cols[keep])), shape=(n, n))


def largest_eigenvalue(matrix: sp.csr_matrix) -> float:
    """Largest eigenvalue of a symmetric sparse matrix: dense below :data:`DENSE_EIGEN_LIMIT`
    rows, else Lanczos (``eigsh``, relative tolerance 1e-10, fixed start vector)."""
    n = matrix.shape[0]
    if n <= DENSE_EIGEN_LIMIT:
        return float(np.linalg.eigvalsh(matrix.toarray())[-1])
    # a fixed random start vector: reproducible limits, and (almost surely) not orthogonal to
    # the top mode
    start = np.random.default_rng(0).uniform(0.5, 1.5, n)
    try:
        return float(eigsh(matrix, k=1, which="LA", tol=1e-10, v0=start,
                           return_eigenvectors=False)[0])
    except ArpackNoConvergence as exc:
        raise StabilityError(f"the stability limit's eigenvalue solve (n = {n}) did not "
                             f"converge: {exc}") from None


def critical_time_step(model: Model, params: ConnectorParams | None = None, *,
                       strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                       damping: float = 0.0) -> float:
    """Stability limit [s] of the explicit step: ``2/omega_max`` (less with damping).

    ``strain_range`` is where the connectors' strains stay during the run: one
    (lo, hi) pair, or per-connector ``(lo (E,), hi (E,))`` arrays (e.g.
    :func:`strain_range_for_release`); :class:`Run` verifies it while stepping.

    The bound is rigorous for any state with strains in that range. Each
    connector's 3x3 tangent block ``A_e`` satisfies ``A_e <= kappa_e I_3`` in the
    Loewner order (:func:`connector_stiffness_bound`), so the tangent stiffness
    ``K_t = sum_e B_e^T A_e B_e`` (``B_e x = x_j - x_i``) satisfies ``K_t <=
    sum_e kappa_e B_e^T B_e = L_kappa (x) I_3``, restricted to the free
    particles. Congruence with ``M^{-1/2}`` keeps the order, hence
    ``omega_max^2 = lambda_max(M^{-1/2} K_t M^{-1/2}) <= lambda_max(M^{-1/2}
    L_kappa M^{-1/2})``, the largest eigenvalue of a scalar Nf x Nf matrix
    (:func:`mass_scaled_laplacian`; Kronecker with I_3 does not change
    eigenvalues). It is computed (:func:`largest_eigenvalue`) and multiplied by
    :data:`EIGENVALUE_MARGIN`. This is never above the block-Gershgorin bound
    of the same matrix (the largest row sum), usually well below. With
    mass-proportional damping gamma the central-difference limit becomes
    ``(2/omega)(sqrt(1 + xi^2) - xi)``, ``xi = gamma/(2 omega)``.

    With the volume term (``params.kv`` given), ``K_t = K_springs + K_vol`` and
    ``lambda_max(A + B) <= lambda_max(A) + lambda_max(B)``: the bound of the
    volume term (:func:`particle.volume.volume_frequency_bound`, the smaller of
    Irons' element bound and a per-particle one; valid
    while the tets' volume ratios stay in :func:`particle.volume.volume_ratio_range`,
    which the runs verify) is added to omega_max^2. (A first version put each
    tet's bound on its six edges of the Laplacian: 2x more pessimistic in
    omega^2 on a Kuhn box.)

    Raises:
        ParameterError: the parameters are non-physical on ``strain_range``
            (:meth:`ConnectorParams.validate`, e.g. a negative K0), naming the connector.
    """
    p = model.params if params is None else params
    # a non-physical model (K0 <= 0, ...) has no meaningful limit: refused, naming the connector
    p.validate(strain_range, model.edges, model.tets)
    if not (~model.fixed).any():
        return math.inf  # nothing moves
    lo, hi = connector_strain_bounds(strain_range, model.n_connectors, model.edges)
    kappa = connector_stiffness_bound(p, lo, hi)
    omega2 = EIGENVALUE_MARGIN * largest_eigenvalue(mass_scaled_laplacian(model, kappa))
    if p.kv is not None:
        omega2 += volume_frequency_bound(model.with_params(p), lo, hi)
    if not omega2 > 0.0:
        return math.inf  # no stiffness at all: nothing oscillates
    omega = math.sqrt(omega2)
    xi = damping / (2.0 * omega)
    return 2.0 / omega * (math.sqrt(1.0 + xi * xi) - xi)


def strain_range_for_release(model: Model, static_displacement: np.ndarray, margin: float
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Per-connector strain range (lo (E,), hi (E,)) of a release from rest under a static load.

    Released from rest in the undeformed shape, a connector overshoots to about
    twice its static strain ``eps_s`` (undamped, linear: exactly twice), so the
    range is ``[min(0, 2 eps_s) - margin, max(0, 2 eps_s) + margin]``, except
    that a compression is capped at half the static length, ``lo >= (eps_s -
    1)/2`` (twice a static strain near -0.5 would reach zero length; the
    viscoelastic arms keep strongly compressed connectors well short of twice
    their static strain). The run verifies the range (:class:`Run`).
    ``static_displacement`` (N, 3) [m] is the static solution (e.g.
    :func:`particle.statics.gravity_static`).
    """
    if not (math.isfinite(margin) and margin >= 0.0):
        raise ParameterError(f"strain margin = {margin} must be >= 0")
    x = model.rest_positions + np.asarray(static_displacement, dtype=np.float64).reshape(-1, 3)
    if x.shape != model.rest_positions.shape:
        raise ParameterError(f"static displacement of shape {np.shape(static_displacement)} "
                             f"does not fit the model's {model.n_particles} particles")
    d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
    static = np.linalg.norm(d, axis=1) / model.rest_lengths - 1.0
    lo = np.maximum(np.minimum(2.0 * static, 0.0) - margin, 0.5 * (static - 1.0))
    hi = np.maximum(2.0 * static, 0.0) + margin
    return connector_strain_bounds((lo, hi), model.n_connectors, model.edges)


def resolve_time_step(section: ParticleSection, critical: float) -> float:
    """The scene's explicit step [s] for a model whose stability limit is ``critical`` [s]
    (:func:`critical_time_step` with ``section.damping``): dt_safety x critical for 'auto',
    else the checked number."""
    if section.dt == "auto":
        return section.dt_safety * critical
    check_time_step(float(section.dt), critical)
    return float(section.dt)


def check_time_step(dt: float, critical: float) -> None:
    """Raise :class:`StabilityError` if ``dt`` is not a positive step below ``critical``."""
    if not (math.isfinite(dt) and dt > 0.0):
        raise StabilityError(f"time step dt = {dt} s must be a finite number > 0")
    if dt > critical:
        raise StabilityError(f"time step dt = {dt:.4g} s is above the stability limit "
                             f"{critical:.4g} s of this model (use particle.dt = 'auto' or a "
                             "smaller step)")


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


def inertial_model(model: Model, inertia: np.ndarray) -> Model:
    """``model`` with the inertial masses ``inertia`` (N,) [kg] as its masses (mass scaling).

    What the stability analysis of a mass-scaled run sees (:func:`critical_time_step`
    of it is the limit of the run); the run itself keeps ``model`` for the loads
    (gravity, damping act on the physical masses). ``inertia`` must be finite and at
    least the physical mass of every particle (scaling only adds mass), else
    :class:`ParameterError` naming the first particle that is not.
    """
    inertia = np.asarray(inertia, dtype=np.float64)
    if inertia.shape != model.masses.shape:
        raise ParameterError(f"inertia of shape {inertia.shape} does not fit the model's "
                             f"{model.n_particles} particles")
    bad = np.nonzero(~(np.isfinite(inertia) & (inertia >= model.masses)))[0]
    if len(bad):
        n = int(bad[0])
        raise ParameterError(f"particle {n}: inertia {inertia[n]:.6g} kg must be finite and at "
                             f"least its mass {model.masses[n]:.6g} kg (mass scaling only adds "
                             "mass)")
    return dataclasses.replace(model, masses=inertia)


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
    blocks of nodes (:func:`particle.step_kernels.parallel_forces`,
    :func:`~particle.step_kernels.parallel_advance`): two numba parallel regions per
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
            status = step_kernels.run_verlet(
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
        if code == step_kernels.VOLUME:
            self._raise_volume_exit(state, node, step)
        if code == step_kernels.STRAIN:
            self._raise_strain_exit(state, node, state.t + (step - 1) * dt)
        if code != step_kernels.OK:
            what = ("has a non-finite position" if code == step_kernels.NONFINITE else
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
            node_volume_force(state.x, node, tets, *self._volume, out)
        return out
