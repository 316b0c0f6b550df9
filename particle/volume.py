"""Per-tetrahedron volume term of the particle model (in the spirit of Teschner et al. 2004).

Each tetrahedron t of the mesh (vertices p0..p3, positively oriented) with rest
volume ``V0`` and present volume ``V = (p1 - p0) . ((p2 - p0) x (p3 - p0)) / 6``
has the volume strain ``j = V/V0 - 1`` and a pressure-like generalised force

    P_t = kv_t j + P_1 + P_2        [Pa]

which pushes its four particles with ``f_a = -P_t dV/dp_a``, ``dV/dp_1 = (p2 - p0) x
(p3 - p0)/6`` (cyclically; ``dV/dp_0 = -(sum of the others)``). The elastic part is
the gradient of the energy

    E_t = kv_t / 2 * V0 * (V/V0 - 1)^2        [J],   kv_t [Pa = N/m^2]

Under a small uniform dilation by strain eps, ``V/V0 - 1 = 3 eps`` and it adds exactly
``kv`` to the body's bulk modulus (``E = 9/2 kv eps^2`` per unit volume), which is how
``kv`` is read and initialised (:func:`network_bulk_modulus`).

**Elastic or viscoelastic.** Without arms (``ConnectorParams.kv1`` None, scene
``particle.volume = true``) the term does not relax. With them (``particle.volume =
"viscoelastic"``) ``P_1, P_2`` are Maxwell arms in the volume strain, exactly the
connectors' arms with ``j`` for the elongation: a spring ``kv_i`` [Pa] in series with a
dashpot ``bv_i`` [Pa s], ``dP_i/dt = kv_i dj/dt - P_i/tau_i``, advanced by the
connectors' recursion ``P_i^t = r_i P_i^{t-1} + c_i (j^t - j^{t-1})``
(:meth:`particle.params.ConnectorParams.volume_arm_recursion`; the explicit runs the
paper's backward Euler ``c_i = kv_i bv_i/(kv_i dt + bv_i)``, the quasi-static path the
exact form). The term's instantaneous stiffness is then ``kv + kv1 + kv2``, its
long-term one ``kv``. Why the volume term relaxes although the FE's Prony series acts
on the deviatoric stress only: on coarse linear tets the per-tet term also carries
shear-like (bending) stiffness, which relaxes in the FE material.

The arm state (pressures (T, 2), last volume strains (T,)) lives in the
:class:`~particle.model.State` (``volume_arm``, ``volume_prev``), as the connectors'
``arm_force``/``dx_prev``. The compiled kernels take it as one tuple ``arms = (r (M, 2),
c (M, 2) [Pa], pressure_prev (M, 2) [Pa], strain_prev (M,), pressure_out (M, 2),
strain_out (M,))`` (outputs aliasing the inputs commit a step in place, scratch outputs
leave the state unchanged, as :func:`particle.kernels.internal_forces` does), or None,
which compiles the arms out; :func:`volume_arm_pressures` / :func:`volume_arm_step`
advance the arms of one *volume element* k given its volume strain: a tet here, and the
same functions serve any other element with a volume strain (the nodal term's particles,
:mod:`particle.nodal_volume`).

``kv`` and the arms live in :class:`particle.params.ConnectorParams` (``kv``, ``kv1``,
``bv1``, ``kv2``, ``bv2``, each (T,) or None), so :meth:`Model.with_params` and
``dataclasses.replace`` carry them with the other parameters; the tetrahedra
(``Model.tets``) and rest volumes (``Model.rest_volumes``) live in the Model. When ``kv``
is None the kernels receive None and numba compiles the term out.

Functions:

* :func:`add_volume_forces` (numba) / :func:`volume_forces_numpy` (twin, with
  :func:`volume_arm_pressures_numpy`): forces (and the arms' step);
* :func:`volume_energy`: the elastic energy (numpy); :func:`volume_arm_energy`: the
  energy held by the arms' springs;
* :func:`volume_kv_sensitivity_numpy`: d(forces)/d(kv) per tet (numpy);
* :func:`add_volume_tangent` (numba, closed form) / :func:`add_volume_tangent_numpy` (twin,
  per tet :func:`volume_hessian_numpy`): the tangent
  ``(kv + c_1 + c_2)/V0 g g^T + P d^2V/dx^2`` (``g = dV/dx``; ``c_i`` the arms' step
  coefficients, 0 without arms or for the long-term, relaxed state);
* :func:`volume_frequency_bound`: an upper bound of the term's largest mass-scaled
  eigenvalue over the states whose connector strains (and volume ratios,
  :func:`volume_ratio_range`) stay in a range, added to the springs' one by the
  rigorous stable-step bound :func:`particle.integrator.critical_time_step`, and
  :func:`node_volume_stiffness_bound`, its per-particle form: defined in
  :mod:`particle.volume_bounds` (numpy only, used when a run is prepared) and
  importable from here with the rest of the term.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from forcecal.errors import MeshError, ParameterError
from particle.dispatch import joined
from particle.lanes import (ALL_LANES, LANES, arm_pair_lanes, gather_rows, vadd, vdiv, vle_mask,
                            vload, vlt_mask, vmul, vsplat, vstore, vsub)
from particle.volume_bounds import (node_volume_stiffness_bound, volume_frequency_bound,
                                    volume_ratio_range)

JIT = dict(cache=True, error_model="numpy")

# the six edges of a tet as vertex-slot pairs (the mesh's TET_EDGES order is not needed here)
TET_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)


def tet_name(t: int, tets: np.ndarray | None = None) -> str:
    """``tet t``, with its four particles when ``tets`` (T, 4) is given (for messages)."""
    if tets is None:
        return f"tet {int(t)}"
    return f"tet {int(t)} (particles {'-'.join(str(int(v)) for v in tets[t])})"


def signed_volumes(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) signed volumes [m^3] of ``tets`` (T, 4) at positions ``x`` (N, 3).

    Compiled for float64 positions (:func:`_signed_volumes`: the operations of
    :func:`signed_volumes_numpy` in its order; a static solve of the relaxed volume arms
    records the strains at every equilibrium, where the numpy expressions cost 30x the
    pass), the numpy expressions otherwise."""
    x, tets = np.asarray(x), np.asarray(tets)
    if (x.dtype == np.float64 and x.ndim == 2 and x.shape[1] == 3 and tets.ndim == 2
            and tets.shape[1] == 4 and tets.dtype.kind in "iu"):
        out = np.empty(len(tets))
        _signed_volumes(x, tets, out)
        return out
    return signed_volumes_numpy(x, tets)


