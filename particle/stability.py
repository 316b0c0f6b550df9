"""Stability of the explicit particle step: the stable-step bound and the strain ranges it holds on.

The step of :class:`~particle.integrator.VerletIntegrator` is stable below
``2/omega_max``; :func:`critical_time_step` bounds ``omega_max`` rigorously for
every state whose connector strains (and, with the volume term, tets' volume ratios)
stay in given ranges (the run verifies them while stepping). The ranges come from here
too: the default +-0.5, the range of a release from a static sag
(:func:`strain_range_for_release`, :func:`release_strain_range` for the gravity stage,
and each tet's :func:`release_volume_range`, all from :func:`overshoot_range`), the
interval where a nonlinear spring stays positive (:func:`positive_spring_range`). The
empirical limit the bound is checked against by the tests and ``make bench`` is in
:mod:`pipelines.bench.empirical_limit` (a bisection over real runs of the integrator).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import ArpackNoConvergence, eigsh

from forcecal.errors import ParameterError, StabilityError, TimeStepError
from forcecal.scene import ParticleSection
from particle.model import Model
from particle.params import ConnectorParams, StrainBounds, connector_strain_bounds
from particle.volume import signed_volumes
from particle.volume_bounds import volume_ratio_range, volume_step_bounds

log = logging.getLogger(__name__)

#: connector strains [1] a run stays in unless told otherwise
DEFAULT_STRAIN_RANGE = (-0.5, 0.5)
# the computed lambda_max is multiplied by this: it covers the eigensolver's tolerance (1e-10
# relative) and rounding with a wide margin, at a cost of 0.05 % of the step
EIGENVALUE_MARGIN = 1.001
# free particles up to which the dense eigensolver is used: Lanczos is faster beyond (measured
# on Kuhn boxes: 294 free particles 6.6 ms dense, 1.2 ms Lanczos; 1089: 227 ms, 2.9 ms)
DENSE_EIGEN_LIMIT = 100



def connector_stiffness_bound(params: ConnectorParams, lo: np.ndarray, hi: np.ndarray,
                              history: tuple[np.ndarray, np.ndarray] | None = None
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

    ``history`` (lo (E,), hi (E,)): the strain hull every past elongation of the run
    stayed in (it holds ``[lo, hi]`` and 0, the rest state; None: ``[lo, hi]``
    itself). Then the arms' transverse part is the tighter ``k_i (hi - h_lo)/(1 +
    hi)``: the arm force is ``c_i (dx - m)`` with ``c_i <= k_i`` and ``m`` a convex
    combination of the past elongations and of the rest state's 0 (the backward-Euler
    recursion ``F/c = r (F_prev/c_prev + dx - dx_prev)``, ``0 <= r <= 1``, keeps ``dx
    - F/c`` a convex combination of the elongations whatever the steps), so ``F_arm/l
    <= k_i (eps - h_lo)/(1 + eps)``, increasing in ``eps`` while ``1 + h_lo > 0``.
    """
    _, tangent = params.extreme_tangent_stiffness((lo, hi))
    kmin, kmax = params.extreme_stiffness((lo, hi))
    arms = params.k1 + params.k2
    spring = np.maximum(np.maximum(kmax, 0.0) * hi / (1.0 + hi),
                        np.maximum(-kmin, 0.0) * -lo / (1.0 + lo))
    if history is None:
        transverse = spring + arms * (hi - lo) / (1.0 + lo)
    else:
        transverse = spring + arms * np.maximum(hi - history[0], 0.0) / (1.0 + hi)
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


