"""Strain bands that follow the state and their stability bound, refreshed within one haptic call.

:class:`StrainBands` holds what :class:`particle.haptics.HapticSession` ``envelope`` verifies
and steps on: per-connector strain bands ``[lo, hi]`` of half-width w around the strains the
bands were last centred on, per-tet volume ratio ranges ``[J_lo, J_hi]``, the hulls of every
band and range used so far (the arms' memory) and an upper bound ``omega2`` of the
mass-scaled tangent's largest eigenvalue at every state inside them. Centring them again
(:meth:`StrainBands.centre`) moves the bands of the connectors whose strains have drifted
more than a quarter of w from their centres (and the ranges of those connectors' tets, and
of the tets whose ratios drifted likewise), then refreshes the bound: a few passes over the
connectors and tets in compiled loops, no eigensolve (the bench's drag, 10,000 calls, one
core: a call that re-centres takes at most 0.3 / 0.7 / 1.5 ms on the 12k-connector liver
with springs / the volume term / the relaxing volume term, against 0.13 / 0.43 / 0.43 ms for
a median call; the refresh itself about 0.25 ms with the volume term, 1 ms on the 54k one).

The bound is the one of :func:`particle.stability.step_bound` (springs and volume term
added): ``K_t <= L_kappa (x) I_3 + K_vol`` and ``v^T K_vol v <= |v|^T S |v|`` with the
connector weights ``kappa`` of :func:`particle.stability.connector_stiffness_bound` (the
arms bounded over the bands' history) and the volume term's scalar matrix ``S`` of
:func:`particle.volume_bounds.volume_scalar_matrix` (its pressure bounded over the tets'
ratio ranges and their history), so ``omega_max^2 <= lambda_max(M^{-1/2} L_kappa M^{-1/2})
+ lambda_max(M^{-1/2} S M^{-1/2})``. Each eigenvalue is bounded without solving for it:

* the Laplacian's largest eigenvalue is at most its signless twin's ``|L| = D + A``
  (``x^T L x <= |x|^T |L| |x|``), a nonnegative matrix, as is ``S``;
* for a nonnegative matrix Q and any positive vector x, ``lambda_max(Q) <= max_i (Q x)_i /
  x_i`` (Collatz-Wielandt: Q x <= c x makes the x-weighted max norm of Q at most c).

x is each matrix's Perron vector, kept with its product ``Q x`` (updated for the bands
that move, so the bound at x costs one scan of the particles), and refreshed by up to
:data:`POWER_ITERATIONS` rounds of (over-relaxed) power iterations, one pass over the
connectors or tets each, only while the bound would need more substeps than the session
takes; every iterate gives a bound and the smallest is taken, times
:data:`particle.stability.EIGENVALUE_MARGIN` for rounding. The Perron vectors of the first
bands come from Lanczos (:func:`scipy.sparse.linalg.eigsh`, when the session starts).
Measured on the bench's livers with bands of half-width 0.05: the signless Laplacian's
eigenvalue is 5.5 % (12k connectors) and 1.2 % (54k) above the Laplacian's; during the
bench's 5 mm drag on the 12k liver with the relaxing volume term the bound rises to 7 %
above the eigensolved bound of the same bands (:func:`particle.stability.step_bound`; 5 %
with two rounds at every centring), still 3 substeps per ms as with the eigensolve. The
joint bound of ``step_bound`` (one Laplacian with the volume term's edge weights) is not
used: on bands this narrow the sum is the smaller (12k liver, relaxing volume: 2.7e7
against 3.3e7 1/s^2).

A tet's volume ratio is not bounded by its edges' strains (a flat tet gains or loses
volume fast), so its range is the one of the uniform dilations of its bands, ``((1 + min
lo)^3, (1 + max hi)^3)`` (:func:`particle.volume_bounds.volume_ratio_range`), widened to
hold ``J0 (1 -+ w)^3`` when its ratio ``J0`` at the centring is not in the range's middle
half: the state a centring starts from is always well inside its new ranges, and a tet
whose ratio leaves the inner half of its range is centred again like a connector. The run
verifies the same arrays the bound is computed from (:meth:`particle.integrator.Run.retarget`),
so no state outside the bands and ranges is stepped from: it stops with StabilityError.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit
from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

from forcecal.errors import ParameterError, StabilityError
from particle.kernels import JIT
from particle.model import Model
from particle.params import connector_name
from particle.stability import DENSE_EIGEN_LIMIT, EIGENVALUE_MARGIN
from particle.nodal_volume import refuse_nodal
from particle.volume import tet_name

log = logging.getLogger(__name__)

#: most rounds of power iterations per centring (each one pass over the connectors and one
#: over the tets), done only while the bound asks for more substeps than the session takes
POWER_ITERATIONS = 4
# the power iteration's step x <- x (r/c)^1.5 (module docstring): after a centring that
# stiffens the tool's region, the Perron vector adapts there slowly (the rows' ratios near
# the eigenvalue); the over-relaxed step brings the bound closer per iteration (measured on the
# 12k liver's volume matrix after a drag: 8 iterations 1.5 % above the eigenvalue against
# 2.0 % for the plain step; 3 oscillates)
OVER_RELAXATION = 1.5
# power iterations after Lanczos when the bands start: Lanczos gets the Perron vector's small
# entries (far from the stiffest region) wrong by its tolerance, which the Collatz-Wielandt
# ratios of their rows magnify (13 % above the eigenvalue on the 12k liver); a few dozen
# iterations bring it to the eigenvalue of the signless matrix (0.01 %)
STARTING_ITERATIONS = 30
# floor of a Perron vector's entries relative to its largest: keeps every entry positive (the
# Collatz-Wielandt bound needs x > 0) where the matrix's row is empty
PERRON_FLOOR = 1e-12
# the tets' faces opposite each vertex, as the connectors (TET_PAIRS order) of their sides
FACES = np.array([[3, 4, 5], [1, 2, 5], [0, 2, 4], [0, 1, 3]])


@njit(**JIT)
def _quadratic_extremes(c0, c1, c2, lo, hi):
    """(min, max) of ``c0 + c1 eps + c2 eps^2`` over ``[lo, hi]``, scalar twin of
    :func:`particle.params._quadratic_extremes`."""
    at_lo = c0 + (c1 + c2 * lo) * lo
    at_hi = c0 + (c1 + c2 * hi) * hi
    at_vertex = at_lo
    if np.sign(c1 + 2.0 * c2 * lo) * np.sign(c1 + 2.0 * c2 * hi) < 0.0:
        vertex = -c1 / (2.0 * c2)
        at_vertex = c0 + (c1 + c2 * vertex) * vertex
    return min(min(at_lo, at_hi), at_vertex), max(max(at_lo, at_hi), at_vertex)


@njit(**JIT)
def centre_connectors(x, edges, rest_lengths, half_width, centre, lo, hi, history_lo,
                      history_hi, inner_lo, inner_hi, elongation_lo, elongation_hi, moved,
                      every):
    """Centre the band of every connector (``every``) or of those whose strain at ``x`` (N, 3)
    [m] has left the inner half of their inner half, in place (``moved`` (E,) marks them):
    ``centre`` the strain ``eps``, ``[lo, hi] = [max(eps - w, (eps - 1)/2), eps + w]``
    (never below half the length), the history hull widened to hold it, the band and its
    inner half ``[(lo + eps)/2, eps + w/2]`` as elongations [m]. Returns how many moved."""
    count = 0
    for e in range(edges.shape[0]):
        i, j = edges[e, 0], edges[e, 1]
        d0 = x[j, 0] - x[i, 0]
        d1 = x[j, 1] - x[i, 1]
        d2 = x[j, 2] - x[i, 2]
        length = rest_lengths[e]
        eps = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / length - 1.0
        c = centre[e]
        moved[e] = every or not 0.25 * (lo[e] + 3.0 * c) <= eps <= c + 0.25 * half_width
        if not moved[e]:
            continue
        count += 1
        centre[e] = eps
        lo[e] = max(eps - half_width, 0.5 * (eps - 1.0))
        hi[e] = eps + half_width
        history_lo[e] = min(history_lo[e], lo[e])
        history_hi[e] = max(history_hi[e], hi[e])
        inner_lo[e] = 0.5 * (lo[e] + eps) * length
        inner_hi[e] = (eps + 0.5 * half_width) * length
        elongation_lo[e] = lo[e] * length
        elongation_hi[e] = hi[e] * length
    return count


@njit(**JIT)
def connector_weights(K0, a, b, arms, lo, hi, history_lo, moved, kappa, edges, scale, x, y):
    """``kappa`` (E,) [N/m] of :func:`particle.stability.connector_stiffness_bound` with the
    bands' history (its lower end ``history_lo`` (E,), holding 0 and ``lo``), in place, on
    the ``moved`` connectors (E,), and ``y = M^{-1/2} |L_kappa| M^{-1/2} x`` (N,) updated
    for their change (:func:`laplacian_product`). Returns the first of them whose spring
    ``K(eps)`` is not > 0 somewhere in its band (-1: none)."""
    soft = -1
    for e in range(lo.shape[0]):
        if not moved[e]:
            continue
        l, h = lo[e], hi[e]
        _, tangent = _quadratic_extremes(K0[e], 2.0 * a[e], 3.0 * b[e], l, h)
        kmin, kmax = _quadratic_extremes(K0[e], a[e], b[e], l, h)
        if soft < 0 and not kmin > 0.0:
            soft = e
        spring = max(max(kmax, 0.0) * h / (1.0 + h), max(-kmin, 0.0) * -l / (1.0 + l))
        transverse = spring + arms[e] * max(h - history_lo[e], 0.0) / (1.0 + h)
        weight = max(max(tangent + arms[e], transverse), 0.0)
        _add_edge_product(edges, scale, x, y, e, weight - kappa[e])
        kappa[e] = weight
    return soft


@njit(**JIT)
def _add_edge_product(edges, scale, x, y, e, weight):
    """Add connector ``e``'s part of :func:`laplacian_product` with the weight ``weight``
    [N/m] to ``y``."""
    i, j = edges[e, 0], edges[e, 1]
    both = scale[i] * x[i] + scale[j] * x[j]
    y[i] += weight * scale[i] * both
    y[j] += weight * scale[j] * both


@njit(**JIT)
def _largest_area(a0, a1, b0, b1, c0, c1):
    """Scalar twin of :func:`particle.volume_bounds._max_triangle_area` [m^2]."""
    heron = ((a1 + b1 + c1) * max(-a0 + b1 + c1, 0.0) * max(a1 - b0 + c1, 0.0)
             * max(a1 + b1 - c0, 0.0))
    return min(0.25 * math.sqrt(heron), 0.5 * min(min(a1 * b1, b1 * c1), a1 * c1))


@njit(**JIT)
def _tet_volume(x, tets, t):
    """Signed volume [m^3] of tet ``t`` at ``x`` (N, 3) [m]."""
    p0, p1, p2, p3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    u0, u1, u2 = x[p1, 0] - x[p0, 0], x[p1, 1] - x[p0, 1], x[p1, 2] - x[p0, 2]
    v0, v1, v2 = x[p2, 0] - x[p0, 0], x[p2, 1] - x[p0, 1], x[p2, 2] - x[p0, 2]
    w0, w1, w2 = x[p3, 0] - x[p0, 0], x[p3, 1] - x[p0, 1], x[p3, 2] - x[p0, 2]
    return (u0 * (v1 * w2 - v2 * w1) + u1 * (v2 * w0 - v0 * w2)
            + u2 * (v0 * w1 - v1 * w0)) / 6.0


@njit(**JIT)
def centre_tets(x, tets, tet_connectors, rest_volumes, rest_lengths, half_width, lo, hi,
                moved, every, modulus, kv, arms_kv, centre, ratio_lo, ratio_hi, history_lo,
                history_hi, volume_lo, volume_hi, inner_lo, inner_hi, gradients, curvatures,
                scale, perron, product):
    """Centre the volume ratio range of every tet (``every``), of those with a ``moved``
    connector (E,) and of those whose ratio at ``x`` (N, 3) [m] has left the inner half of
    their inner half on ``x`` and the connector bands ``lo``, ``hi`` (E,), in place:
    ``centre`` the ratio ``J0``, ``[J_lo, J_hi] = ((1 + min lo)^3, (1 + max hi)^3)``,
    widened to hold ``J0 ((1 - w)^3, (1 + w)^3)`` when ``J0`` is not in its middle half,
    the history hull widened to hold it, the range as volumes [m^3], its inner half ``[(J_lo
    + J0)/2, (J_hi + J0)/2]`` as volume strains ``J - 1``, and the tets' ``S_t`` of
    :func:`particle.volume_bounds.volume_scalar_matrix` on them
    (:func:`particle.volume_bounds._tet_bounds`' per-tet bounds: Heron's face areas
    ``G_a``, the pressure ``|P| <= kv |J - 1|_max + (kv1 + kv2) max(J_hi - Jh_lo, Jh_hi -
    J_lo)``): ``S_t[a, b] = g_a g_b + (a != b) c_k`` with ``gradients`` (T, 4) ``g_a =
    sqrt(k/V0) G_a`` [N^0.5/m^0.5] and ``curvatures`` (T, 6) ``c_k = |P| lmax_k/6`` [N/m],
    k the edge opposite the pair (a, b). ``modulus``, ``kv``, ``arms_kv`` (T,) [Pa]: the
    instantaneous stiffness k, kv, and kv1 + kv2 (0: elastic). ``product`` (N,) ``=
    M^{-1/2} S M^{-1/2} perron`` is updated for the tets' change (:func:`scalar_product`).
    Returns the first tet that is flat or inverted at ``x`` (-1: none)."""
    shrink, grow = (1.0 - half_width) ** 3, (1.0 + half_width) ** 3
    lmin = np.empty(6)
    lmax = np.empty(6)
    for t in range(tets.shape[0]):
        v_rest = rest_volumes[t]
        ratio = _tet_volume(x, tets, t) / v_rest
        if not ratio > 0.0:
            return t
        c = centre[t]
        stale = every or not 0.25 * (ratio_lo[t] + 3.0 * c) <= ratio <= 0.25 * (ratio_hi[t]
                                                                                 + 3.0 * c)
        for k in range(6):
            stale = stale or moved[tet_connectors[t, k]]
        if not stale:
            continue
        _add_tet_product(tets, gradients, curvatures, scale, perron, product, t, -1.0)
        centre[t] = ratio
        smallest, largest = math.inf, -math.inf
        for k in range(6):
            e = tet_connectors[t, k]
            smallest = min(smallest, lo[e])
            largest = max(largest, hi[e])
            lmin[k] = (1.0 + lo[e]) * rest_lengths[e]
            lmax[k] = (1.0 + hi[e]) * rest_lengths[e]
        low, high = 1.0 + smallest, 1.0 + largest
        j_lo, j_hi = low * low * low, high * high * high
        quarter = 0.25 * (j_hi - j_lo)
        if not j_lo + quarter <= ratio <= j_hi - quarter:
            j_lo, j_hi = min(j_lo, ratio * shrink), max(j_hi, ratio * grow)
        ratio_lo[t], ratio_hi[t] = j_lo, j_hi
        history_lo[t] = min(history_lo[t], j_lo)
        history_hi[t] = max(history_hi[t], j_hi)
        volume_lo[t], volume_hi[t] = j_lo * v_rest, j_hi * v_rest
        inner_lo[t] = 0.5 * (j_lo + ratio) - 1.0
        inner_hi[t] = 0.5 * (j_hi + ratio) - 1.0
        pressure = kv[t] * max(1.0 - j_lo, j_hi - 1.0) + arms_kv[t] * max(
            j_hi - history_lo[t], history_hi[t] - j_lo)
        rank_one = math.sqrt(modulus[t] / v_rest) / 3.0
        for a in range(4):
            f0, f1, f2 = FACES[a, 0], FACES[a, 1], FACES[a, 2]
            gradients[t, a] = rank_one * _largest_area(lmin[f0], lmax[f0], lmin[f1], lmax[f1],
                                                       lmin[f2], lmax[f2])
        for k in range(6):
            curvatures[t, k] = pressure / 6.0 * lmax[k]
        _add_tet_product(tets, gradients, curvatures, scale, perron, product, t, 1.0)
    return -1


@njit(**JIT)
def laplacian_product(edges, kappa, scale, x, y):
    """``y = M^{-1/2} |L_kappa| M^{-1/2} x`` (N,): the signless mass-scaled graph Laplacian of
    :func:`particle.stability.mass_scaled_laplacian` (``scale`` (N,) = ``m^{-1/2}`` on free
    particles, 0 on fixed ones, whose rows and columns it drops)."""
    y[:] = 0.0
    for e in range(edges.shape[0]):
        _add_edge_product(edges, scale, x, y, e, kappa[e])


@njit(**JIT)
def scalar_product(tets, gradients, curvatures, scale, x, y):
    """``y = M^{-1/2} S M^{-1/2} x`` (N,) with the tets' ``gradients`` and ``curvatures`` of
    :func:`centre_tets` (``scale`` as :func:`laplacian_product`)."""
    y[:] = 0.0
    for t in range(tets.shape[0]):
        _add_tet_product(tets, gradients, curvatures, scale, x, y, t, 1.0)


@njit(**JIT)
def _add_tet_product(tets, gradients, curvatures, scale, x, y, t, sign):
    """Add ``sign`` x tet ``t``'s part of :func:`scalar_product` to ``y``."""
    n0, n1, n2, n3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    z0, z1, z2, z3 = scale[n0] * x[n0], scale[n1] * x[n1], scale[n2] * x[n2], scale[n3] * x[n3]
    g0, g1, g2, g3 = gradients[t, 0], gradients[t, 1], gradients[t, 2], gradients[t, 3]
    c = curvatures[t]  # by the edge opposite each pair: 01 -> 5, 02 -> 4, 03 -> 3, ...
    s = g0 * z0 + g1 * z1 + g2 * z2 + g3 * z3
    y[n0] += sign * scale[n0] * (g0 * s + c[5] * z1 + c[4] * z2 + c[3] * z3)
    y[n1] += sign * scale[n1] * (g1 * s + c[5] * z0 + c[2] * z2 + c[1] * z3)
    y[n2] += sign * scale[n2] * (g2 * s + c[4] * z0 + c[2] * z1 + c[0] * z3)
    y[n3] += sign * scale[n3] * (g3 * s + c[3] * z0 + c[1] * z1 + c[0] * z2)


