"""Compiled (numba) passes of the nodal volume term (:mod:`particle.nodal_volume`).

:func:`add_nodal_volume_forces` is the explicit step's force pass, in three passes:

1. over the tets: each tet's volume (the per-tet pass's formula,
   :func:`particle.volume.tet_volume`, bit for bit, so the range check and the stored volumes
   are the per-tet term's), a quarter of it added to each of its particles' volume ``V_n``;
2. over the particles: the strain ``j_n = V_n / V0_n - 1`` and pressure ``P_n = kv_n j_n``,
   plus the arms' (:func:`particle.volume.volume_arm_step` with the particle as the volume
   element);
3. over the tets: the per-tet force ``-Pbar_t dV_t/dp_a`` with ``Pbar_t`` the pairwise mean of
   its particles' pressures (:func:`particle.nodal_volume.mean_tet_pressures`' order), with
   the per-tet pass's scalar operations.

Its arguments are the per-tet pass's (:func:`particle.volume.add_volume_forces`) with the
rest volumes and ``kv`` of the particles instead of the tets', and ``nodes`` = (volumes
(N,) [m^3], pressures (N,) [Pa]), scratch the passes fill. The plain-numpy twin is
:func:`particle.nodal_volume.nodal_volume_forces_numpy` (round-off equal).

:func:`nodal_node_volume_force` is the force on one particle (the haptic probe,
:meth:`particle.integrator.Run.force_on`): from its tets' particles' pressures, whose volumes
need those particles' tets, the particle's two-ring of tets (:func:`ring_tets`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from particle.volume import (JIT, _tet_gradient_tuples, add_tet_force, add_tet_tangent,
                             crosses_forces, tet_crosses, tet_volume, volume_arm_pressures,
                             volume_arm_step)


@njit(**JIT)
def _mean_pressure(tets, t, pressure):
    """``((P_0 + P_1) + (P_2 + P_3)) / 4`` [Pa] of tet t's particles' ``pressure`` (N,)."""
    return ((pressure[tets[t, 0]] + pressure[tets[t, 1]])
            + (pressure[tets[t, 2]] + pressure[tets[t, 3]])) * 0.25


@njit(**JIT)
def add_nodal_volume_forces(x, tets, node_volumes, kv, v_lo, v_hi, forces, arms, volumes,
                            nodes):
    """forces += the nodal volume forces [N]; returns (first bad tet, its volume [m^3]).

    ``tets`` (T, 4), ``node_volumes`` (N,) [m^3] the particles' rest volumes, ``kv`` (N,)
    [Pa] theirs, ``v_lo``/``v_hi`` (T,) [m^3] each tet's volume range (as the per-tet
    pass: a tet outside ``(v_lo, v_hi]`` is bad, (-1, 0.0) if none; it still gets its
    force), ``volumes`` (T,) receives every tet's volume, ``arms``: the particles' arms (the
    kernels' tuple of :mod:`particle.volume` with one row per particle) advanced and stored,
    or None; ``nodes`` = (volumes (N,), pressures (N,)) scratch (module docstring).

    Scalar loops (the per-tet pass's scalar operations, :func:`particle.volume.tet_crosses`,
    :func:`particle.volume.crosses_forces`). Measured and not kept: both passes over the tets
    as :data:`~particle.lanes.LANES`-wide lanes like the per-tet pass (a 12^3-cell Kuhn box,
    10,368 tets, 2,197 particles, 13,428 connectors, elastic: 194-201 us per explicit step
    with the springs against 194-195 us scalar; the per-tet term's step 151-163 us): the
    scatter of the particles' volumes and the gather of their pressures, not the arithmetic,
    are what the term adds.
    """
    node_volume, node_pressure = nodes
    node_volume[:] = 0.0
    bad = -1
    bad_volume = 0.0
    n_tets = tets.shape[0]
    for t in range(n_tets):
        v = tet_volume(x, tets, t)
        if bad < 0 and not (v > v_lo[t] and v <= v_hi[t]):
            bad = np.int64(t)
            bad_volume = v
        volumes[t] = v
        quarter = v * 0.25
        node_volume[tets[t, 0]] += quarter
        node_volume[tets[t, 1]] += quarter
        node_volume[tets[t, 2]] += quarter
        node_volume[tets[t, 3]] += quarter
    for m in range(node_volume.shape[0]):
        strain = node_volume[m] / node_volumes[m] - 1.0
        pressure = kv[m] * strain
        if arms is not None:
            pressure += volume_arm_step(m, strain, arms)
        node_pressure[m] = pressure
    sixth = 1.0 / 6.0
    for t in range(n_tets):
        _, g1, g2, g3 = tet_crosses(x, tets, t)
        add_tet_force(forces, tets, t, crosses_forces(
            g1, g2, g3, -_mean_pressure(tets, t, node_pressure) * sixth))
    return bad, bad_volume


@njit(**JIT)
def nodal_node_volume_force(x, node, ring, tets, node_volumes, kv, arms, node_volume, out):
    """out (3,) += the nodal volume force [N] on particle ``node``; ``ring``: its two-ring of
    tets (:func:`ring_tets`, ascending: each of its particles' volumes summed in the full
    pass's order), ``node_volume`` (N,) scratch (only its ring's entries are written),
    ``arms`` (or None) advanced one step into scratch (nothing stored)."""
    for k in range(ring.shape[0]):
        t = ring[k]
        for a in range(4):
            node_volume[tets[t, a]] = 0.0
    for k in range(ring.shape[0]):
        t = ring[k]
        quarter = tet_volume(x, tets, t) * 0.25
        for a in range(4):
            node_volume[tets[t, a]] += quarter
    for k in range(ring.shape[0]):
        t = ring[k]
        slot = -1
        for a in range(4):
            if tets[t, a] == node:
                slot = a
        if slot < 0:
            continue
        p = np.empty(4)
        for a in range(4):
            m = tets[t, a]
            strain = node_volume[m] / node_volumes[m] - 1.0
            p[a] = kv[m] * strain
            if arms is not None:
                p1, p2 = volume_arm_pressures(m, strain, arms)
                p[a] += p1 + p2
        _, g1, g2, g3 = tet_crosses(x, tets, t)
        f = crosses_forces(g1, g2, g3, -(((p[0] + p[1]) + (p[2] + p[3])) * 0.25) * (1.0 / 6.0))
        if slot == 0:
            out[0] -= f[9]
            out[1] -= f[10]
            out[2] -= f[11]
        else:
            out[0] += f[3 * slot - 3]
            out[1] += f[3 * slot - 2]
            out[2] += f[3 * slot - 1]


@njit(**JIT)
def add_nodal_volume_tangent(x, tets, node_volumes, kv, pattern, tet_slots, data, arms,
                             scratch):
    """data += the nodal term's tangent -d(forces)/dx [N/m] (:mod:`particle.nodal_volume`).

    ``x`` (N, 3) [m], ``tets`` (T, 4), ``node_volumes`` (N,) [m^3] and ``kv`` (N,) [Pa] the
    particles', ``pattern`` = (node_tet_ptr (N + 1,), node_tets (K,), node_tet_local (K, 4),
    star_ptr (N + 1,), block_ptr (N + 1,), block_slots (B, 3, 3)) (:class:`NodalPattern`),
    ``tet_slots`` (T, 4, 4, 3, 3) the tets' blocks (:func:`particle.volume.tet_slots`), ``arms``
    None (elastic, or the arms relaxed) or (the arms' step coefficients c_1 + c_2 (N,) [Pa],
    their summed pressures at ``x`` (N,) [Pa]), ``scratch`` = (volumes (N,), pressures (N,)).

    The curvature ``sum_t Pbar_t d^2V_t`` per tet (:func:`particle.volume.add_tet_tangent`
    with no rank-one part), then per particle n the rank-one ``k_n/V0_n b_n b_n^T``, ``b_n =
    sum_{t ∋ n} dV_t/dx / 4`` over its star (the particles of its tets), ``k_n = kv_n (+ c_1,n
    + c_2,n)``.
    """
    node_tet_ptr, node_tets, node_tet_local, star_ptr, block_ptr, block_slots = pattern
    node_volume, node_pressure = scratch
    node_volume[:] = 0.0
    for t in range(tets.shape[0]):
        quarter = tet_volume(x, tets, t) * 0.25
        for a in range(4):
            node_volume[tets[t, a]] += quarter
    for m in range(node_volume.shape[0]):
        pressure = kv[m] * (node_volume[m] / node_volumes[m] - 1.0)
        if arms is not None:
            pressure += arms[1][m]
        node_pressure[m] = pressure
    sixth = 1.0 / 6.0
    grads = np.empty((tets.shape[0], 4, 3))  # each tet's dV/dp_a, for the particles' b_n too
    for t in range(tets.shape[0]):
        g0, g1, g2, g3, _ = _tet_gradient_tuples(x, tets[t, 0], tets[t, 1], tets[t, 2],
                                                 tets[t, 3])
        for a, g in ((0, g0), (1, g1), (2, g2), (3, g3)):
            grads[t, a, 0], grads[t, a, 1], grads[t, a, 2] = g[0], g[1], g[2]
        add_tet_tangent(x, tets, t, 0.0, _mean_pressure(tets, t, node_pressure) * sixth,
                        (g0, g1, g2, g3), tet_slots, data)
    for n in range(node_volume.shape[0]):
        size = star_ptr[n + 1] - star_ptr[n]
        b = np.zeros((size, 3))
        for k in range(node_tet_ptr[n], node_tet_ptr[n + 1]):
            t = node_tets[k]
            for a in range(4):
                row = node_tet_local[k, a]
                b[row, 0] += 0.25 * grads[t, a, 0]
                b[row, 1] += 0.25 * grads[t, a, 1]
                b[row, 2] += 0.25 * grads[t, a, 2]
        stiffness = kv[n] if arms is None else kv[n] + arms[0][n]
        w = stiffness / node_volumes[n]
        base = block_ptr[n]
        for i in range(size):
            for j in range(size):
                slots = block_slots[base + i * size + j]
                for p in range(3):
                    for q in range(3):
                        s = slots[p, q]
                        if s >= 0:
                            data[s] += w * b[i, p] * b[j, q]


def ring_tets(tets: np.ndarray, node: int) -> np.ndarray:
    """(k,) int64 ascending: the tets touching any particle of particle ``node``'s tets (what
    :func:`nodal_node_volume_force` needs)."""
    own = np.any(tets == node, axis=1)
    ring = np.unique(tets[own])
    return np.nonzero(np.isin(tets, ring).any(axis=1))[0].astype(np.int64)


__all__ = ["add_nodal_volume_forces", "add_nodal_volume_tangent", "nodal_node_volume_force",
           "ring_tets"]
