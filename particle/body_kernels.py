"""Compiled (numba) passes of :func:`particle.body.incremental_form`.

The whole-body fit's loaded-mode rows take the incremental tangent's quadratic form and its
position gradient twice per row (polarisation), thousands of times per calibration; as numpy
expressions each call allocated some forty (E, 3) and (T, 3) temporaries. These passes compute
the same per-connector and per-tet quantities in one loop each, operation for operation as the
numpy expressions of :func:`particle.body.incremental_form_numpy` (its twin) evaluate them,
and scatter the gradient in the order ``np.add.at`` adds. The sums over connectors and tets
stay numpy's (pairwise) in the caller.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from particle.kernels import JIT
from particle.volume import einsum_dot3


@njit(**JIT)
def connector_form(x, field, edges, rest_lengths, K0, a, b, k1, k2, q, grad, explicit):
    """Connectors' part of the incremental form.

    Args:
        x: (N, 3) positions [m]; field: (N, 3) the field ``phi`` [m].
        edges: (E, 2) int64; rest_lengths: (E,) [m]; K0, a, b, k1, k2: (E,) [N/m].
        q: (E,) out, each connector's ``s (u.w)^2 + (T/l)(|w|^2 - (u.w)^2)`` [N m].
        grad: (N, 3) in/out, the form's position gradient added [N].
        explicit: (4, E) out, dq/dK0, dq/da, dq/db, dq/dk1 (= dq/dk2) [m^2].
    """
    n_e = edges.shape[0]
    grad_d = np.empty((n_e, 3))
    for e in range(n_e):
        i, j = edges[e, 0], edges[e, 1]
        d0, d1, d2 = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
        length = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
        u0, u1, u2 = d0 / length, d1 / length, d2 / length
        L0 = rest_lengths[e]
        eps = length / L0 - 1.0
        dx = length - L0
        w0 = field[j, 0] - field[i, 0]
        w1 = field[j, 1] - field[i, 1]
        w2 = field[j, 2] - field[i, 2]
        uw = einsum_dot3(u0, u1, u2, w0, w1, w2)
        ww = einsum_dot3(w0, w1, w2, w0, w1, w2)
        uw2 = uw * uw
        eps2 = eps * eps
        transverse = ww - uw2
        tension = ((K0[e] + a[e] * eps) + b[e] * eps2) * dx
        s_long = (K0[e] + 2.0 * a[e] * eps) + 3.0 * b[e] * eps2
        s = (s_long + k1[e]) + k2[e]
        per_l = tension / length
        q[e] = s * uw2 + per_l * transverse
        c1 = uw2 * (2.0 * a[e] + 6.0 * b[e] * eps) / L0
        c2 = 2.0 * (s - per_l) * uw
        c3 = transverse * (s_long / length - tension / (length * length))
        grad_d[e, 0] = (c1 * u0 + c2 * ((w0 - uw * u0) / length)) + c3 * u0
        grad_d[e, 1] = (c1 * u1 + c2 * ((w1 - uw * u1) / length)) + c3 * u1
        grad_d[e, 2] = (c1 * u2 + c2 * ((w2 - uw * u2) / length)) + c3 * u2
        per_length = transverse * dx / length
        explicit[0, e] = uw2 + per_length
        explicit[1, e] = 2.0 * eps * uw2 + eps * per_length
        explicit[2, e] = 3.0 * eps2 * uw2 + eps2 * per_length
        explicit[3, e] = uw2
    for e in range(n_e):
        j = edges[e, 1]
        for c in range(3):
            grad[j, c] += grad_d[e, c]
    for e in range(n_e):
        i = edges[e, 0]
        for c in range(3):
            grad[i, c] -= grad_d[e, c]


@njit(**JIT)
def _cross(a, b, out):
    # np.cross's products and differences, component by component
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(**JIT)
def _dot3(a, b):
    return einsum_dot3(a[0], a[1], a[2], b[0], b[1], b[2])


@njit(**JIT)
def tet_form(x, field, tets, rest_volumes, kv, stiffness, q, grad, explicit):
    """The volume term's part of the incremental form.

    Args:
        x, field: (N, 3) as :func:`connector_form`.
        tets: (T, 4) int64; rest_volumes: (T,) [m^3]; kv: (T,) the long-term bulk stiffness
            [Pa]; stiffness: (T,) the instantaneous one [Pa].
        q: (T,) out, each tet's ``stiffness/V0 (g.phi)^2 + P phi^T (d^2V/dx^2) phi`` [N m].
        grad: (N, 3) in/out, the form's position gradient added [N].
        explicit: (2, T) out, dq/dkv and dq/dkv1 (= dq/dkv2) [m^3].
    """
    n_t = tets.shape[0]
    e = np.empty((3, 3))  # edge vectors from vertex 0
    f = np.empty((3, 3))  # the field's differences along them
    # cross products: (f1 x e2 + e1 x f2, e2 x f0 + f2 x e0, f0 x e1 + e0 x f1) -> d_g,
    # (e1 x e2, e2 x e0, e0 x e1) -> d_v, (f1 x f2, f2 x f0, f0 x f1) -> d_h
    pair = np.empty((3, 2, 3))
    ee = np.empty((3, 3))
    ff = np.empty((3, 3))
    grad_e = np.empty((3, n_t, 3))
    for t in range(n_t):
        for k in range(3):
            for m in range(3):
                e[k, m] = x[tets[t, k + 1], m] - x[tets[t, 0], m]
                f[k, m] = field[tets[t, k + 1], m] - field[tets[t, 0], m]
        for k in range(3):
            k1, k2 = (k + 1) % 3, (k + 2) % 3
            _cross(f[k1], e[k2], pair[k, 0])
            _cross(e[k1], f[k2], pair[k, 1])
            _cross(e[k1], e[k2], ee[k])
            _cross(f[k1], f[k2], ff[k])
        V0 = rest_volumes[t]
        volume = _dot3(e[0], ee[0]) / 6.0
        strain = volume / V0 - 1.0
        pressure = kv[t] * strain
        g_phi = (_dot3(f[0], ee[0]) + _dot3(e[0], pair[0, 0]) + _dot3(e[0], pair[0, 1])) / 6.0
        h_phi = (_dot3(f[0], pair[0, 0]) + _dot3(f[0], pair[0, 1]) + _dot3(e[0], ff[0])) / 3.0
        q[t] = stiffness[t] / V0 * (g_phi * g_phi) + pressure * h_phi
        coef_g = 2.0 * stiffness[t] / V0 * g_phi
        coef_v = kv[t] / V0 * h_phi
        for k in range(3):
            for m in range(3):
                grad_e[k, t, m] = ((coef_g * ((pair[k, 0, m] + pair[k, 1, m]) / 6.0)
                                    + coef_v * (ee[k, m] / 6.0)) + pressure * (ff[k, m] / 3.0))
        g2 = g_phi * g_phi / V0
        explicit[0, t] = g2 + strain * h_phi
        explicit[1, t] = g2
    # np.add.at's order: each edge vector's gradient to its far vertex, then off vertex 0
    for k in range(3):
        for t in range(n_t):
            node = tets[t, k + 1]
            for m in range(3):
                grad[node, m] += grad_e[k, t, m]
        for t in range(n_t):
            node = tets[t, 0]
            for m in range(3):
                grad[node, m] -= grad_e[k, t, m]