@njit(**JIT)
def largest_ratio(x, y, free):
    """The Collatz-Wielandt bound ``max (y/x)`` over the ``free`` particles of ``y = Q x``."""
    bound = 0.0
    for n in range(x.shape[0]):
        if free[n]:
            bound = max(bound, y[n] / x[n])
    return bound


@njit(**JIT)
def power_step(x, y, free, floor, relaxation):
    """``x <- x (r/c)^relaxation`` for ``y = Q x``, with the rows' ratios ``r = y/x`` and
    their largest ``c`` over the ``free`` particles (1: the power iteration, above:
    over-relaxed), normalised to a largest entry of 1, every free entry at least
    ``floor``."""
    bound = largest_ratio(x, y, free)
    if not bound > 0.0:
        return
    top = 0.0
    for n in range(x.shape[0]):
        if free[n]:
            x[n] *= (y[n] / (x[n] * bound)) ** relaxation
            top = max(top, x[n])
    for n in range(x.shape[0]):
        if free[n]:
            x[n] = max(x[n] / top, floor)


@njit(**JIT)
def elongations_within(dx, lo, hi):
    """True if every ``dx[e]`` (E,) [m] lies in ``[lo[e], hi[e]]``."""
    for e in range(dx.shape[0]):
        if not lo[e] <= dx[e] <= hi[e]:
            return False
    return True