@dataclasses.dataclass(frozen=True)
class StepBound:
    """The bound ``omega_max^2 <= omega2`` of :func:`critical_time_step` and the matrices it is
    made of, so that what sets the step is read off the bound the step is taken from
    (:func:`pipelines.realtime.step_limiters`).

    ``omega2 = laplacian_part + volume_part``: ``laplacian_part`` is
    :data:`EIGENVALUE_MARGIN` x the largest eigenvalue of ``laplacian`` (the mass-scaled graph
    Laplacian of the connector weights ``kappa``); ``volume_part`` is the volume term's own
    bound when it is added separately (then ``volume_matrix`` is
    :func:`particle.volume_bounds.volume_scalar_matrix`), else 0 and None (no volume term, or
    the joint bound is the smaller: ``kappa`` then includes the term's edge weights).

    Attributes:
        omega2: the bound [1/s^2].
        kappa: (E,) connector weights of ``laplacian`` [N/m].
        laplacian: (Nf, Nf) ``M^{-1/2} L_kappa M^{-1/2}`` [1/s^2] on the free particles.
        laplacian_part: its part of ``omega2`` [1/s^2].
        volume_part: the volume term's own part of ``omega2`` [1/s^2].
        volume_matrix: (Nf, Nf) the volume term's scalar matrix [1/s^2], or None.
    """

    omega2: float
    kappa: np.ndarray
    laplacian: sp.csr_matrix
    laplacian_part: float
    volume_part: float = 0.0
    volume_matrix: sp.csr_matrix | None = None


def step_bound(model: Model, strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
               history: StrainBounds | None = None,
               volume_range: tuple[np.ndarray, np.ndarray] | None = None) -> StepBound:
    """The ``omega_max^2`` bound of :func:`critical_time_step` for ``model`` (its own parameters,
    validated on ``strain_range``, and at least one free particle): with the volume term the
    smaller of the springs' bound plus the term's own and the joint bound (see there).
    ``history``: the strain hull the run's past elongations stayed in, for the arms'
    forces (:func:`connector_stiffness_bound`; None: ``strain_range``, the classic bound).
    ``volume_range``: the tets' verified volume ratios
    (:func:`particle.volume_bounds.verified_ratio_range`; None: those of ``strain_range``)."""
    p = model.params
    lo, hi = connector_strain_bounds(strain_range, model.n_connectors, model.edges)
    past = None if history is None else strain_history(history, lo, hi, model)
    kappa = connector_stiffness_bound(p, lo, hi, past)
    laplacian = mass_scaled_laplacian(model, kappa)
    springs = EIGENVALUE_MARGIN * largest_eigenvalue(laplacian)
    if p.kv is None:
        return StepBound(springs, kappa, laplacian, springs)
    own, edge_weights, scalar = volume_step_bounds(model, lo, hi, past, volume_range)
    own = min(own, EIGENVALUE_MARGIN * largest_eigenvalue(scalar))
    joint_kappa = kappa + edge_weights
    joint_laplacian = mass_scaled_laplacian(model, joint_kappa)
    joint = EIGENVALUE_MARGIN * largest_eigenvalue(joint_laplacian)
    if joint < springs + own:
        return StepBound(joint, joint_kappa, joint_laplacian, joint)
    return StepBound(springs + own, kappa, laplacian, springs, own, scalar)


