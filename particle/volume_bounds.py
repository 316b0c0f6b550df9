"""Stability bounds of the per-tet volume term (:mod:`particle.volume`) for the explicit step.

The stable step :func:`particle.stability.critical_time_step` takes the smaller of two
bounds: an upper bound of the term's largest mass-scaled eigenvalue (the smallest of
:func:`volume_frequency_bound` and the largest eigenvalue of
:func:`volume_scalar_matrix`) added to the springs' eigenvalue bound, and one eigenvalue of
the springs' Laplacian with :func:`volume_edge_stiffness_bound` added to its weights; mass
scaling
(:func:`particle.mass_scaling.stiffness_weights`) steers its added mass with
:func:`node_volume_stiffness_bound`. All three hold for every state whose connector strains
lie in a range and whose tets' volume ratios lie in :func:`volume_ratio_range` of it, or in
a range of each tet's own that a run is given instead (:func:`verified_ratio_range`), which
the explicit runs verify at every step. Kept apart from the force kernels: numpy only, used
when a run is prepared, never inside the loop. The same bounds hold for the nodal term
(:mod:`particle.nodal_volume`) with each tet's modulus and pressure bound taken from its
particles' (:func:`particle.nodal_volume.tet_moduli`, :func:`_nodal_pressure_bound`).

With the volume term's Maxwell arms (:mod:`particle.volume`) a tet's tangent is
``k/V0 g g^T + P d^2V`` with the instantaneous stiffness ``k = kv + c_1 + c_2 <= kv + kv1 +
kv2`` (an arm's step coefficient ``c_i = kv_i bv_i/(kv_i dt + bv_i)`` is at most
``kv_i``) and the pressure ``P = kv j + P_1 + P_2``. An arm's pressure is ``kv_i`` times
the volume strain minus a weighted mean of its past values (the Maxwell convolution, as
the connectors' arms in :func:`particle.stability.connector_stiffness_bound`), so
``|P_i| <= kv_i (J_hi - J_lo)`` while the volume ratios stay in ``[J_lo, J_hi]``; every
bound below takes ``k`` and that bound of ``|P|`` (:func:`_tet_bounds`), which are ``kv``
and ``kv |J - 1|_max`` for the elastic term.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from forcecal.errors import ParameterError


def volume_ratio_range(model, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) (J_lo, J_hi): the volume ratios V/V0 a run whose connector strains stay in
    ``[lo, hi]`` (E,) is verified for: ``((1 + min lo)^3, (1 + max hi)^3)`` over each
    tet's edges, the ratios of a uniform compression/dilation by those strains.

    Edge lengths alone do not bound V/V0 usefully (a flat tet gains volume fast), so
    the range is an assumption the explicit runs verify at every step, as they verify
    the strains (:class:`particle.integrator.Run`).
    """
    conn = model.tet_connectors
    return (1.0 + lo[conn].min(axis=1)) ** 3, (1.0 + hi[conn].max(axis=1)) ** 3