@njit(**JIT)
def einsum_dot3(a0, a1, a2, b0, b1, b2):
    """``a . b`` of two 3-vectors as numpy's ``einsum("ij,ij->i")`` adds a row's three
    products (first and last, then the middle one): what the compiled twins of numpy
    expressions use to give their bits."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@njit(**JIT)
def _signed_volumes(x, tets, out):
    for t in range(tets.shape[0]):
        i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        a0, a1, a2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
        b0, b1, b2 = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
        c0, c1, c2 = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
        g0, g1, g2 = b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0
        out[t] = einsum_dot3(a0, a1, a2, g0, g1, g2) / 6.0


def signed_volumes_numpy(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """:func:`signed_volumes` as numpy expressions (its twin)."""
    p = x[tets]
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0],
                     np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0


def volume_gradients_numpy(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T, 4, 3) dV/dp_a [m^2] of every tet's four vertices."""
    p = x[tets]
    e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    g = np.empty((len(tets), 4, 3))
    g[:, 1] = np.cross(e2, e3) / 6.0
    g[:, 2] = np.cross(e3, e1) / 6.0
    g[:, 3] = np.cross(e1, e2) / 6.0
    g[:, 0] = -(g[:, 1] + g[:, 2] + g[:, 3])
    return g


def volume_energy(x: np.ndarray, tets: np.ndarray, rest_volumes: np.ndarray,
                  kv: np.ndarray) -> float:
    """Total volume energy ``sum kv/2 V0 (V/V0 - 1)^2`` [J] at positions ``x`` (N, 3)."""
    j = signed_volumes(x, tets) / rest_volumes - 1.0
    return float(np.sum(0.5 * kv * rest_volumes * j * j))


def volume_arm_energy(pressure: np.ndarray, stiffness: np.ndarray,
                      rest_volumes: np.ndarray) -> float:
    """Energy [J] held by the volume arms' springs: ``sum V0 P_i^2 / (2 kv_i)`` of the arm
    pressures ``pressure`` (T, 2) [Pa] with stiffnesses ``stiffness`` (T, 2) [Pa]."""
    return float(np.sum(rest_volumes[:, None] * pressure ** 2 / (2.0 * stiffness)))


def volume_strains(x: np.ndarray, tets: np.ndarray, rest_volumes: np.ndarray) -> np.ndarray:
    """(T,) volume strains ``V/V0 - 1`` [1] of ``tets`` at positions ``x`` (N, 3)."""
    return signed_volumes(x, tets) / rest_volumes - 1.0


def volume_arm_pressures_numpy(strain: np.ndarray, r: np.ndarray, c: np.ndarray,
                               pressure_prev: np.ndarray, strain_prev: np.ndarray
                               ) -> np.ndarray:
    """(M, 2) arm pressures [Pa] after one step to the volume strains ``strain`` (M,) from
    ``pressure_prev`` (M, 2) at ``strain_prev`` (M,): ``r P + c (j - j_prev)`` (the twin of
    :func:`volume_arm_pressures`)."""
    return r * pressure_prev + c * (strain - strain_prev)[:, None]


def volume_forces_numpy(x: np.ndarray, tets: np.ndarray, rest_volumes: np.ndarray,
                        kv: np.ndarray, arm_pressure: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) volume forces [N] (the plain-numpy twin of :func:`add_volume_forces`);
    ``arm_pressure`` (T,) [Pa]: the arms' summed pressures at ``x`` (None: no arms)."""
    j = volume_strains(x, tets, rest_volumes)
    pressure = kv * j if arm_pressure is None else kv * j + arm_pressure
    return pressure_forces_numpy(x, tets, pressure)


def pressure_forces_numpy(x: np.ndarray, tets: np.ndarray, pressure: np.ndarray) -> np.ndarray:
    """(N, 3) forces [N] ``f_a = -P_t dV_t/dp_a`` of tet pressures ``pressure`` (T,) [Pa]
    summed on the particles (the per-tet and the nodal term's force pass)."""
    f = -pressure[:, None, None] * volume_gradients_numpy(x, tets)
    out = np.zeros_like(x, dtype=np.float64)
    np.add.at(out, tets.ravel(), f.reshape(-1, 3))
    return out