def strain_history(history: StrainBounds, lo: np.ndarray, hi: np.ndarray, model: Model
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(E,) (lo, hi): ``history`` as per-connector arrays, widened to hold ``[lo, hi]`` and the
    rest state's 0 (the hull the arms' convolution averages over)."""
    h_lo, h_hi = connector_strain_bounds(history, model.n_connectors, model.edges)
    return np.minimum(np.minimum(h_lo, lo), 0.0), np.maximum(np.maximum(h_hi, hi), 0.0)


def critical_time_step(model: Model, params: ConnectorParams | None = None, *,
                       strain_range: StrainBounds = DEFAULT_STRAIN_RANGE,
                       damping: float = 0.0,
                       volume_range: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Stability limit [s] of the explicit step: ``2/omega_max`` (less with damping).

    ``strain_range`` is where the connectors' strains stay during the run: one
    (lo, hi) pair, or per-connector ``(lo (E,), hi (E,))`` arrays (e.g.
    :func:`strain_range_for_release`); :class:`Run` verifies it while stepping.
    ``volume_range`` (J_lo (T,), J_hi (T,)): with the volume term, each tet's volume
    ratios V/V0 [1] the run verifies (e.g. :func:`release_volume_range`; None:
    :func:`particle.volume_bounds.volume_ratio_range` of ``strain_range``).

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

    With the volume term (``params.kv`` given), ``K_t = K_springs + K_vol``, and the
    smaller of two bounds is taken, each valid while the tets' volume ratios stay in
    :func:`particle.volume_bounds.verified_ratio_range` (which the runs verify):

    * ``lambda_max(A + B) <= lambda_max(A) + lambda_max(B)``: the volume term's own
      bound added to omega_max^2, the smallest of Irons' element bound, a per-particle one
      (:func:`particle.volume_bounds.volume_frequency_bound`) and the largest eigenvalue of
      :func:`particle.volume_bounds.volume_scalar_matrix` (times the margin), a nonnegative
      scalar matrix whose row sums are the per-particle bound (kv 8.9 kPa, strains +-0.5:
      stable step 0.249 -> 0.287 ms on the 12k-connector liver, 5 -> 4 haptic substeps at
      ``dt_safety`` 0.9; 0.546 -> 0.706 ms on the 1400-connector liver, 3 -> 2);
    * ``K_vol <= L_w (x) I_3`` (:func:`particle.volume_bounds.volume_edge_stiffness_bound`,
      each tet's bound on its six edges after removing its rigid translation), so
      ``K_t <= L_{kappa + w} (x) I_3``: one eigenvalue of the sum, which lets the
      springs' and the tets' stiffest modes differ (tighter on fine meshes: kv 8.9 kPa,
      strains +-0.5, stable step 0.217 -> 0.249 ms on the 12k-connector liver, 0.139 ->
      0.169 ms on the 54k one, 0.541 -> 0.546 ms on the 1400-connector liver).

    Raises:
        ParameterError: the parameters are non-physical on ``strain_range``
            (:meth:`ConnectorParams.validate`, e.g. a negative K0), naming the connector.
    """
    p = model.params if params is None else params
    # a non-physical model (K0 <= 0, ...) has no meaningful limit: refused, naming the connector
    p.validate(strain_range, model.edges, model.tets)
    if not (~model.fixed).any():
        return math.inf  # nothing moves
    return stable_step(step_bound(model if params is None else model.with_params(p),
                                  strain_range, volume_range=volume_range).omega2, damping)


def stable_step(omega2: float, damping: float = 0.0) -> float:
    """The central-difference limit [s] for the largest frequency ``sqrt(omega2)`` [1/s] and
    mass-proportional damping [1/s]: ``(2/omega)(sqrt(1 + xi^2) - xi)``, ``xi = damping/(2
    omega)`` (inf without stiffness)."""
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
    their static strain): :func:`overshoot_range` of the static strains. The run
    verifies the range (:class:`Run`). ``static_displacement`` (N, 3) [m] is the
    static solution (e.g. :func:`particle.statics.gravity_static`).
    """
    x = _static_positions(model, static_displacement)
    d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
    static = np.linalg.norm(d, axis=1) / model.rest_lengths - 1.0
    lo, hi = overshoot_range(static, margin)
    return connector_strain_bounds((np.maximum(lo, 0.5 * (static - 1.0)), hi),
                                   model.n_connectors, model.edges)


def strain_range_of_states(model: Model, displacements: np.ndarray, margin: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Per-connector strain range (lo (E,), hi (E,)) of static states: each connector's strain
    at rest and in every state of ``displacements`` (L, N, 3) [m] (e.g. the FE's states under
    the whole-body loads a calibration fits), widened by ``margin`` >= 0, a compression capped
    at half its way to zero length, ``lo >= (eps - 1)/2``, as :func:`strain_range_for_release`
    caps it. A state is where the model is used, not released from, so no overshoot."""
    if not (math.isfinite(margin) and margin >= 0.0):
        raise ParameterError(f"strain margin = {margin} must be >= 0")
    states = np.asarray(displacements, dtype=np.float64)
    if states.ndim != 3 or states.shape[1:] != model.rest_positions.shape:
        raise ParameterError(f"displacements of shape {states.shape} are not (L, "
                             f"{model.n_particles}, 3) states of the model's particles")
    eps = connector_strains(model, states)  # (L, E)
    lo = np.minimum(0.0, np.min(np.maximum(eps - margin, 0.5 * (eps - 1.0)), axis=0,
                                initial=0.0))
    hi = np.maximum(0.0, np.max(eps + margin, axis=0, initial=0.0))
    return connector_strain_bounds((lo, hi), model.n_connectors, model.edges)