def verified_ratio_range(model, lo: np.ndarray, hi: np.ndarray, volume_range=None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(T,) (J_lo, J_hi): the volume ratios V/V0 [1] a run whose connector strains stay in
    ``[lo, hi]`` (E,) is verified for: ``volume_range`` (J_lo (T,), J_hi (T,)) when given (a
    range of each tet's own, e.g. :func:`particle.stability.release_volume_range`), else
    :func:`volume_ratio_range` of the strains. Every bound here holds on it and the runs
    check it; a given range must be finite with ``0 <= J_lo <= 1 <= J_hi`` (the runs stop
    at ``V <= J_lo V0``, and the arms' pressures average over the past volume strains, the
    rest state's among them), else :class:`~forcecal.errors.ParameterError` naming the tet.
    """
    if volume_range is None:
        return volume_ratio_range(model, lo, hi)
    from particle.volume import tet_name
    if len(volume_range) != 2:
        raise ParameterError(f"a volume ratio range is a (lo, hi) pair, got {volume_range!r}")
    j_lo, j_hi = (np.asarray(b, dtype=np.float64) for b in volume_range)
    if j_lo.shape != (model.n_tets,) or j_hi.shape != (model.n_tets,):
        raise ParameterError(f"volume ratio range bounds of shapes {j_lo.shape}, {j_hi.shape}: "
                             f"expected one per tet ({model.n_tets},)")
    bad = np.nonzero(~(np.isfinite(j_lo) & np.isfinite(j_hi) & (j_lo >= 0.0) & (j_lo <= 1.0)
                       & (j_hi >= 1.0)))[0]
    if len(bad):
        t = int(bad[0])
        raise ParameterError(f"{tet_name(t, model.tets)}: volume ratio range [{j_lo[t]:g}, "
                             f"{j_hi[t]:g}] must be finite with 0 <= lo <= 1 <= hi")
    return j_lo, j_hi


def _max_triangle_area(a: tuple, b: tuple, c: tuple) -> np.ndarray:
    """Upper bound [m^2] of a triangle's area whose side lengths lie in ``(lo, hi)`` pairs.

    Heron: ``16 A^2 = (a + b + c)(-a + b + c)(a - b + c)(a + b - c)``; each factor is
    bounded by its own maximum over the box (and the area by ``a b/2``).
    """
    (a0, a1), (b0, b1), (c0, c1) = a, b, c
    heron = ((a1 + b1 + c1) * np.maximum(-a0 + b1 + c1, 0.0) * np.maximum(a1 - b0 + c1, 0.0)
             * np.maximum(a1 + b1 - c0, 0.0))
    return np.minimum(0.25 * np.sqrt(heron), 0.5 * np.minimum(np.minimum(a1 * b1, b1 * c1),
                                                              a1 * c1))


def _tet_bounds(model, lo: np.ndarray, hi: np.ndarray, history=None, volume_range=None):
    """Per-tet quantities of the volume term's frequency bounds over the strain box ``[lo, hi]``:
    (face gradient bounds G (T, 4) [m^2] >= |dV/dp_a| (the face opposite a over 3, Heron),
    longest lengths lmax (T, 6) [m] of the edges (:data:`TET_PAIRS` order), the largest
    instantaneous stiffness k (T,) [Pa] and the largest ``|P|`` (T,) [Pa] (module
    docstring; ``|V/V0 - 1|`` on :func:`verified_ratio_range` of ``volume_range``), free
    vertices (T, 4) bool). ``history`` (lo (E,), hi (E,)): the strain hull the run's past
    states stayed in (:func:`particle.stability.strain_history`, None: ``[lo, hi]``): an
    arm's pressure is ``c_i (j - m)``, ``m`` a convex combination of the past volume strains
    (as the connectors' arms, :func:`particle.stability.connector_stiffness_bound`), so
    ``|P_i| <= kv_i max(J_hi - Jh_lo, Jh_hi - J_lo)`` with ``Jh`` the history's volume ratio
    range, widened to hold the verified one.

    The pressure bound is the only part a volume ratio range enters: the face and edge
    bounds follow from the edge lengths alone (Heron), so a range reaching down towards 0
    (a tet squeezed flat) adds at most ``kv`` to the elastic pressure bound (``|J - 1| <=
    1`` below rest) and ``kv_i`` to each arm's."""
    conn = model.tet_connectors  # (T, 6) in TET_PAIRS order: 01 02 03 12 13 23
    L0 = model.rest_lengths[conn]
    lmin, lmax = (1.0 + lo[conn]) * L0, (1.0 + hi[conn]) * L0
    side = [(lmin[:, k], lmax[:, k]) for k in range(6)]
    # the face opposite vertex a: 0 -> (12, 13, 23), 1 -> (02, 03, 23), 2 -> (01, 03, 13),
    # 3 -> (01, 02, 12)
    faces = ((3, 4, 5), (1, 2, 5), (0, 2, 4), (0, 1, 3))
    grad = np.column_stack([_max_triangle_area(*(side[k] for k in f)) / 3.0 for f in faces])
    from particle.nodal_volume import tet_moduli
    j_lo, j_hi = verified_ratio_range(model, lo, hi, volume_range)
    h_lo, h_hi = j_lo, j_hi
    if history is not None:
        h_lo, h_hi = volume_ratio_range(model, *history)
        h_lo, h_hi = np.minimum(h_lo, j_lo), np.maximum(h_hi, j_hi)
    if model.volume_element == "nodal":
        pressure = _nodal_pressure_bound(model, j_lo, j_hi, h_lo, h_hi)
    else:
        p = model.params
        pressure = p.kv * np.maximum(1.0 - j_lo, j_hi - 1.0)
        if p.has_volume_arms:
            pressure = pressure + (p.kv1 + p.kv2) * np.maximum(j_hi - h_lo, h_hi - j_lo)
    return grad, lmax, tet_moduli(model), pressure, ~model.fixed[model.tets]


def _nodal_pressure_bound(model, j_lo, j_hi, h_lo, h_hi):
    """(T,) the per-tet pressure bound that, with the modulus of
    :func:`particle.nodal_volume.tet_moduli`, makes the per-tet bounds hold for the nodal term
    (:mod:`particle.nodal_volume`), over the tets' volume ratios ``[j_lo, j_hi]`` (T,) and
    their history's ``[h_lo, h_hi]`` (T,).

    Its tangent is ``sum_n k_n/V0_n (b_n . v)^2 + sum_t Pbar_t v^T d^2V_t v`` with ``b_n . v
    = sum_{t ∋ n} g_t . v_t / 4`` and ``V0_n = sum_{t ∋ n} V0_t / 4``. Cauchy-Schwarz with
    the weights ``V0_t / 4``: ``(sum_{t ∋ n} g_t . v_t / 4)^2 <= V0_n sum_{t ∋ n} (g_t .
    v_t)^2 / (4 V0_t)``, so the rank-one part is at most ``sum_t kbar_t / V0_t (g_t . v)^2``
    with ``kbar_t`` the mean of the tet's particles' instantaneous ``k_n``: in the Loewner
    order the nodal tangent is below a per-tet tangent with modulus ``kbar_t`` and pressure
    ``Pbar_t``, a mean of four ``P_n``. A particle's volume ratio ``V_n / V0_n = sum_{t ∋ n}
    (V0_t / 4 / V0_n) V_t / V0_t`` is a convex combination of its tets', so it lies in
    ``[min j_lo, max j_hi]`` over them (the history's likewise), and ``|P_n| <= kv_n |J_n -
    1|_max + (kv1_n + kv2_n) max(J_hi - Jh_lo, Jh_hi - J_lo)`` (the per-tet argument,
    :func:`_tet_bounds`); ``|Pbar_t|`` is at most the largest of its four."""
    from particle.nodal_volume import nodal_params
    tets, n = model.tets, model.n_particles
    nodal = nodal_params(model)

    def node_range(lo_t, hi_t):
        lo_n, hi_n = np.full(n, np.inf), np.full(n, -np.inf)
        np.minimum.at(lo_n, tets.ravel(), np.repeat(lo_t, 4))
        np.maximum.at(hi_n, tets.ravel(), np.repeat(hi_t, 4))
        return lo_n, hi_n

    jn_lo, jn_hi = node_range(j_lo, j_hi)
    hn_lo, hn_hi = node_range(h_lo, h_hi)
    pressure = nodal.kv * np.maximum(1.0 - jn_lo, jn_hi - 1.0)
    if nodal.arm_stiffness is not None:
        pressure = pressure + nodal.arm_stiffness.sum(axis=1) * np.maximum(jn_hi - hn_lo,
                                                                           hn_hi - jn_lo)
    return pressure[tets].max(axis=1)


def _irons_bound(model, grad, lmax, modulus, pressure, free) -> float:
    """Irons' element bound [1/s^2]: the largest tet eigenvalue against its share of the
    particles' masses (see :func:`volume_frequency_bound`)."""
    tets, v0 = model.tets, model.rest_volumes
    volume_sum = np.bincount(tets.ravel(), np.repeat(v0, 4), model.n_particles)
    share = model.masses[tets] * v0[:, None] / volume_sum[tets]  # (T, 4) [kg]
    rank_one = modulus / v0 * np.sum(np.where(free, grad ** 2 / share, 0.0), axis=1)
    row = np.maximum(np.maximum(lmax[:, 1] + lmax[:, 2], lmax[:, 0] + lmax[:, 2]),
                     lmax[:, 0] + lmax[:, 1]) / 6.0
    lightest = np.min(np.where(free, share, np.inf), axis=1)
    curvature = pressure * 4.0 * row / lightest
    return float(np.max(np.where(free.any(axis=1), rank_one + curvature, 0.0)))


# the edge joining the two vertices other than a and b (TET_PAIRS index), per pair (a, b)
OPPOSITE_EDGE = np.array([[-1, 5, 4, 3], [5, -1, 2, 1], [4, 2, -1, 0], [3, 1, 0, -1]])


def node_volume_stiffness_bound(model, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) ``D_n`` [N/m] with ``K_vol <= diag(D) (x) I_3`` on the free particles (0 on fixed ones)
    for every state whose connector strains lie in ``[lo, hi]`` (E,) and volume ratios in
    :func:`volume_ratio_range`.

    Per tet, ``v^T H_t v = kv/V0 (g . v)^2 + kv (J - 1) v^T d^2V v`` over the free vertices:

    * Cauchy-Schwarz with weights ``G_a`` (the bound of ``|g_a|``): ``(sum g_a . v_a)^2 <=
      (sum_b G_b)(sum_a G_a |v_a|^2)``, so ``kv/V0 (sum_b G_b) G_a`` on vertex a;
    * the blocks ``d^2V/dp_a dp_b = +-[s]_x/6`` (s the edge joining the other two vertices)
      have norm ``|s|/6``, and ``|v_a^T A v_b| <= |A| (|v_a|^2 + |v_b|^2)/2`` puts
      ``kv |J - 1|_max sum_b lmax(s_ab)/6`` on vertex a.

    Summed over each particle's tets. ``max_n D_n/m_n`` bounds the term's largest
    mass-scaled eigenvalue; the same ``D`` steers mass scaling's added mass
    (:func:`particle.mass_scaling.stiffness_weights`).
    """
    return _nodal(model, *_tet_bounds(model, lo, hi))


def _nodal(model, grad, lmax, modulus, pressure, free) -> np.ndarray:
    v0 = model.rest_volumes
    g = np.where(free, grad, 0.0)
    rank_one = (modulus / v0 * g.sum(axis=1))[:, None] * g
    curvature = np.zeros_like(g)
    for a in range(4):
        for b in range(4):
            if a != b:
                curvature[:, a] += np.where(free[:, b], lmax[:, OPPOSITE_EDGE[a, b]], 0.0)
    curvature *= (pressure / 6.0)[:, None]
    return np.bincount(model.tets.ravel(), np.where(free, rank_one + curvature, 0.0).ravel(),
                       model.n_particles)


def volume_edge_stiffness_bound(model, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(E,) ``w_e`` [N/m] with ``K_vol <= L_w (x) I_3`` in the Loewner order (``L_w`` the graph
    Laplacian with connector weights ``w``) for every state whose connector strains lie in
    ``[lo, hi]`` (E,) and volume ratios in :func:`volume_ratio_range`: the volume term's
    share of the springs' bound (:func:`particle.stability.critical_time_step` adds it to
    the connectors' ``kappa`` and takes one eigenvalue of the sum).

    Both parts of a tet's tangent ``H_t = kv/V0 g g^T + kv (J - 1) d^2V`` vanish on rigid
    translations (``sum_a g_a = 0``, and so ``sum_b d^2V/dp_a dp_b = 0``), so they see only
    ``w_a = v_a - mean(v)``, and ``sum_a |w_a|^2 = (1/4) sum_{a<b} |v_a - v_b|^2``
    (fixed particles: ``v = 0``, as the Laplacian's kept diagonal terms):

    * ``(g . v)^2 = (g . w)^2 <= |g|^2 |w|^2`` with ``|g|^2 <= sum_a G_a^2`` (Heron, as
      :func:`node_volume_stiffness_bound`);
    * ``|w^T d^2V w| <= |d^2V| |w|^2``, the spectral norm at most the largest row sum of the
      block norms ``|s_ab|/6``, ``max_a sum_b lmax(s_ab)/6``;

    so each of the tet's six edges gets ``(kv/V0 sum_a G_a^2 + kv |J - 1|_max |d^2V|)/4``.
    Exact for the rank-one part of a regular tet at rest (``L_w`` of its four particles has
    the eigenvalue ``4 w = kv/V0 |g|^2``), and, assembled, tighter than the per-particle
    bound where the mesh is fine: kv 8.9 kPa on strains +-0.5, 12k-connector liver 5.5e7
    against 7.5e7 1/s^2 for the term alone.
    """
    return _edge_weights(model, *_tet_bounds(model, lo, hi)[:4])


def _edge_weights(model, grad, lmax, modulus, pressure) -> np.ndarray:
    v0 = model.rest_volumes
    curvature_norm = np.max([sum(lmax[:, OPPOSITE_EDGE[a, b]] for b in range(4) if b != a)
                             for a in range(4)], axis=0) / 6.0
    per_edge = (modulus / v0 * np.sum(grad ** 2, axis=1) + pressure * curvature_norm) / 4.0
    return np.bincount(model.tet_connectors.ravel(), np.repeat(per_edge, 6), model.n_connectors)


def volume_frequency_bound(model, lo: np.ndarray, hi: np.ndarray) -> float:
    """omega^2 bound [1/s^2] of the volume term: >= lambda_max(M^{-1/2} K_vol M^{-1/2}).

    The smaller of two rigorous bounds, each valid for every state whose connector
    strains lie in ``[lo, hi]`` (E,) and whose volume ratios lie in
    :func:`volume_ratio_range` (which the runs verify). 0 without free particles.

    Irons' element bound: with each particle's (lumped) mass shared among its
    tets in proportion to their volumes, ``M = sum_t B_t^T M_t B_t``, and the tet
    tangents ``H_t <= lambda_t M_t`` give ``K_vol <= max_t lambda_t M``. On the free
    particles of tet t, ``H_t = kv/V0 g g^T + kv (J - 1) d^2V``:

    * the rank-one part has ``lambda = kv/V0 sum_a |g_a|^2/m_a`` (free a), with
      ``|g_a|`` = area of the face opposite a over 3, bounded from its side lengths
      ``(1 + lo) L0 .. (1 + hi) L0`` by Heron's formula (:func:`_max_triangle_area`);
    * ``d^2V`` in the edge coordinates ``e_k = p_k - p_0`` has the blocks
      ``+-[e_m]_x/6``, spectral norm at most the largest row sum of the block norms,
      ``max (l_i + l_j)/6``, and the map from vertex coordinates has ``|G|^2 = 4``:
      ``lambda <= kv |J - 1|_max 4 max(l_i + l_j)/6 / min_a m_a``, ``|J - 1| <=
      max(1 - J_lo, J_hi - 1)``.

    The nodal bound ``max_n D_n/m_n`` (:func:`node_volume_stiffness_bound`): a
    particle's tets are summed rather than the worst tet taken, so one sliver
    tet with a small mass share does not set the bound for the whole mesh.
    Measured at kv 8.9 kPa on strains +-0.5: 12k-connector liver, Irons 2.6e8,
    nodal 7.5e7 1/s^2 (the true eigenvalue at rest is 3.0e6); 1400-connector
    liver 3.8e7 vs 1.2e7. On a regular (Kuhn) box at kv 20 kPa: 4.9e7 vs 3.2e7
    on +-0.5, but at rest (strains +-0) Irons is the smaller (3.9e6 vs 4.5e6).
    """
    return _frequency_bound(model, _tet_bounds(model, lo, hi))


def _frequency_bound(model, bounds) -> float:
    if not (~model.fixed[model.tets]).any():
        return 0.0
    free = ~model.fixed
    nodal = float(np.max(_nodal(model, *bounds)[free] / model.masses[free]))
    return min(_irons_bound(model, *bounds), nodal)


def volume_scalar_matrix(model, lo: np.ndarray, hi: np.ndarray) -> sp.csr_matrix:
    """(Nf, Nf) ``M^{-1/2} S M^{-1/2}`` [1/s^2] on the free particles, a symmetric nonnegative
    matrix whose largest eigenvalue bounds the volume term's largest mass-scaled eigenvalue
    for every state whose connector strains lie in ``[lo, hi]`` (E,) and volume ratios in
    :func:`volume_ratio_range`.

    ``S = sum_t S_t`` with, on the free vertices a, b of tet t (:func:`_tet_bounds`'
    ``G_a`` >= |dV/dp_a|, ``k`` the instantaneous stiffness, ``|P|`` the pressure bound,
    ``lmax(s_ab)`` the longest length of the edge joining the other two vertices)::

        S_t[a, b] = k/V0 G_a G_b + (a != b) |P| lmax(s_ab)/6.

    Proof: a tet's ``v^T H_t v = k/V0 (sum_a g_a . v_a)^2 + P sum_{a != b} v_a^T
    d^2V/dp_a dp_b v_b`` with ``|sum_a g_a . v_a| <= sum_a G_a |v_a|`` and ``|v_a^T
    d^2V/dp_a dp_b v_b| <= lmax(s_ab)/6 |v_a| |v_b|`` (the block is ``+-[s_ab]_x/6``), so
    ``v^T K_vol v <= u^T S u`` with ``u_a = |v_a|`` (``|u| = |v|``); with ``v =
    M^{-1/2} z``, ``z^T M^{-1/2} K_vol M^{-1/2} z <= |z|^T M^{-1/2} S M^{-1/2} |z|``,
    at most the largest eigenvalue of this matrix times ``|z|^2``.

    The same per-particle sums as :func:`node_volume_stiffness_bound`: ``D_n`` is the row
    sum of ``S``, so ``max_n D_n/m_n`` (the largest row sum of the similar ``M^{-1} S``) is
    a Gershgorin bound of this matrix's largest eigenvalue, which is never above it and
    where the mesh is fine well below: kv 8.9 kPa on strains +-0.5, 12k-connector liver 3.9e7
    against 7.5e7 1/s^2 (the edge bound 5.5e7, the true eigenvalue at rest 3.0e6).
    """
    return _scalar_matrix(model, _tet_bounds(model, lo, hi))


def _scalar_entries(model, grad, lmax, modulus, pressure, free) -> np.ndarray:
    """(T, 4, 4) the tets' ``S_t[a, b]`` [N/m] of :func:`volume_scalar_matrix` (0 on fixed
    vertices)."""
    g = np.where(free, grad, 0.0)
    entries = (modulus / model.rest_volumes)[:, None, None] * g[:, :, None] * g[:, None, :]
    for a in range(4):
        for b in range(4):
            if a != b:
                entries[:, a, b] += pressure / 6.0 * np.where(
                    free[:, a] & free[:, b], lmax[:, OPPOSITE_EDGE[a, b]], 0.0)
    return entries


def _scalar_matrix(model, bounds) -> sp.csr_matrix:
    entries = _scalar_entries(model, *bounds)
    tets = model.tets
    n_tets = len(tets)  # entry (t, a, b) -> (tets[t, a], tets[t, b]), listed by a, b, then t
    rows = np.broadcast_to(tets.T[:, None, :], (4, 4, n_tets)).ravel()
    cols = np.broadcast_to(tets.T[None, :, :], (4, 4, n_tets)).ravel()
    vals = entries.transpose(1, 2, 0).ravel()
    index = np.full(model.n_particles, -1, dtype=np.int64)
    movable = ~model.fixed
    index[movable] = np.arange(int(movable.sum()))
    keep = (index[rows] >= 0) & (index[cols] >= 0)
    scale = 1.0 / np.sqrt(model.masses)
    n = int(movable.sum())
    return sp.csr_matrix((vals[keep] * scale[rows[keep]] * scale[cols[keep]],
                          (index[rows[keep]], index[cols[keep]])), shape=(n, n))


def volume_tet_energies(model, lo: np.ndarray, hi: np.ndarray, mode: np.ndarray) -> np.ndarray:
    """(T,) each tet's part ``x_t^T S_t x_t`` [1/s^2] of the Rayleigh quotient of
    :func:`volume_scalar_matrix` at ``mode`` (Nf,) (free particles, mass-scaled; ``x =
    M^{-1/2} mode``, 0 on fixed particles): they sum to ``mode^T (M^{-1/2} S M^{-1/2})
    mode``, so at its top eigenvector each tet's term over the sum is its share of the
    bound."""
    free = ~model.fixed
    x = np.zeros(model.n_particles)
    x[free] = np.asarray(mode, dtype=np.float64) / np.sqrt(model.masses[free])
    xt = x[model.tets]
    return np.einsum("ta,tab,tb->t", xt, _scalar_entries(model, *_tet_bounds(model, lo, hi)), xt)


def volume_step_bounds(model, lo: np.ndarray, hi: np.ndarray, history=None, volume_range=None
                       ) -> tuple[float, np.ndarray, sp.csr_matrix]:
    """(:func:`volume_frequency_bound`, :func:`volume_edge_stiffness_bound`,
    :func:`volume_scalar_matrix`) of one strain range, the per-tet bounds they share computed
    once (the stable step takes all three); ``history``, ``volume_range`` (the tets' verified
    volume ratios, None: :func:`volume_ratio_range` of the strains): :func:`_tet_bounds`'."""
    bounds = _tet_bounds(model, lo, hi, history, volume_range)
    return (_frequency_bound(model, bounds), _edge_weights(model, *bounds[:4]),
            _scalar_matrix(model, bounds))