def volume_kv_sensitivity_numpy(x: np.ndarray, tets: np.ndarray,
                                rest_volumes: np.ndarray) -> np.ndarray:
    """(T, 4, 3) d f_a / d kv_t [N/Pa = m^2]: the force on each tet's vertices per unit kv.

    The forces are linear in kv: ``f_a = -kv_t (V/V0 - 1) dV/dp_a``, so this is
    ``-(V/V0 - 1) dV/dp_a`` (for adjoint/direct sensitivities of the curves to kv;
    a global kv's sensitivity is the sum over the tets).
    """
    j = signed_volumes(x, tets) / rest_volumes - 1.0
    return -j[:, None, None] * volume_gradients_numpy(x, tets)


def volume_hessian_numpy(x: np.ndarray, tet: np.ndarray, rest_volume: float,
                         kv: float, arm_stiffness: float | None = None,
                         arm_pressure: float | None = None) -> np.ndarray:
    """(12, 12) -d(forces)/dx [N/m] of one tet (vertex-major: rows 3a..3a+2 are vertex a):
    d^2 E/dx^2 of the elastic term, and with ``arm_stiffness`` (the arms' step coefficients
    c_1 + c_2 [Pa]) and ``arm_pressure`` (their summed pressure at ``x`` [Pa]) the arms'
    part too."""
    p = x[tet]
    j = signed_volumes(p, np.arange(4)[None])[0] / rest_volume - 1.0
    # d^2 V / dp_a dp_b (a != b) = [s]_x / 6 with s the edge between the other two vertices
    # oriented by the permutation's sign; built from the affine dependence of g_a on p_b:
    # the gradients at p (copy 0) and with coordinate q of vertex b moved by 1 (copy 1 + 3b + q)
    moved = np.repeat(p[None], 13, axis=0)
    for b in range(4):
        for q in range(3):
            moved[1 + 3 * b + q, b, q] += 1.0
    grads = volume_gradients_numpy(moved.reshape(-1, 3), np.arange(52).reshape(13, 4))
    g = grads[0].ravel()
    h = (grads[1:].reshape(12, 12) - g).T
    for a in range(4):
        h[3 * a:3 * a + 3, 3 * a:3 * a + 3] = 0.0  # g_a does not depend on p_a
    if arm_stiffness is None:
        return kv / rest_volume * np.outer(g, g) + kv * j * h
    return ((kv + arm_stiffness) / rest_volume * np.outer(g, g)
            + (kv * j + arm_pressure) * h)


def add_volume_tangent_numpy(x: np.ndarray, tets: np.ndarray, rest_volumes: np.ndarray,
                             kv: np.ndarray, tet_slots: np.ndarray, data: np.ndarray,
                             arms: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """data (nnz,) += the volume tangent [N/m] (the plain-numpy twin of :func:`add_volume_tangent`).

    Same arguments; each tet's block from :func:`volume_hessian_numpy` (its second
    derivative from unit displacements, not the kernel's closed form), scattered
    through ``tet_slots`` (T, 4, 4, 3, 3), skipping the -1 slots.
    """
    blocks = np.empty((len(tets), 4, 4, 3, 3))
    for t in range(len(tets)):
        extra = () if arms is None else (arms[0][t], arms[1][t])
        h = volume_hessian_numpy(x, tets[t], rest_volumes[t], kv[t], *extra)
        blocks[t] = h.reshape(4, 3, 4, 3).transpose(0, 2, 1, 3)
    valid = tet_slots >= 0
    np.add.at(data, tet_slots[valid], blocks[valid])


@njit(**JIT)
def _tet_gradient_tuples(x, i0, i1, i2, i3):
    """``(g0, g1, g2, g3, V)``: dV/dp_a (3-tuples [m^2]) and the volume V [m^3] of the tet
    with particles i0..i3 of ``x`` (N, 3) [m]."""
    a0, a1, a2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
    b0, b1, b2 = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
    c0, c1, c2 = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
    s = 1.0 / 6.0
    g1 = ((b1 * c2 - b2 * c1) * s, (b2 * c0 - b0 * c2) * s, (b0 * c1 - b1 * c0) * s)
    g2 = ((c1 * a2 - c2 * a1) * s, (c2 * a0 - c0 * a2) * s, (c0 * a1 - c1 * a0) * s)
    g3 = ((a1 * b2 - a2 * b1) * s, (a2 * b0 - a0 * b2) * s, (a0 * b1 - a1 * b0) * s)
    g0 = (-(g1[0] + g2[0] + g3[0]), -(g1[1] + g2[1] + g3[1]), -(g1[2] + g2[2] + g3[2]))
    return g0, g1, g2, g3, a0 * g1[0] + a1 * g1[1] + a2 * g1[2]


@njit(**JIT)
def _tet_gradient(x, tets, t, g):
    """Writes dV/dp_a (4, 3) [m^2] of tet t into ``g``; returns its volume V [m^3]."""
    g0, g1, g2, g3, v = _tet_gradient_tuples(x, tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3])
    for c in range(3):
        g[0, c], g[1, c], g[2, c], g[3, c] = g0[c], g1[c], g2[c], g3[c]
    return v