def overshoot_range(static: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [1] around each static strain ``static`` [1] (a connector's length strain or a
    tet's volume strain) that a release from rest reaches: ``[min(0, 2 s) - margin, max(0, 2
    s) + margin]``, twice the static strain (the undamped linear overshoot) widened by
    ``margin`` >= 0. The callers bound its compressive end, each by what its stability
    bound can take (:func:`strain_range_for_release`, :func:`release_volume_range`)."""
    if not (math.isfinite(margin) and margin >= 0.0):
        raise ParameterError(f"strain margin = {margin} must be >= 0")
    static = np.asarray(static, dtype=np.float64)
    return np.minimum(2.0 * static, 0.0) - margin, np.maximum(2.0 * static, 0.0) + margin


def _static_positions(model: Model, static_displacement: np.ndarray) -> np.ndarray:
    """(N, 3) positions [m] of the static state ``static_displacement`` (N, 3) [m] (its shape
    checked against the model)."""
    x = model.rest_positions + np.asarray(static_displacement, dtype=np.float64).reshape(-1, 3)
    if x.shape != model.rest_positions.shape:
        raise ParameterError(f"static displacement of shape {np.shape(static_displacement)} "
                             f"does not fit the model's {model.n_particles} particles")
    return x


def resolve_time_step(section: ParticleSection, critical: float) -> float:
    """The scene's explicit step [s] for a model whose stability limit is ``critical`` [s]
    (:func:`critical_time_step` with ``section.damping``): dt_safety x critical for 'auto',
    else the checked number (:class:`~forcecal.errors.TimeStepError` above ``critical``)."""
    if section.dt == "auto":
        return section.dt_safety * critical
    try:
        check_time_step(float(section.dt), critical)
    except StabilityError as exc:
        raise TimeStepError(str(exc)) from None
    return float(section.dt)


def check_time_step(dt: float, critical: float) -> None:
    """Raise :class:`StabilityError` if ``dt`` is not a positive step below ``critical``."""
    if not (math.isfinite(dt) and dt > 0.0):
        raise StabilityError(f"time step dt = {dt} s must be a finite number > 0")
    if dt > critical:
        raise StabilityError(f"time step dt = {dt:.4g} s is above the stability limit "
                             f"{critical:.4g} s of this model (use particle.dt = 'auto' or a "
                             "smaller step)")


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


# ---------------------------------------------------------------------------- strain ranges

#: a release range ends this fraction of the way to the strain where a spring's K(eps) is 0
SOFT_SPRING_CLEARANCE = 0.95


def positive_spring_range(params: ConnectorParams) -> tuple[np.ndarray, np.ndarray]:
    """(lo (E,), hi (E,)): the strain interval around 0 in which each connector's spring
    ``K(eps) = K0 + a eps + b eps^2`` stays > 0 [1] (the roots of K nearest to 0 on either
    side; -inf / +inf on a side where K never reaches 0)."""
    K0, a, b = params.K0, params.a, params.b
    lo = np.full(params.n_connectors, -np.inf)
    hi = np.full(params.n_connectors, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        linear = b == 0.0
        root = -K0 / a
        lo = np.where(linear & (a > 0.0), root, lo)
        hi = np.where(linear & (a < 0.0), root, hi)
        disc = a * a - 4.0 * b * K0
        real = ~linear & (disc >= 0.0)
        sq = np.sqrt(np.maximum(disc, 0.0))
        r1, r2 = (-a - sq) / (2.0 * b), (-a + sq) / (2.0 * b)
        rmin, rmax = np.minimum(r1, r2), np.maximum(r1, r2)
        below = np.where(rmax < 0.0, rmax, np.where(rmin < 0.0, rmin, -np.inf))
        above = np.where(rmin > 0.0, rmin, np.where(rmax > 0.0, rmax, np.inf))
    return np.where(real, below, lo), np.where(real, above, hi)


def release_strain_range(model: Model, static: np.ndarray, margin: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per-connector strain range of the gravity release: :func:`strain_range_for_release`
    (twice the static sag's strain, widened by ``margin``), cut to
    :data:`SOFT_SPRING_CLEARANCE` of the way to the strain where the connector's spring
    would lose its stiffness (a calibrated spring is positive on the calibrated range,
    not necessarily beyond it). The step is chosen for this range and the run verifies
    it, so a connector that would reach a soft spring stops the run with a clear error
    instead of the release being refused before it starts. ``static`` (N, 3) [m] must
    have positive springs (:func:`particle.statics.check_stiffness`).
    """
    lo, hi = strain_range_for_release(model, static, margin)
    soft_lo, soft_hi = positive_spring_range(model.params)
    eps = connector_strains(model, static)
    cut_lo = np.maximum(lo, np.minimum(SOFT_SPRING_CLEARANCE * soft_lo, np.minimum(eps, 0.0)))
    cut_hi = np.minimum(hi, np.maximum(SOFT_SPRING_CLEARANCE * soft_hi, np.maximum(eps, 0.0)))
    cut = int(np.count_nonzero((cut_lo > lo) | (cut_hi < hi)))
    if cut:
        log.info("gravity release: %d connector(s) verified on a narrower strain range than "
                 "twice their static strain +- %g: their springs would lose stiffness there",
                 cut, margin)
    return cut_lo, cut_hi


