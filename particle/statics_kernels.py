"""Compiled (numba) Newton iteration of :meth:`particle.statics.EquilibriumSolver.solve`.

On a calibration's small meshes an iteration's arithmetic (a force evaluation, a solve
with the kept ``L D L^T``) takes a few microseconds, and calling it from Python, a
dozen small calls and allocations per iteration, took ten times that. Here the
iteration runs in one compiled loop, :func:`newton_iterations`: the forces (connectors,
the volume term, gravity), the convergence test, the modified-Newton step with the
kept factorisation, the trial point, the line search on a fresh factorisation's step and
the refactorise-when-not-contracting rule, and the factorisations (:func:`factorise`:
the tangent assembled as :func:`particle.statics.tangent_data` does, the constraints
applied, :func:`particle.sparse_ldl._numeric`). It returns to Python only where a
factorisation meets a zero pivot (the singular-shift fallback and its logging in
:func:`particle.statics.factorize`) and resumes after it.

Every operation is the one the Python loop did, in the same order, on arrays of the
same types: the same compiled kernels (:func:`particle.kernels.internal_forces`,
:func:`particle.volume.add_volume_forces`, :func:`particle.sparse_ldl._solve_restricted`,
the tangent's and the factorisation's), gravity added as ``forces += m g`` did, the norms
as ``np.dot`` (BLAS ``ddot``, which numpy's ``res @ res`` called), the arms' summed
coefficients and pressures as numpy's ``sum(axis=1)`` (:func:`row_sums`): the equilibria
and the kept factorisations are bitwise those of the loop it replaced
(``tests/test_particle_statics.py`` keeps that loop as its reference).

Cold compilation: the loop is one more specialisation that links the kernels it calls
(compiled for the Python paths anyway) into its own machine code, some 3-6 s of CPU in a
process with an empty cache; a process with the cache loads it in milliseconds.

An iterate lives in one of two buffer sets (index 0 or 1 of each array of ``buffers``):
the current one and the trial. ``buffers`` = ``(x (2, N, 3), forces (2, N, 3), tension
(2, E), arm forces (2, E, 2), elongations (2, E), volume arm pressures (2, T, 2), volume
strains (2, T), residuals (2, k))``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from particle.kernels import JIT, assemble_tangent, internal_forces
from particle.sparse_ldl import _numeric, _solve_restricted
from particle.nodal_kernels import add_nodal_volume_forces, add_nodal_volume_tangent
from particle.volume import add_volume_forces, add_volume_tangent

#: what :func:`newton_iterations` returns for: a converged iterate, a tangent to factorise
#: in Python at the current iterate (then call again with ``resume``), no convergence
CONVERGED, FACTORISE, FAILED = 0, 1, 2


@njit(**JIT)
def evaluate(k, buffers, springs, volume, loads, flat, nodal):
    """Forces of iterate ``k`` at its positions ``buffers[0][k]`` into its buffers (as
    :func:`particle.statics.net_forces`: connectors, the volume term unless ``volume[0]``
    is False, its arms stepped if ``volume[1]``, an inverted tet -> infinite forces, then
    gravity if ``loads[0]``), its residual (the components ``flat``); returns its norm.

    ``springs`` = ``(edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev)``
    (:func:`particle.statics.kernel_terms`), ``volume`` = ``(on, arms on, tets,
    rest_volumes, kv, v_lo, v_hi, r, c, pressure_prev, strain_prev, force_tets, volumes)``
    (the tets twice: as the tangent takes them, and as an unsigned index view with a
    scratch for their volumes, the explicit runs' typing of the force pass, so that the
    two share its compiled code: another typing costs ~4 s of compilation), ``loads`` =
    ``(on, masses (N,), gravity (3,))``; ``nodal`` = ``(on, pattern, scratch)``: with ``on``
    the volume term is nodal (its rest volumes and kv the particles', its arms one row per
    particle; :func:`particle.nodal_kernels.add_nodal_volume_forces` with the scratch).
    """
    xs, forces, tension, arm_out, dx, vol_p, vol_s, res = buffers
    edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev = springs
    x, f = xs[k], forces[k]
    arm_out[k][:] = 0.0
    internal_forces(x, edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev, f,
                    tension[k], arm_out[k], dx[k])
    on, arms_on, _, rest_volumes, kv, v_lo, v_hi, r, c, p_prev, s_prev, tets, volumes = volume
    if on:
        if nodal[0]:
            if arms_on:
                vol_p[k][:] = 0.0
                bad, _ = add_nodal_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, f,
                                                 (r, c, p_prev, s_prev, vol_p[k], vol_s[k]),
                                                 volumes, nodal[2])
            else:
                bad, _ = add_nodal_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, f,
                                                 None, volumes, nodal[2])
        elif arms_on:
            vol_p[k][:] = 0.0
            bad, _ = add_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, f,
                                       (r, c, p_prev, s_prev, vol_p[k], vol_s[k]), volumes)
        else:
            bad, _ = add_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, f, None, volumes)
        if bad >= 0:
            f[:] = np.inf
    gravity_on, masses, g = loads
    if gravity_on:
        for i in range(f.shape[0]):
            for q in range(3):
                f[i, q] += masses[i] * g[q]
    out = res[k]
    flat_f = f.reshape(-1)
    for t in range(len(flat)):
        out[t] = flat_f[flat[t]]
    return math.sqrt(np.dot(out, out)) if len(out) else 0.0


@njit(**JIT)
def converged(forces, held_flat, held, norm, rtol, floor):
    """Whether the iterate with ``forces`` (N, 3) and residual norm ``norm`` [N] has converged:
    the residual within ``rtol`` x the force scale, the constraint reaction (its components
    ``held_flat``; ``held`` (h,) scratch) but at least ``floor`` [N]."""
    flat_f = forces.reshape(-1)
    for t in range(len(held_flat)):
        held[t] = flat_f[held_flat[t]]
    reaction = math.sqrt(np.dot(held, held)) if len(held) else 0.0
    scale = reaction if reaction > floor else floor  # max(floor, reaction), floor on a tie/NaN
    # an inadmissible iterate (an inverted tet: infinite forces) has an infinite scale,
    # and inf <= rtol x inf must not pass for convergence
    return norm <= rtol * scale and math.isfinite(scale)


@njit(**JIT)
def moved(trial, cur, step, buffers, springs, volume, loads, flat, nodal):
    """Iterate ``trial`` at iterate ``cur``'s positions plus ``step`` on the components
    ``flat`` (:func:`particle.statics.displaced`), evaluated; returns its residual norm."""
    xs = buffers[0]
    xs[trial][:] = xs[cur]
    out = xs[trial].reshape(-1)
    for t in range(len(flat)):
        out[flat[t]] += step[t]
    return evaluate(trial, buffers, springs, volume, loads, flat, nodal)


@njit(**JIT)
def row_sums(v):
    """(M,) ``v.sum(axis=1)`` of ``v`` (M, 2) as numpy sums: ``(0.0 + v[:, 0]) + v[:, 1]``."""
    out = np.empty(v.shape[0])
    for m in range(v.shape[0]):
        out[m] = (0.0 + v[m, 0]) + v[m, 1]
    return out


@njit(**JIT)
def factorise(cur, buffers, springs, volume, tangent, symbolic, nodal):
    """``(first bad pivot or -1, L, D)``: the ``L D L^T`` factorisation
    (:func:`particle.sparse_ldl._numeric`) of the tangent at iterate ``cur`` with the
    constraints applied, as :meth:`particle.statics.EquilibriumSolver._factorize` builds it
    (:func:`particle.statics.tangent_data`).

    ``tangent`` = ``(nnz, slots, tet_slots, zero_slots, diag_slots)`` (the pattern's entries
    and the data indices of its blocks and of the constraints), ``symbolic`` the pattern's
    :class:`particle.sparse_ldl.Symbolic` arrays ``(sup_ptr, row_ptr, rows, x_ptr, upd_ptr,
    upd_sup, upd_q1, upd_q2, a_src, a_dst, perm)``, ``nodal`` :func:`evaluate`'s (the nodal
    term's tangent, :func:`particle.nodal_kernels.add_nodal_volume_tangent`).
    """
    xs, _, tension, _, _, vol_p, _, _ = buffers
    edges, rest_lengths, K0, a, b, _, arm_c, _, _ = springs
    on, arms_on, tets, rest_volumes, kv, _, _, _, v_c, _, _, _, _ = volume
    nnz, slots, tet_slots, zero_slots, diag_slots = tangent
    sup_ptr, row_ptr, rows, x_ptr, upd_ptr, upd_sup, upd_q1, upd_q2, a_src, a_dst, perm = symbolic
    x = xs[cur]
    data = np.empty(nnz)
    assemble_tangent(x, edges, rest_lengths, K0, a, b, row_sums(arm_c), tension[cur], slots,
                     data)
    if on:
        if nodal[0]:
            if arms_on:
                add_nodal_volume_tangent(x, tets, rest_volumes, kv, nodal[1], tet_slots, data,
                                         (row_sums(v_c), row_sums(vol_p[cur])), nodal[2])
            else:
                add_nodal_volume_tangent(x, tets, rest_volumes, kv, nodal[1], tet_slots, data,
                                         None, nodal[2])
        elif arms_on:
            add_volume_tangent(x, tets, rest_volumes, kv, tet_slots, data,
                               (row_sums(v_c), row_sums(vol_p[cur])))
        else:
            add_volume_tangent(x, tets, rest_volumes, kv, tet_slots, data, None)
    for t in range(len(zero_slots)):
        data[zero_slots[t]] = 0.0
    for t in range(len(diag_slots)):
        data[diag_slots[t]] = 1.0
    lx, ld = np.empty(x_ptr[-1]), np.empty(len(perm))
    bad = _numeric(sup_ptr, row_ptr, rows, x_ptr, upd_ptr, upd_sup, upd_q1, upd_q2, a_src,
                   a_dst, data, lx, ld)
    return bad, lx, ld


@njit(**JIT)
def newton_iterations(cur, it, fresh, stale, start, resume, norm,
                      xs, forces, tension, arm_out, dx, vol_p, vol_s, res,
                      edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev,
                      volume_on, volume_arms_on, tets, rest_volumes, kv, v_lo, v_hi, v_r, v_c,
                      v_pressure_prev, v_strain_prev, force_tets, volumes,
                      gravity_on, masses, gravity,
                      flat, held_flat, mat,
                      nnz, slots, tet_slots, zero_slots, diag_slots,
                      nodal_on, node_tet_ptr, node_tets, node_tet_local, star_ptr, block_ptr,
                      block_slots, node_volume, node_pressure,
                      sup_ptr, row_ptr, rows, x_ptr, upd_ptr, upd_sup, upd_q1, upd_q2, a_src,
                      a_dst, perm, lx, ld,
                      rtol, floor, max_iter, refactor_ratio):
    """Modified Newton iterations from a state until convergence, a refactorisation or failure.

    The state: the current buffer index ``cur``, the iteration ``it``, ``fresh``, ``stale``,
    ``start`` (evaluate the current buffer's positions first), ``resume`` (continue an
    iteration after its factorisation: fresh, not stale) and the current residual
    ``norm``. Then the groups ``buffers``, ``springs``, ``volume``, ``loads`` of
    :func:`evaluate`, the dofs (the free components, the prescribed ones, the free dofs in
    the tangent), the groups ``tangent``, ``nodal`` (:func:`evaluate`'s, flattened: the flag,
    the pattern's six arrays, the scratch's two) and ``symbolic`` of :func:`factorise`, the kept
    factorisation's ``L`` and ``D`` (``lx``, ``ld``: :class:`particle.sparse_ldl.Factor`)
    and the settings, every argument on its own: numba types a call's arguments fast one
    by one, a tuple of more than four arrays slowly (microseconds). Returns ``(status,
    cur, it, fresh, stale, norm, lx, ld, factorisations)``: the status :data:`CONVERGED`,
    :data:`FACTORISE` (a zero pivot: factorise in Python) or :data:`FAILED`, the kept
    factorisation and how many factorisations this call made.
    """
    buffers = (xs, forces, tension, arm_out, dx, vol_p, vol_s, res)
    springs = (edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev)
    volume = (volume_on, volume_arms_on, tets, rest_volumes, kv, v_lo, v_hi, v_r, v_c,
              v_pressure_prev, v_strain_prev, force_tets, volumes)
    loads = (gravity_on, masses, gravity)
    tangent = (nnz, slots, tet_slots, zero_slots, diag_slots)
    nodal = (nodal_on, (node_tet_ptr, node_tets, node_tet_local, star_ptr, block_ptr,
                        block_slots), (node_volume, node_pressure))
    symbolic = (sup_ptr, row_ptr, rows, x_ptr, upd_ptr, upd_sup, upd_q1, upd_q2, a_src, a_dst,
                perm)
    factorisations = 0
    step = np.empty(len(mat))
    held = np.empty(len(held_flat))
    if start:
        norm = evaluate(cur, buffers, springs, volume, loads, flat, nodal)
    while True:
        if not resume:
            if converged(forces[cur], held_flat, held, norm, rtol, floor):
                return CONVERGED, cur, it, fresh, stale, norm, lx, ld, factorisations
            if it == max_iter:
                return FAILED, cur, it, fresh, stale, norm, lx, ld, factorisations
            if stale:
                bad, new_lx, new_ld = factorise(cur, buffers, springs, volume, tangent,
                                                symbolic, nodal)
                if bad >= 0:
                    return FACTORISE, cur, it, fresh, stale, norm, lx, ld, factorisations
                lx, ld = new_lx, new_ld
                factorisations += 1
                stale, fresh = False, True
        resume = False
        _solve_restricted(sup_ptr, row_ptr, rows, x_ptr, lx, ld, perm, mat, res[cur], step)
        trial = 1 - cur
        trial_norm = moved(trial, cur, step, buffers, springs, volume, loads, flat, nodal)
        if fresh:  # line search on a fresh tangent's step
            for _ in range(8):
                if trial_norm < norm:
                    break
                for t in range(len(step)):
                    step[t] = 0.5 * step[t]
                trial_norm = moved(trial, cur, step, buffers, springs, volume, loads, flat,
                                   nodal)
        if not trial_norm < norm:  # includes NaN
            if fresh:
                return FAILED, cur, it, fresh, stale, norm, lx, ld, factorisations
            stale = True  # old factorisation: refactorise here and retry
            it += 1
            continue
        if trial_norm > refactor_ratio * norm:
            stale = True
        fresh = False
        cur, norm = trial, trial_norm
        it += 1