@njit(**JIT)
def volume_strains_within(x, tets, rest_volumes, lo, hi):
    """True if every tet's volume strain ``V/V0 - 1`` at ``x`` (N, 3) [m] lies in ``[lo[t],
    hi[t]]`` (T,)."""
    for t in range(tets.shape[0]):
        if not lo[t] <= _tet_volume(x, tets, t) / rest_volumes[t] - 1.0 <= hi[t]:
            return False
    return True


class StrainBands:
    """Strain bands of half-width ``half_width`` [1] that follow the state, the tets' volume ratio
    ranges, and the stability bound ``omega2`` [1/s^2] of every state inside them (module
    docstring), centred at rest to start with.

    ``model``: the stability model (its masses the inertial ones of a mass-scaled run,
    :meth:`particle.integrator.VerletIntegrator.stability_model`). Arrays updated in place
    by :meth:`centre` (a run verifying them keeps seeing the current ones): ``lo``, ``hi``
    (E,) [1] the bands, ``elongation_lo``, ``elongation_hi`` (E,) [m] the same as
    elongations; with the volume term ``ratio_lo``, ``ratio_hi`` (T,) [1] the volume ratio
    ranges, ``volume_lo``, ``volume_hi`` (T,) [m^3] the same as volumes.
    """

    def __init__(self, model: Model, half_width: float) -> None:
        if not (math.isfinite(half_width) and 0.0 < half_width < 1.0):
            raise ParameterError(f"strain band half-width = {half_width} must be in (0, 1)")
        self.model, self.half_width = model, float(half_width)
        p = model.params
        n_edges, n = model.n_connectors, model.n_particles
        self.lo, self.hi = np.zeros(n_edges), np.zeros(n_edges)
        self._centre, self._moved = np.zeros(n_edges), np.zeros(n_edges, dtype=np.bool_)
        # the hull of every band so far, and the rest state's 0 (the arms' memory)
        self._history = (np.zeros(n_edges), np.zeros(n_edges))
        self._inner = (np.zeros(n_edges), np.zeros(n_edges))
        self.elongation_lo, self.elongation_hi = np.zeros(n_edges), np.zeros(n_edges)
        self._arms = np.ascontiguousarray(p.k1 + p.k2, dtype=np.float64)
        self.kappa = np.zeros(n_edges)
        self.free = ~model.fixed
        self._scale = np.where(self.free, 1.0 / np.sqrt(model.masses), 0.0)
        self.volume = p.kv is not None and model.n_tets > 0
        refuse_nodal(model, "the haptic strain envelope (particle.envelope)")
        # per matrix (springs, volume term): its Perron vector x (0 until the first bands are
        # set) and y = Q x, kept up to date as the bands move
        self._perron = [np.zeros(n) for _ in range(1 + self.volume)]
        self._product = [np.zeros(n) for _ in range(1 + self.volume)]
        if self.volume:
            t = model.n_tets
            self._moduli = tuple(np.ascontiguousarray(np.broadcast_to(v, (t,)), dtype=np.float64)
                                 for v in (p.volume_instantaneous, p.kv,
                                           (p.kv1 + p.kv2) if p.has_volume_arms else 0.0))
            self.ratio_lo, self.ratio_hi = np.ones(t), np.ones(t)
            self._ratio_centre = np.ones(t)
            self._ratio_history = (np.ones(t), np.ones(t))  # and the rest state's ratio 1
            self.volume_lo, self.volume_hi = np.zeros(t), np.zeros(t)
            self._inner_volume = (np.zeros(t), np.zeros(t))  # as volume strains V/V0 - 1
            self._gradients, self._curvatures = np.zeros((t, 4)), np.zeros((t, 6))
        # a writable copy: the compiled loops' signature of a state's positions, not of the
        # model's read-only ones (a second signature would compile at the first re-centring)
        self.centre(model.rest_positions.copy(), iterations=0, every=True)
        # Perron vectors of the first bands' matrices (Lanczos), refreshed at each centring
        for product, x, y in zip(self._products(), self._perron, self._product):
            x[:] = self._lanczos_perron(product)
            product(x, y)
        self.omega2 = self._bound(STARTING_ITERATIONS)

    def _products(self) -> list:
        """The matrices whose largest eigenvalues add up to the bound, as y = Q x products."""
        m = self.model
        out = [lambda x, y: laplacian_product(m.edges, self.kappa, self._scale, x, y)]
        if self.volume:
            out.append(lambda x, y: scalar_product(m.tets, self._gradients, self._curvatures,
                                                   self._scale, x, y))
        return out

    def _lanczos_perron(self, product) -> np.ndarray:
        """(N,) the nonnegative matrix ``product``'s Perron vector on the free particles (0 on
        fixed ones), largest entry 1, every free entry at least :data:`PERRON_FLOOR` (dense
        below :data:`~particle.stability.DENSE_EIGEN_LIMIT` free particles, else Lanczos)."""
        free = np.nonzero(self.free)[0]
        n = self.model.n_particles
        x, y = np.zeros(n), np.zeros(n)

        def matvec(v):
            x[free] = np.ravel(v)
            product(x, y)
            return y[free].copy()

        size = len(free)
        if size <= DENSE_EIGEN_LIMIT:
            vector = np.linalg.eigh(np.column_stack([matvec(column)
                                                     for column in np.eye(size)]))[1][:, -1]
        else:
            operator = LinearOperator((size, size), matvec=matvec, dtype=np.float64)
            try:
                vector = eigsh(operator, k=1, which="LA", tol=1e-8,
                               v0=np.random.default_rng(0).uniform(0.5, 1.5, size))[1][:, 0]
            except ArpackNoConvergence as exc:
                raise StabilityError(f"the strain bands' Perron vector (n = {size}) did not "
                                     f"converge: {exc}") from None
        vector = np.abs(vector)
        x[:] = 0.0
        x[free] = np.maximum(vector / vector.max(), PERRON_FLOOR)
        return x

    def _bound(self, iterations: int, enough=None) -> float:
        """:data:`~particle.stability.EIGENVALUE_MARGIN` x the sum of the matrices'
        Collatz-Wielandt bounds at their Perron vectors, the smallest over up to
        ``iterations`` rounds of one power iteration per matrix, stopping once
        ``enough(bound)`` (None: never)."""
        bounds = [largest_ratio(x, y, self.free) for x, y in zip(self._perron, self._product)]
        for _ in range(iterations):
            if enough is not None and enough(EIGENVALUE_MARGIN * sum(bounds)):
                break
            for k, (product, x, y) in enumerate(zip(self._products(), self._perron,
                                                    self._product)):
                power_step(x, y, self.free, PERRON_FLOOR, OVER_RELAXATION)
                product(x, y)
                bounds[k] = min(bounds[k], largest_ratio(x, y, self.free))
        return EIGENVALUE_MARGIN * sum(bounds)

    def centre(self, x: np.ndarray, iterations: int | None = None, every: bool = False,
               enough=None) -> None:
        """Centre on positions ``x`` (N, 3) [m] the bands of the connectors whose strains (and
        the volume ranges of the tets whose ratios) have left the inner half of their inner
        half, and of ``every`` one if asked, the tets' ranges on their connectors' bands, and
        refresh ``omega2``: the Collatz-Wielandt bounds at the current Perron vectors (their
        products updated for the bands that moved), tightened by up to ``iterations`` rounds
        of power iterations (None: :data:`POWER_ITERATIONS`) unless ``enough(omega2)`` is
        true (None: all rounds). Raises
        :class:`ParameterError` naming a connector whose spring stiffness is not > 0
        somewhere in its new band, :class:`StabilityError` naming a tet that is flat or
        inverted at ``x``."""
        m, w = self.model, self.half_width
        centre_connectors(x, m.edges, m.rest_lengths, w, self._centre, self.lo, self.hi,
                          *self._history, *self._inner, self.elongation_lo, self.elongation_hi,
                          self._moved, every)
        p = m.params
        soft = connector_weights(p.K0, p.a, p.b, self._arms, self.lo, self.hi,
                                 self._history[0], self._moved, self.kappa, m.edges,
                                 self._scale, self._perron[0], self._product[0])
        if soft >= 0:
            raise ParameterError(
                f"{connector_name(soft, m.edges)}: spring stiffness K(eps) = K0 + a eps + b "
                f"eps^2 reaches <= 0 in its strain band [{self.lo[soft]:g}, "
                f"{self.hi[soft]:g}]")
        if self.volume:
            flat = centre_tets(x, m.tets, m.tet_connectors, m.rest_volumes, m.rest_lengths, w,
                               self.lo, self.hi, self._moved, every, *self._moduli,
                               self._ratio_centre, self.ratio_lo, self.ratio_hi,
                               *self._ratio_history, self.volume_lo, self.volume_hi,
                               *self._inner_volume, self._gradients, self._curvatures,
                               self._scale, self._perron[1], self._product[1])
            if flat >= 0:
                raise StabilityError(f"{tet_name(flat, m.tets)} is flat or inverted: no volume "
                                     "ratio range to verify")
        self.omega2 = self._bound(POWER_ITERATIONS if iterations is None else iterations,
                                  enough)

    def holds(self, state) -> bool:
        """True while ``state``'s connectors (their elongations at the start of its last step,
        ``dx_prev``) and tets (their volumes then, ``volume_prev`` with the volume term's arms,
        else at its positions) stay in the inner halves of their bands and ranges."""
        if not elongations_within(state.dx_prev, *self._inner):
            return False
        if not self.volume:
            return True
        if state.volume_prev is not None:
            return elongations_within(state.volume_prev, *self._inner_volume)
        m = self.model
        return volume_strains_within(state.x, m.tets, m.rest_volumes, *self._inner_volume)