def release_volume_range(model: Model, static: np.ndarray, margin: float,
                         strain_range: tuple[np.ndarray, np.ndarray]
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-tet volume ratio range (J_lo (T,), J_hi (T,)) [1] of the gravity release from the
    static sag ``static`` (N, 3) [m] whose strain range is ``strain_range`` (lo (E,), hi (E,),
    e.g. :func:`release_strain_range`); None without the volume term (nothing to verify).

    A tet's edges do not bound its volume: a sliver flattened by the sag loses volume while
    its edges stretch, so :func:`particle.volume_bounds.volume_ratio_range` of the strain
    range (the uniform dilations of each tet's connector ranges) can miss the tet's own
    static volume ratio ``J_s`` and its overshoot. The range is that one widened to hold
    ``1 +`` :func:`overshoot_range` of the tet's static volume strain ``J_s - 1`` (the
    connectors' rule: twice the static volume strain widened by ``margin``), its lower end
    cut at 0, where the run stops anyway (an inverted tet). Unlike a connector's, a
    compression is not capped short of that: the volume term's pressure bound stays finite
    down to ``V = 0`` (``kv |J - 1| <= kv`` below rest,
    :func:`particle.volume_bounds._tet_bounds`), while a spring's transverse stiffness grows
    without bound as its length goes to 0. Where the cube range already holds the overshoot
    it is the cube range, unchanged. The step is chosen for this range
    (:func:`particle.volume_bounds.verified_ratio_range`) and the run verifies it.
    """
    if model.params.kv is None:
        return None
    lo, hi = volume_ratio_range(model, *strain_range)
    ratio = signed_volumes(_static_positions(model, static), model.tets) / model.rest_volumes
    own_lo, own_hi = overshoot_range(ratio - 1.0, margin)
    wider = (own_lo + 1.0 < lo) | (own_hi + 1.0 > hi)
    if wider.any():
        log.info("gravity release: %d tet(s) verified on a wider volume ratio range than their "
                 "connectors' strain ranges give: their static volume ratios (%.3g .. %.3g) need "
                 "it", int(np.count_nonzero(wider)), float(ratio[wider].min()),
                 float(ratio[wider].max()))
    return (np.maximum(np.minimum(lo, own_lo + 1.0), 0.0), np.maximum(hi, own_hi + 1.0))


def connector_strains(model: Model, displacement: np.ndarray) -> np.ndarray:
    """(..., E) connector strains [1] of displacements (..., N, 3) [m]."""
    x = model.rest_positions + displacement
    d = x[..., model.edges[:, 1], :] - x[..., model.edges[:, 0], :]
    return np.linalg.norm(d, axis=-1) / model.rest_lengths - 1.0