@njit(**JIT)
def volume_arm_pressures(k, strain, arms):
    """(P_1, P_2) [Pa]: the two arm pressures of volume element ``k`` after one step to
    the volume strain ``strain`` [1], ``P_i = r_i P_i^prev + c_i (strain - strain_prev)``
    (``arms``: module docstring; nothing stored)."""
    r, c, prev, strain_prev = arms[0], arms[1], arms[2], arms[3]
    d = strain - strain_prev[k]
    return r[k, 0] * prev[k, 0] + c[k, 0] * d, r[k, 1] * prev[k, 1] + c[k, 1] * d


@njit(**JIT)
def volume_arm_step(k, strain, arms):
    """:func:`volume_arm_pressures` of element ``k``, stored into the arms' outputs (the
    pressures and ``strain``); returns their sum [Pa]."""
    p1, p2 = volume_arm_pressures(k, strain, arms)
    out = arms[4]
    out[k, 0] = p1  # may alias the previous pressures: element k's are already read
    out[k, 1] = p2
    arms[5][k] = strain
    return p1 + p2


@njit(**JIT)
def add_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, forces, arms, volumes=None):
    """forces += the volume forces of every tet [N]; returns (first bad tet, its volume [m^3]).

    ``tets`` (T, 4), ``rest_volumes`` (T,) [m^3], ``kv`` (T,) [Pa], ``x``/``forces``
    (N, 3). ``arms``: the volume arms (module docstring), advanced by one step and
    stored in their outputs, or None (elastic: compiled out). A tet is bad when its
    volume V is not in ``(v_lo, v_hi]`` (T,) [m^3]
    (``v_lo`` >= 0: an inverted tet, V <= 0, is always bad); (-1, 0.0) if none. A bad
    tet still gets its (restoring) force; the caller decides to stop. ``volumes`` (T,)
    [m^3], unless None, receives every tet's volume (for a run's final-state check,
    :func:`particle.step_kernels.final_volume_check`). The tets go
    :data:`~particle.lanes.LANES` at a time through :func:`tet_lanes` (the same operations
    lane-wise: bit for bit the scalar loop's forces), the remainder one by one.
    """
    bad = -1
    bad_volume = 0.0
    n = tets.shape[0]
    rest = n // LANES * LANES
    seen = 0  # the lanes outside their range, or-ed over the batches (no branch in the loop)
    for t in range(0, rest, LANES):
        f, v, outside = tet_lanes(x, tets, rest_volumes, kv, v_lo, v_hi, arms, t)
        seen |= outside
        if volumes is not None:
            vstore(volumes, t, v)
        for k in range(LANES):
            add_tet_force(forces, tets, t + k, (f[0][k], f[1][k], f[2][k], f[3][k], f[4][k],
                                                f[5][k], f[6][k], f[7][k], f[8][k], f[9][k],
                                                f[10][k], f[11][k]))
    if seen != 0:  # which tet, and its volume: the same formula, scalar
        for t in range(rest):
            v = tet_volume(x, tets, t)
            if not (v > v_lo[t] and v <= v_hi[t]):
                bad, bad_volume = np.int64(t), v
                break
    sixth = 1.0 / 6.0
    for t in range(rest, n):
        v, g1, g2, g3 = tet_crosses(x, tets, t)
        if bad < 0 and not (v > v_lo[t] and v <= v_hi[t]):
            bad = np.int64(t)
            bad_volume = v
        if volumes is not None:
            volumes[t] = v
        strain = v / rest_volumes[t] - 1.0
        pressure = kv[t] * strain
        if arms is not None:
            pressure += volume_arm_step(t, strain, arms)
        add_tet_force(forces, tets, t, crosses_forces(g1, g2, g3, -pressure * sixth))
    return bad, bad_volume


@njit(**JIT)
def tet_crosses(x, tets, t):
    """(volume [m^3], 6 dV/dp_1, 6 dV/dp_2, 6 dV/dp_3 (3-tuples [m^2])) of tet t: the scalar
    loop's (:func:`tet_volume`'s volume, bit for bit)."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    p0, p1, p2 = x[i0, 0], x[i0, 1], x[i0, 2]
    a0, a1, a2 = x[i1, 0] - p0, x[i1, 1] - p1, x[i1, 2] - p2
    b0, b1, b2 = x[i2, 0] - p0, x[i2, 1] - p1, x[i2, 2] - p2
    c0, c1, c2 = x[i3, 0] - p0, x[i3, 1] - p1, x[i3, 2] - p2
    g10, g11, g12 = b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0  # 6 dV/dp1
    g20, g21, g22 = c1 * a2 - c2 * a1, c2 * a0 - c0 * a2, c0 * a1 - c1 * a0  # 6 dV/dp2
    g30, g31, g32 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0  # 6 dV/dp3
    return ((a0 * g10 + a1 * g11 + a2 * g12) * (1.0 / 6.0), (g10, g11, g12), (g20, g21, g22),
            (g30, g31, g32))


@njit(**JIT)
def crosses_forces(g1, g2, g3, s):
    """The 12 floats of :func:`add_tet_force` for ``s`` = -P/6 [Pa] and the cross products
    ``g_a`` = 6 dV/dp_a (a = 1, 2, 3; :func:`tet_crosses`)."""
    return (s * g1[0], s * g1[1], s * g1[2], s * g2[0], s * g2[1], s * g2[2], s * g3[0],
            s * g3[1], s * g3[2], s * (g1[0] + g2[0] + g3[0]), s * (g1[1] + g2[1] + g3[1]),
            s * (g1[2] + g2[2] + g3[2]))


@njit(**JIT)
def add_volume_forces_grouped(x, tets, rest_volumes, kv, v_lo, v_hi, forces, arms, arms_out,
                              volumes=None):
    """:func:`add_volume_forces` with its ``arms`` in two groups, (r, c, pressure_prev,
    strain_prev) and (pressure_out, strain_out), each None: elastic (the call from Python:
    no argument of more than four arrays, :mod:`particle.dispatch`)."""
    return add_volume_forces(x, tets, rest_volumes, kv, v_lo, v_hi, forces,
                             joined(arms, arms_out), volumes)


@njit(**JIT)
def tet_volume(x, tets, t):
    """The volume [m^3] of tet t, as :func:`add_volume_forces` computes it (bit for bit)."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    p0, p1, p2 = x[i0, 0], x[i0, 1], x[i0, 2]
    a0, a1, a2 = x[i1, 0] - p0, x[i1, 1] - p1, x[i1, 2] - p2
    b0, b1, b2 = x[i2, 0] - p0, x[i2, 1] - p1, x[i2, 2] - p2
    c0, c1, c2 = x[i3, 0] - p0, x[i3, 1] - p1, x[i3, 2] - p2
    g10, g11, g12 = b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0
    return (a0 * g10 + a1 * g11 + a2 * g12) * (1.0 / 6.0)


