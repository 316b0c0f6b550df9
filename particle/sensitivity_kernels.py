"""Compiled (numba) pieces of the adjoint pass of :mod:`particle.sensitivity`.

One adjoint step (the module docstring there) needs, besides the tangent's LU:

* the force pattern ``G`` (n_dofs, E) of unit connector tensions (``+u_e`` on the
  dofs of end i, ``-u_e`` on those of end j, nothing on a fixed particle) applied
  both ways, ``G beta`` (:func:`pattern_product`) and ``G^T lam``
  (:func:`pattern_transpose_product`), straight from the unit vectors and the dofs
  of the connector ends (no sparse matrix); ``beta = dbar + sum_i c_i abar_i``
  (:func:`elongation_adjoint`);
* ``K_aP n`` (:func:`csc_columns_product`);
* the explicit parameter derivatives contracted with the adjoints, and the
  history adjoints stepped back (:func:`arm_derivatives`, :func:`add_partials`),
  and the volume term's (:func:`add_volume_partials`; its arms':
  :func:`add_volume_pattern_product`, :func:`add_volume_arm_partials`).

The adjoints are stored sample-major: a row per output sample (``lam`` (S', n),
``tau`` (S', E), ``abar`` (S, 2, E), ``dbar`` (S, E)), so that the kernels run along
contiguous memory and the factorisation's (n, S') Fortran-ordered solution
(:meth:`particle.sparse_ldl.Factor.solve`, like SuperLU's) is ``lam.T`` without a
copy. ``cols`` (S',) lists the samples a step carries (the live columns), in
ascending order; row k of ``lam``/``tau``/``beta`` is sample ``cols[k]``, and
``abar``/``dbar``/``jac`` are indexed by the sample itself.

Sums run in the order of the scipy products they replace (edges ascending per
dof, dofs ascending per connector: ``G beta`` and ``G^T lam`` are bitwise scipy's),
so the pass matches its plain numpy/scipy twin
(:func:`particle.sensitivity.point_jacobian_numpy`) to round-off.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from particle.kernels import JIT, connector_vector
from particle.volume import _tet_gradient


@njit(**JIT)
def connector_geometry(x, edges, rest_lengths, unit, dx):
    """Writes unit vectors ``unit`` (E, 3) [-] (i to j) and elongations ``dx`` (E,) [m] at
    positions ``x`` (N, 3) [m]."""
    for e in range(edges.shape[0]):
        i, j, d0, d1, d2, length = connector_vector(x, edges, e)
        unit[e, 0] = d0 / length
        unit[e, 1] = d1 / length
        unit[e, 2] = d2 / length
        dx[e] = length - rest_lengths[e]


@njit(**JIT)
def csc_columns_product(indptr, indices, data, cols, values, out):
    """``out`` (n,) = ``A[:, cols] @ values`` of the CSC matrix (indptr, indices, data);
    ``cols`` ascending (the order of scipy's ``A @ v`` when v is zero elsewhere)."""
    out[:] = 0.0
    for k in range(cols.shape[0]):
        c = cols[k]
        v = values[k]
        for idx in range(indptr[c], indptr[c + 1]):
            out[indices[idx]] += data[idx] * v


@njit(**JIT)
def elongation_adjoint(cols, dbar, abar, arm_c, with_arms, beta):
    """``beta`` (S', E) = ``dbar + sum_i c_i abar_i`` [1/m] of the samples ``cols``: the
    adjoint of each connector's elongation; ``arm_c`` (E, 2) [N/m], read only
    ``with_arms`` (an elastic step: ``beta = dbar``).

    Why a flag and not None for an elastic step: numba compiles one specialisation per
    None/array combination, in every fresh worker of a calibration."""
    c1, c2 = np.ascontiguousarray(arm_c[:, 0]), np.ascontiguousarray(arm_c[:, 1])
    for k in range(cols.shape[0]):
        s = cols[k]
        if not with_arms:
            beta[k] = dbar[s]
        else:
            _elongation_row(beta[k], dbar[s], c1, abar[s, 0], c2, abar[s, 1])


@njit(**JIT)
def _elongation_row(out, d, c1, a1, c2, a2):
    """``out = d + (c1 a1 + c2 a2)`` (1-D, element by element: a loop the compiler
    vectorises)."""
    for j in range(out.shape[0]):
        out[j] = d[j] + (c1[j] * a1[j] + c2[j] * a2[j])


@njit(**JIT)
def pattern_product(end_dofs, unit, beta, out):
    """``out`` (S', n) = ``(G beta^T)^T``: the forces on the matrix dofs of connector tensions
    ``beta`` (S', E), ``G`` putting ``+u_e`` on end i and ``-u_e`` on end j (``end_dofs``
    (E, 2) first dof of each end, -1 for a fixed particle)."""
    out[:] = 0.0
    for k in range(beta.shape[0]):
        row = out[k]
        for e in range(end_dofs.shape[0]):
            b = beta[k, e]
            f0, f1, f2 = unit[e, 0] * b, unit[e, 1] * b, unit[e, 2] * b
            di = end_dofs[e, 0]
            if di >= 0:
                row[di] += f0
                row[di + 1] += f1
                row[di + 2] += f2
            dj = end_dofs[e, 1]
            if dj >= 0:
                row[dj] -= f0
                row[dj + 1] -= f1
                row[dj + 2] -= f2


@njit(**JIT)
def pattern_transpose_product(end_dofs, unit, lam, tau):
    """``tau`` (S', E) = ``(G^T lam^T)^T``: each connector's ``u_e . (lam_i - lam_j)`` for
    the dof vectors ``lam`` (S', n) (a fixed end contributes nothing)."""
    for k in range(lam.shape[0]):
        row = lam[k]
        for e in range(end_dofs.shape[0]):
            first, second = end_dofs[e, 0], end_dofs[e, 1]
            u0, u1, u2 = unit[e, 0], unit[e, 1], unit[e, 2]
            if second >= 0 and (first < 0 or second < first):  # lower dof first, as scipy
                first, second = second, first
                u0, u1, u2 = -u0, -u1, -u2
            t = 0.0
            if first >= 0:
                t += u0 * row[first]
                t += u1 * row[first + 1]
                t += u2 * row[first + 2]
            if second >= 0:
                t -= u0 * row[second]
                t -= u1 * row[second + 1]
                t -= u2 * row[second + 2]
            tau[k, e] = t


@njit(**JIT)
def arm_derivatives(r, c, k, b, force_prev, dx, dx_prev, dA_dk, dA_db):
    """Writes ``dA_i/dk_i`` [m] and ``dA_i/db_i`` [m/s] (E, 2) of the arm forces
    ``A_i = r_i A_i^prev + c_i (dx - dx_prev)`` of one exact step: ``r`` [-], ``c`` [N/m],
    ``k`` [N/m], ``b`` [N s/m], ``force_prev`` [N] (E, 2); ``dx``, ``dx_prev`` (E,) [m]."""
    for e in range(r.shape[0]):
        step = dx[e] - dx_prev[e]
        for i in range(2):
            log_r = math.log(r[e, i])
            dA_dk[e, i] = (log_r * r[e, i] / k[e, i]) * force_prev[e, i] + r[e, i] * step
            dA_db[e, i] = ((-log_r * r[e, i] / b[e, i]) * force_prev[e, i]
                           + ((c[e, i] - r[e, i] * k[e, i]) / b[e, i]) * step)


@njit(**JIT)
def add_partials(cols, tau, dx, rest_lengths, jac, with_arms, arm_r, arm_c, dA_dk, dA_db,
                 abar, dbar):
    """``jac`` (S, 7, E) += this step's explicit parameter derivatives contracted with the
    adjoints of the samples ``cols``, and the history adjoints stepped back in place.

    ``tau`` (S', E) tension adjoints; springs: ``dT/d(K0, a, b) = dx, eps dx, eps^2 dx``
    (``dx`` (E,) [m], ``eps = dx / rest_lengths``). ``with_arms`` (else the arm arrays are
    not read, :func:`elongation_adjoint` says why a flag): ``mu_i = abar_i + tau`` times
    ``dA_dk``, ``dA_db`` (:func:`arm_derivatives`), then ``abar_i <- r_i mu_i``,
    ``dbar <- -sum_i c_i mu_i`` (``arm_r``, ``arm_c`` (E, 2), ``abar`` (S, 2, E),
    ``dbar`` (S, E)).

    Row by row (one output's row of each array per loop, the per-connector factors taken
    out of the output loop): loops the compiler vectorises, with the same operations on each
    element (bitwise the same results); measured 1.6x as fast as one loop doing every row per
    connector (120 outputs x 1,400 connectors, the liver punch's relaxation: median 1.35 ->
    0.86 ms, minimum 1.18 -> 0.61 ms).
    """
    e = dx.shape[0]
    spring = np.empty((3, e))  # dT/dK0, dT/da, dT/db
    for j in range(e):
        eps = dx[j] / rest_lengths[j]
        spring[0, j] = dx[j]
        spring[1, j] = eps * dx[j]
        spring[2, j] = eps * eps * dx[j]
    for k in range(cols.shape[0]):
        s = cols[k]
        for q in range(3):
            _add_product(jac[s, q], tau[k], spring[q])
    if with_arms:
        _arms_adjoint(cols, tau, abar, dbar, jac, 3, arm_r, arm_c, dA_dk, dA_db)


@njit(**JIT)
def _add_product(out, a, b):
    """``out += a * b`` (1-D, element by element)."""
    for j in range(out.shape[0]):
        out[j] += a[j] * b[j]


@njit(**JIT)
def _arms_adjoint(cols, adjoint, history, d_history, jac, first, arm_r, arm_c, dA_dk, dA_db):
    """The Maxwell arms of M elements (connectors, or the volume elements' arms) in the
    adjoint pass, for the samples ``cols``: ``mu_i = history[s, i] + adjoint[k]`` (the
    adjoint of arm force i, ``adjoint`` (S', M) those of the elements' tensions or
    pressures), ``jac[s, first .. first + 3] += mu_1 dA_1/dk_1, mu_1 dA_1/db_1, mu_2
    dA_2/dk_2, mu_2 dA_2/db_2``, then the history adjoints stepped back: ``history[s, i] =
    r_i mu_i``, ``d_history[s] = -sum_i c_i mu_i`` (``arm_r``, ``arm_c``, ``dA_dk``,
    ``dA_db`` (M, 2))."""
    m = arm_r.shape[0]
    r, c = np.ascontiguousarray(arm_r.T), np.ascontiguousarray(arm_c.T)
    dk, db = np.ascontiguousarray(dA_dk.T), np.ascontiguousarray(dA_db.T)
    mu = np.empty((2, m))
    for k in range(cols.shape[0]):
        s = cols[k]
        a_row, d_row, out = history[s], d_history[s], jac[s]
        for i in range(2):
            _sum_into(mu[i], a_row[i], adjoint[k])
            _add_product(out[first + 2 * i], mu[i], dk[i])
            _add_product(out[first + 2 * i + 1], mu[i], db[i])
            _product_into(a_row[i], r[i], mu[i])
        _negative_dot_into(d_row, c[0], mu[0], c[1], mu[1])


@njit(**JIT)
def _sum_into(out, a, b):
    """``out = a + b`` (1-D, element by element)."""
    for j in range(out.shape[0]):
        out[j] = a[j] + b[j]


@njit(**JIT)
def _product_into(out, a, b):
    """``out = a * b`` (1-D, element by element)."""
    for j in range(out.shape[0]):
        out[j] = a[j] * b[j]


@njit(**JIT)
def _negative_dot_into(out, a1, b1, a2, b2):
    """``out = -(a1 b1 + a2 b2)`` (1-D, element by element)."""
    for j in range(out.shape[0]):
        out[j] = -(a1[j] * b1[j] + a2[j] * b2[j])


@njit(**JIT)
def add_volume_arm_partials(cols, pressure, jac, arm_r, arm_c, dP_dk, dP_db, pbar, jbar):
    """``jac`` (S, 4, T) += this step's derivatives with respect to each tet's volume arms
    ``kv1, bv1, kv2, bv2`` of the samples ``cols`` (``pressure`` (S', T) the adjoints of the
    tets' pressures, ``dP_dk``, ``dP_db`` (T, 2) from :func:`arm_derivatives`), and the
    history adjoints ``pbar`` (S, 2, T), ``jbar`` (S, T) stepped back
    (:func:`_arms_adjoint`)."""
    _arms_adjoint(cols, pressure, pbar, jbar, jac, 0, arm_r, arm_c, dP_dk, dP_db)


@njit(**JIT)
def add_volume_pattern_product(x, tets, tet_dofs, rest_volumes, gamma, out):
    """``out`` (S', n) += the forces on the matrix dofs of the pressures ``gamma / V0``
    (``gamma`` (S', T), the adjoints of the tets' volume strains): ``-gamma_t/V0_t dV/dp_a``
    on the dofs of each vertex a (``tet_dofs`` (T, 4), -1 fixed: nothing)."""
    n_tets = tets.shape[0]
    g = np.empty((n_tets, 4, 3))
    for t in range(n_tets):
        _tet_gradient(x, tets, t, g[t])
    # output by output (each row's sums in tet order, as tet by tet): a row stays in cache
    for k in range(gamma.shape[0]):
        row = out[k]
        for t in range(n_tets):
            w = gamma[k, t] / rest_volumes[t]
            for a in range(4):
                d = tet_dofs[t, a]
                if d >= 0:
                    row[d] -= w * g[t, a, 0]
                    row[d + 1] -= w * g[t, a, 1]
                    row[d + 2] -= w * g[t, a, 2]


@njit(**JIT)
def add_volume_partials(x, tets, tet_dofs, rest_volumes, cols, lam, jac_kv, pressure, strain):
    """``jac_kv`` (S, T) += ``omega . df/dkv_t`` of the samples ``cols``, with ``df/dkv_t =
    -(V/V0 - 1) dV/dx`` at positions ``x`` (N, 3) [m] and ``omega`` the dof vectors ``lam``
    (S', n) (``tet_dofs`` (T, 4) first dof of each vertex, -1 fixed: omega = 0 there);
    [N/Pa per unit adjoint]. Writes ``pressure`` (S', T), the adjoint of each tet's
    pressure ``omega . (-dV/dx)``, and ``strain`` (T,), the volume strains ``V/V0 - 1``
    (the volume arms' partials need both)."""
    n_tets = tets.shape[0]
    grad = np.empty((n_tets, 4, 3))
    for t in range(n_tets):
        _tet_gradient(x, tets, t, grad[t])
        i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        a0, a1, a2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
        b0, b1, b2 = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
        c0, c1, c2 = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
        # V from the triple product (V/V0 - 1 cancels, so its round-off shows in the strain;
        # its terms summed in the order written, not numpy einsum's of signed_volumes_numpy)
        volume = (a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2)
                  + a2 * (b0 * c1 - b1 * c0)) / 6.0
        strain[t] = volume / rest_volumes[t] - 1.0
    for k in range(cols.shape[0]):
        row = lam[k]
        out = jac_kv[cols[k]]
        for t in range(n_tets):
            g = grad[t]
            acc = 0.0
            for a in range(4):
                d = tet_dofs[t, a]
                if d >= 0:
                    acc += g[a, 0] * row[d]
                    acc += g[a, 1] * row[d + 1]
                    acc += g[a, 2] * row[d + 2]
            pressure[k, t] = -acc
            out[t] -= strain[t] * acc