@njit(**JIT)
def add_tet_force(forces, tets, t, f):
    """forces += tet t's forces [N]: ``f`` = the forces on vertices 1, 2, 3 and minus the
    force on vertex 0 (12 floats, the sum of the others), added in that order."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    forces[i1, 0] += f[0]
    forces[i1, 1] += f[1]
    forces[i1, 2] += f[2]
    forces[i2, 0] += f[3]
    forces[i2, 1] += f[4]
    forces[i2, 2] += f[5]
    forces[i3, 0] += f[6]
    forces[i3, 1] += f[7]
    forces[i3, 2] += f[8]
    forces[i0, 0] -= f[9]
    forces[i0, 1] -= f[10]
    forces[i0, 2] -= f[11]


@njit(inline="always", **JIT)
def _tet_edge_lanes(x, tets, t):
    """The edge vectors p1 - p0, p2 - p0, p3 - p0 (3-tuples of vectors [m]) of tets
    ``t .. t+LANES-1``."""
    q0, q1, q2 = gather_rows(x, tets, t, 0)
    r1 = gather_rows(x, tets, t, 1)
    r2 = gather_rows(x, tets, t, 2)
    r3 = gather_rows(x, tets, t, 3)
    return ((vsub(r1[0], q0), vsub(r1[1], q1), vsub(r1[2], q2)),
            (vsub(r2[0], q0), vsub(r2[1], q1), vsub(r2[2], q2)),
            (vsub(r3[0], q0), vsub(r3[1], q1), vsub(r3[2], q2)))


@njit(**JIT)
def _volume_lanes(a, g1):
    """The volumes ``(a . g1) / 6`` [m^3] of the lanes' tets, ``a`` = p1 - p0, ``g1`` = 6
    dV/dp1, as :func:`tet_volume` computes them."""
    return vmul(vadd(vadd(vmul(a[0], g1[0]), vmul(a[1], g1[1])), vmul(a[2], g1[2])),
                vsplat(1.0 / 6.0))


@njit(**JIT)
def _cross_lanes(a, b):
    """The lane-wise cross product of two 3-tuples of vectors."""
    return (vsub(vmul(a[1], b[2]), vmul(a[2], b[1])), vsub(vmul(a[2], b[0]), vmul(a[0], b[2])),
            vsub(vmul(a[0], b[1]), vmul(a[1], b[0])))


@njit(inline="always", **JIT)
def tet_lanes(x, tets, rest_volumes, kv, v_lo, v_hi, arms, t):
    """Tets ``t .. t+LANES-1`` as lanes (:mod:`particle.lanes`), the scalar loop of
    :func:`add_volume_forces` lane-wise: returns (the 12 force vectors of
    :func:`add_tet_force` [N], the volumes [m^3], the bit mask of the lanes whose volume is
    outside ``(v_lo, v_hi]``); the arms (or None) advanced and stored. Inlined where it is called: as a
    function of its own, its 14 returned vectors go through memory (measured 1.4x slower).
    """
    a, b, c = _tet_edge_lanes(x, tets, t)
    g1 = _cross_lanes(b, c)
    g2 = _cross_lanes(c, a)
    g3 = _cross_lanes(a, b)
    v = _volume_lanes(a, g1)
    sixth = vsplat(1.0 / 6.0)
    inside = vlt_mask(vload(v_lo, t), v) & vle_mask(v, vload(v_hi, t))  # NaN: outside
    strain = vsub(vdiv(v, vload(rest_volumes, t)), vsplat(1.0))
    pressure = vmul(vload(kv, t), strain)
    if arms is not None:  # the outputs may alias the previous pressures and strains
        r, k, prev, strain_prev, out, strain_out = arms
        change = vsub(strain, vload(strain_prev, t))
        vstore(strain_out, t, strain)
        pressure = vadd(pressure, arm_pair_lanes(r, k, prev, out, t, change))
    s = vmul(vmul(pressure, vsplat(-1.0)), sixth)  # -P exactly, then / 6 as the scalar loop
    f = (vmul(s, g1[0]), vmul(s, g1[1]), vmul(s, g1[2]), vmul(s, g2[0]), vmul(s, g2[1]),
         vmul(s, g2[2]), vmul(s, g3[0]), vmul(s, g3[1]), vmul(s, g3[2]),
         vmul(s, vadd(vadd(g1[0], g2[0]), g3[0])), vmul(s, vadd(vadd(g1[1], g2[1]), g3[1])),
         vmul(s, vadd(vadd(g1[2], g2[2]), g3[2])))
    return f, v, ALL_LANES ^ inside


@njit(**JIT)
def first_volume_outside(x, tets, v_lo, v_hi):
    """The first tet whose volume at ``x`` is not in ``(v_lo, v_hi]`` (T,) [m^3] (-1: none):
    the range check of :func:`add_volume_forces` (its volumes, bit for bit) without the
    forces (a run's final state), :data:`~particle.lanes.LANES` tets at a time."""
    n = tets.shape[0]
    rest = n // LANES * LANES
    seen = 0  # the lanes outside, or-ed (no branch in the loop)
    for t in range(0, rest, LANES):
        a, b, c = _tet_edge_lanes(x, tets, t)
        v = _volume_lanes(a, _cross_lanes(b, c))
        seen |= ALL_LANES ^ (vlt_mask(vload(v_lo, t), v) & vle_mask(v, vload(v_hi, t)))
    for t in range(0 if seen != 0 else rest, n):  # which one: the same formula, scalar
        v = tet_volume(x, tets, t)
        if not (v > v_lo[t] and v <= v_hi[t]):
            return np.int64(t)
    return np.int64(-1)


@njit(**JIT)
def node_volume_force(x, node, node_tets, tets, rest_volumes, kv, arms, out):
    """out (3,) += the volume force [N] on particle ``node`` from its tets ``node_tets``;
    ``arms`` (or None) advanced one step into scratch (nothing stored)."""
    g = np.empty((4, 3))
    for k in range(node_tets.shape[0]):
        t = node_tets[k]
        v = _tet_gradient(x, tets, t, g)
        strain = v / rest_volumes[t] - 1.0
        s = -kv[t] * strain
        if arms is not None:
            p1, p2 = volume_arm_pressures(t, strain, arms)
            s -= p1 + p2
        for a in range(4):
            if tets[t, a] == node:
                out[0] += s * g[a, 0]
                out[1] += s * g[a, 1]
                out[2] += s * g[a, 2]


@njit(**JIT)
def _add_tet_block(data, slots, k1, ga, gb, w):
    """data += one (a, b) block of a tet's volume tangent, ``k1 g_a g_b^T + [w]_x`` [N/m].

    ``slots`` (3, 3): the block's data indices (``tet_slots[t, a, b]``, -1 skipped);
    ``k1 = kv/V0`` [Pa/m^3 = N/m^5], ``ga``/``gb`` dV/dp_a, dV/dp_b (3-tuples [m^2]),
    ``w`` (3-tuple [N/m]) with ``[w]_x y = w x y``. Unrolled on purpose: loops over
    (p, q) with a skew-matrix lookup measured 2x slower on the liver punch (0.27 against
    0.12 ms per assembly). The block comes as a view, not as ``(t, a, b)``: numba
    compiles a call with literal integer arguments once per value, and the 16 literal
    (a, b) pairs took 3.9 s of compilation in every fresh process.
    """
    w0, w1, w2 = w[0], w[1], w[2]
    s = slots[0, 0]
    if s >= 0:
        data[s] += k1 * ga[0] * gb[0]
    s = slots[0, 1]
    if s >= 0:
        data[s] += k1 * ga[0] * gb[1] - w2
    s = slots[0, 2]
    if s >= 0:
        data[s] += k1 * ga[0] * gb[2] + w1
    s = slots[1, 0]
    if s >= 0:
        data[s] += k1 * ga[1] * gb[0] + w2
    s = slots[1, 1]
    if s >= 0:
        data[s] += k1 * ga[1] * gb[1]
    s = slots[1, 2]
    if s >= 0:
        data[s] += k1 * ga[1] * gb[2] - w0
    s = slots[2, 0]
    if s >= 0:
        data[s] += k1 * ga[2] * gb[0] - w1
    s = slots[2, 1]
    if s >= 0:
        data[s] += k1 * ga[2] * gb[1] + w0
    s = slots[2, 2]
    if s >= 0:
        data[s] += k1 * ga[2] * gb[2]


@njit(**JIT)
def _scaled_difference(k, p, q):
    """The 3-tuple ``k (p - q)`` of two 3-tuples."""
    return k * (p[0] - q[0]), k * (p[1] - q[1]), k * (p[2] - q[2])


@njit(**JIT)
def add_volume_tangent(x, tets, rest_volumes, kv, tet_slots, data, arms):
    """data += the volume tangent -d(forces)/dx [N/m] through ``tet_slots`` (T, 4, 4, 3, 3).

    ``x`` (N, 3) [m], ``tets`` (T, 4), ``rest_volumes`` (T,) [m^3], ``kv`` (T,) [Pa],
    ``data`` (nnz,) [N/m], ``arms`` None (elastic, or the arms relaxed) or (the arms' step
    coefficients ``c_1 + c_2`` (T,) [Pa], their summed pressures at ``x`` (T,) [Pa]).
    ``tet_slots[t, a, b, p, q]`` is the CSC data index of entry
    (3 tets[t,a] + p, 3 tets[t,b] + q), -1 where a fixed particle is involved. Per tet
    the block (a, b) is ``k/V0 g_a g_b^T + P d^2V/dp_a dp_b`` with ``k = kv (+ c_1 +
    c_2)`` and ``P = kv (V/V0 - 1) (+ P_1 + P_2)``, in closed
    form: V is linear in each vertex, so ``d^2V/dp_a dp_a = 0``, and for (a, b, c, d) an
    even permutation of (0, 1, 2, 3), ``d^2V/dp_a dp_b = [p_c - p_d]_x / 6`` (``[w]_x y
    = w x y``) and ``d^2V/dp_b dp_a = [p_d - p_c]_x / 6``, its transpose (exactly: the
    differences are antisymmetric in floating point too). Written with scalars (as
    :func:`add_volume_forces`): 4.7x faster on the punch liver (885 tets) than the former
    kernel, which took d^2V from 12 displaced gradients per tet as the plain-numpy twin
    :func:`add_volume_tangent_numpy` still does.
    """
    sixth = 1.0 / 6.0
    for t in range(tets.shape[0]):
        g0, g1, g2, g3, v = _tet_gradient_tuples(x, tets[t, 0], tets[t, 1], tets[t, 2],
                                                 tets[t, 3])
        if arms is None:
            k1 = kv[t] / rest_volumes[t]
            k2 = kv[t] * (v / rest_volumes[t] - 1.0) * sixth
        else:
            k1 = (kv[t] + arms[0][t]) / rest_volumes[t]
            k2 = (kv[t] * (v / rest_volumes[t] - 1.0) + arms[1][t]) * sixth
        add_tet_tangent(x, tets, t, k1, k2, (g0, g1, g2, g3), tet_slots, data)


@njit(**JIT)
def add_tet_tangent(x, tets, t, k1, k2, grads, tet_slots, data):
    """data += tet t's tangent blocks ``k1 g_a g_b^T + k2 [p_c - p_d]_x`` [N/m] (the
    closed form of :func:`add_volume_tangent`: ``k1`` = k/V0 [N/m^5], ``k2`` = P/6 [Pa],
    ``grads`` its dV/dp_a, four 3-tuples [m^2])."""
    zero = (0.0, 0.0, 0.0)
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    p0 = (x[i0, 0], x[i0, 1], x[i0, 2])
    p1 = (x[i1, 0], x[i1, 1], x[i1, 2])
    p2 = (x[i2, 0], x[i2, 1], x[i2, 2])
    p3 = (x[i3, 0], x[i3, 1], x[i3, 2])
    g0, g1, g2, g3 = grads
    # kv (V/V0 - 1) d^2V/dp_a dp_b = [w_ab]_x, w_ab = k2 (p_c - p_d), (a, b, c, d) even
    w01 = _scaled_difference(k2, p2, p3)  # (0, 1, 2, 3)
    w02 = _scaled_difference(k2, p3, p1)  # (0, 2, 3, 1)
    w03 = _scaled_difference(k2, p1, p2)  # (0, 3, 1, 2)
    w12 = _scaled_difference(k2, p0, p3)  # (1, 2, 0, 3)
    w13 = _scaled_difference(k2, p2, p0)  # (1, 3, 2, 0)
    w23 = _scaled_difference(k2, p0, p1)  # (2, 3, 0, 1)
    w10 = _scaled_difference(k2, p3, p2)  # w_ba = -w_ab
    w20 = _scaled_difference(k2, p1, p3)
    w30 = _scaled_difference(k2, p2, p1)
    w21 = _scaled_difference(k2, p3, p0)
    w31 = _scaled_difference(k2, p0, p2)
    w32 = _scaled_difference(k2, p1, p0)
    # in storage order (a, b)
    _add_tet_block(data, tet_slots[t, 0, 0], k1, g0, g0, zero)
    _add_tet_block(data, tet_slots[t, 0, 1], k1, g0, g1, w01)
    _add_tet_block(data, tet_slots[t, 0, 2], k1, g0, g2, w02)
    _add_tet_block(data, tet_slots[t, 0, 3], k1, g0, g3, w03)
    _add_tet_block(data, tet_slots[t, 1, 0], k1, g1, g0, w10)
    _add_tet_block(data, tet_slots[t, 1, 1], k1, g1, g1, zero)
    _add_tet_block(data, tet_slots[t, 1, 2], k1, g1, g2, w12)
    _add_tet_block(data, tet_slots[t, 1, 3], k1, g1, g3, w13)
    _add_tet_block(data, tet_slots[t, 2, 0], k1, g2, g0, w20)
    _add_tet_block(data, tet_slots[t, 2, 1], k1, g2, g1, w21)
    _add_tet_block(data, tet_slots[t, 2, 2], k1, g2, g2, zero)
    _add_tet_block(data, tet_slots[t, 2, 3], k1, g2, g3, w23)
    _add_tet_block(data, tet_slots[t, 3, 0], k1, g3, g0, w30)
    _add_tet_block(data, tet_slots[t, 3, 1], k1, g3, g1, w31)
    _add_tet_block(data, tet_slots[t, 3, 2], k1, g3, g2, w32)
    _add_tet_block(data, tet_slots[t, 3, 3], k1, g3, g3, zero)


def tet_edge_connectors(tets: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(T, 6) connector id of each tet edge (order :data:`TET_PAIRS`).

    Raises :class:`MeshError` naming the first tet with an edge that is no
    connector (the volume term's tangent pattern and stability bound use them).
    """
    n = int(max(edges.max(), tets.max())) + 1
    key = np.sort(edges, axis=1)
    keys = key[:, 0] * n + key[:, 1]
    order = np.argsort(keys)
    pairs = np.sort(tets[:, TET_PAIRS], axis=2)  # (T, 6, 2)
    wanted = pairs[..., 0] * n + pairs[..., 1]
    pos = np.clip(np.searchsorted(keys[order], wanted), 0, len(keys) - 1)
    found = keys[order][pos] == wanted
    if not found.all():
        t = int(np.nonzero(~found.all(axis=1))[0][0])
        raise MeshError(f"{tet_name(t, tets)}: an edge of the tet is not a connector; the volume "
                        "term needs every tet edge to be one")
    return order[pos]


def node_volume_stiffness(model) -> np.ndarray:
    """(N,) diagonal stiffness scale of the volume term at rest [N/m]: sum over a
    particle's tets of ``k/V0 |dV/dp|^2`` with ``k`` the instantaneous stiffness ``kv (+
    kv1 + kv2)`` (for the divergence bound's work estimate; for the nodal term
    :func:`particle.nodal_volume.tet_moduli`'s, which bound it)."""
    from particle.nodal_volume import tet_moduli
    g = volume_gradients_numpy(model.rest_positions, model.tets)
    per = (tet_moduli(model)[:, None] / model.rest_volumes[:, None]
           * np.sum(g * g, axis=2))
    return np.bincount(model.tets.ravel(), per.ravel(), model.n_particles)


def tet_slots(tets: np.ndarray, node_dof: np.ndarray, indptr: np.ndarray,
              indices: np.ndarray) -> np.ndarray:
    """(T, 4, 4, 3, 3) CSC data index of each tet block entry, -1 where a fixed particle is involved.

    The pattern (``indptr``/``indices``, dofs ``node_dof``) must contain every
    pair of a tet's vertices (true when the tet edges are connectors).
    """
    n = len(indptr) - 1
    r0 = node_dof[tets][:, :, None, None, None] + np.arange(3)[:, None]  # (T, 4, 1, 3, 1)
    c0 = node_dof[tets][:, None, :, None, None] + np.arange(3)[None, :]  # (T, 1, 4, 1, 3)
    rows, cols = np.broadcast_arrays(r0, c0)
    valid = (node_dof[tets][:, :, None] >= 0) & (node_dof[tets][:, None, :] >= 0)
    valid = np.broadcast_to(valid[..., None, None], rows.shape)
    col_of = np.repeat(np.arange(n), np.diff(indptr))
    keys = col_of.astype(np.int64) * n + indices
    want = cols[valid].astype(np.int64) * n + rows[valid]
    pos = np.searchsorted(keys, want)  # keys are sorted: CSC with sorted row indices
    if not np.array_equal(keys[np.clip(pos, 0, len(keys) - 1)], want):
        raise MeshError("the tangent pattern lacks a pair of tet vertices; every tet edge must "
                        "be a connector")
    slots = np.full(rows.shape, -1, dtype=np.int64)
    slots[valid] = pos
    return slots


def check_kv(kv: np.ndarray, tets: np.ndarray | None = None, name: str = "kv") -> None:
    """Raise :class:`~forcecal.errors.ParameterError` naming the first tet whose ``name``
    (``kv`` or a volume arm's ``kv_i``, ``bv_i``) is <= 0 or non-finite."""
    bad = np.nonzero(~(np.isfinite(kv) & (kv > 0.0)))[0]
    if len(bad):
        t = int(bad[0])
        what = "volume stiffness" if name == "kv" else "volume arm"
        unit = "Pa s" if name.startswith("bv") else "Pa"
        raise ParameterError(f"{tet_name(t, tets)}: {what} {name} = {kv[t]} {unit} must be a "
                             "finite number > 0")


def network_bulk_modulus(mesh_or_model, K0: float) -> float:
    """Bulk modulus [Pa] of a uniform spring network of stiffness ``K0`` [N/m] under uniform dilation.

    Every connector stretches by ``eps L``: energy ``sum K0 (eps L)^2/2 = 9/2 kappa
    eps^2 V_total``, so ``kappa = K0 sum L^2 / (9 V_total)``.
    """
    lengths = getattr(mesh_or_model, "rest_lengths", None)
    if lengths is None:
        lengths = mesh_or_model.edge_lengths
        volume = float(np.abs(mesh_or_model.signed_volumes).sum())
    else:
        volume = float(mesh_or_model.rest_volumes.sum())
    return float(K0 * np.sum(np.asarray(lengths) ** 2) / (9.0 * volume))


__all__ = ["add_tet_tangent", "add_volume_forces", "add_volume_tangent",
           "add_volume_tangent_numpy", "check_kv",
           "network_bulk_modulus", "node_volume_force", "pressure_forces_numpy",
           "signed_volumes", "tet_edge_connectors",
           "tet_name", "tet_slots", "volume_arm_energy", "volume_arm_pressures",
           "volume_arm_pressures_numpy", "volume_arm_step", "volume_frequency_bound",
           "volume_ratio_range", "node_volume_stiffness", "node_volume_stiffness_bound",
           "volume_energy", "volume_forces_numpy", "volume_hessian_numpy",
           "volume_kv_sensitivity_numpy", "volume_strains"]
