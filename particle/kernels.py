"""Compiled (numba) force kernels: connector forces, the force terms composed, tangent assembly.

Optional terms of the connector pass are passed either as arrays or as ``None``. Numba
compiles one specialisation per argument-type combination and prunes ``if arg is None``
branches at compile time, so a run without Maxwell arms or with linear springs (a = b = 0)
executes a connector loop without those terms at all; the choice is made once per run by
:class:`particle.integrator.Terms`, never inside the inner loop. The node loads (gravity,
damping) are switched by flags instead, tested once per step outside their node loops:
each specialisation costs seconds of compilation in every fresh process, and a test per
step costs nothing measurable. The static Newton path passes zero arrays instead
(:func:`particle.statics.kernel_terms`): there a specialisation per combination costs
more compilation in every fresh calibration worker than the skipped terms save. The
explicit step loop that calls these kernels (serial and multi-threaded) is
:mod:`particle.step_kernels`.

Without a tension output (every explicit step) :func:`add_connector_forces` takes the
connectors four at a time as SIMD lanes (:mod:`particle.lanes`, :func:`connector_lanes`),
bit for bit the scalar loop it keeps for the remainder and the static path (measured in
:mod:`particle.step_kernels`' docstring).

Index arrays (connector ends, node lists) may be passed as unsigned views
(:func:`index_view`): numba then drops the wrap-around handling of negative
indices from every gathered index. Measured on the 12k-connector liver: one
force evaluation 61 -> 50 us, results bitwise identical.

The optional per-tet volume term (:mod:`particle.volume`) enters the same
way: ``volume`` None compiles it out of :func:`net_forces` and the loop; with
``volume_nodes`` its nodal form (:mod:`particle.nodal_kernels`) replaces it.

The force terms are small functions composed in :func:`net_forces`; the
plain-numpy twin used as the reference in tests is :mod:`particle.reference_numpy`.

Where another force term plugs in: a function ``add_<term>_forces(x, ...,
forces)`` that adds into ``forces`` (N, 3) [N], called in :func:`net_forces`
after :func:`internal_forces` (the serial path, which every haptic and dynamic
run uses by default) and, for the threaded path, in
:func:`particle.step_kernels.explicit_step` (as the volume term is); its term
selector joins :class:`particle.integrator.Terms`, its arrays one of the argument groups
of :func:`particle.step_kernels.run_verlet` (as ``connector_terms`` and ``loads`` are; no
group of more than four arrays, :mod:`particle.dispatch`). Mass scaling needs its stiffness in
:func:`particle.integrator.critical_time_step` and, to put the added mass where
the term stiffens the model, a per-particle bound in
:func:`particle.mass_scaling.stiffness_weights` (as the volume term has).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types
from numba.extending import overload

from particle.lanes import (ALL_LANES, LANES, arm_pair_lanes, first_lane, gather_rows, vadd,
                            vdiv, vle_mask, vload, vmul, vsqrt, vstore, vsub)
from particle.nodal_kernels import add_nodal_volume_forces
from particle.volume import add_volume_forces

# numpy's error model: a degenerate input gives inf/NaN, which the divergence check turns
# into a StabilityError, instead of an exception raised from inside compiled code
JIT = dict(cache=True, error_model="numpy")
#: an overload's options (compiled into its cached caller: no cache of its own)
OVERLOAD_JIT = dict(error_model="numpy")



def index_view(ids: np.ndarray) -> np.ndarray:
    """The same non-negative int64 ids as a zero-copy uint64 view, for the kernels' gathers."""
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    return ids.view(np.uint64)




@njit(**JIT)
def connector_vector(x, edges, e):
    """Ends i, j, vector x_j - x_i (3 floats) [m] and length [m] of connector e."""
    i = edges[e, 0]
    j = edges[e, 1]
    d0 = x[j, 0] - x[i, 0]
    d1 = x[j, 1] - x[i, 1]
    d2 = x[j, 2] - x[i, 2]
    return i, j, d0, d1, d2, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@njit(**JIT)
def spring_tension(e, dx, strain, K0, a, b):
    """Elastic spring tension K(eps) dx [N] of connector e; a, b None = linear spring."""
    if a is None:
        return K0[e] * dx
    return (K0[e] + a[e] * strain + b[e] * strain * strain) * dx


@njit(**JIT)
def spring_tangent(e, strain, K0, a, b):
    """d(K(eps) dx)/d(dx) = K0 + 2 a eps + 3 b eps^2 [N/m] of connector e."""
    if a is None:
        return K0[e]
    return K0[e] + 2.0 * a[e] * strain + 3.0 * b[e] * strain * strain


@njit(**JIT)
def arm_forces(e, dx, arm_r, arm_c, arm_prev, dx_prev):
    """The two Maxwell arm forces [N] of connector e after one recursion step.

    ``F^t = r F^{t-1} + c (dx^t - dx^{t-1})``.
    """
    ddx = dx - dx_prev[e]
    return (arm_r[e, 0] * arm_prev[e, 0] + arm_c[e, 0] * ddx,
            arm_r[e, 1] * arm_prev[e, 1] + arm_c[e, 1] * ddx)


@njit(**JIT)
def internal_forces(x, edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev,
                    forces, tension, arm_out, dx_out, dx_lo=None, dx_hi=None):
    """Connector forces on every particle (N, 3) [N], overwriting ``forces``.

    Also writes each connector's tension (E,) [N] (unless ``tension`` is None),
    new arm forces (E, 2) [N] (arms skipped if ``arm_r`` is None) and
    elongation (E,) [m]; ``arm_out``/``dx_out`` may alias ``arm_prev``/``dx_prev``
    to commit the step in place (dynamics) or be scratch arrays (Newton
    iterations, which must not commit). Returns the first connector whose
    elongation is outside ``[dx_lo, dx_hi]`` (E,) [m], -1 if none or if
    ``dx_lo`` is None (the explicit runs' strain-range check, done here where
    each elongation is at hand rather than in a second pass over the connectors).
    """
    forces[:] = 0.0
    return add_connector_forces(x, edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev,
                                dx_prev, forces, tension, arm_out, dx_out, dx_lo, dx_hi, 0,
                                edges.shape[0])


@njit(**JIT)
def add_connector_forces(x, edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev,
                         forces, tension, arm_out, dx_out, dx_lo, dx_hi, first, stop):
    """:func:`internal_forces` of the connectors ``first .. stop-1``, added to ``forces``.

    Returns the first of them outside ``[dx_lo, dx_hi]``, -1 if none (or ``dx_lo`` None).
    Without ``tension`` (the explicit steps) the connectors go :data:`LANES` at a time
    through :func:`connector_lanes` and :func:`add_lane_forces`, the remainder one by one;
    each connector's force and each particle's sum are the scalar loop's, bit for bit.
    """
    outside = -1
    rest = first
    if tension is None and stop - first >= LANES:
        rest = first + (stop - first) // LANES * LANES
        i = edges[first, 0]
        held = (i, forces[i, 0], forces[i, 1], forces[i, 2])
        ahead = connector_lengths(x, edges, first)
        for e in range(first, rest, LANES):
            current = ahead
            # the next connectors' lengths first: their gathers and square roots overlap
            # this batch's divisions and scatter (the last batch recomputes its own)
            ahead = connector_lengths(x, edges, e + LANES if e + LANES < rest else e)
            s0, s1, s2, lanes_outside = connector_lanes(
                current, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev, arm_out,
                dx_out, dx_lo, dx_hi, e)
            if lanes_outside != 0 and outside < 0:
                outside = np.int64(e) + first_lane(lanes_outside)
            held = add_lane_forces(forces, edges, e, s0, s1, s2, held)
        i, f0, f1, f2 = held
        forces[i, 0] = f0
        forces[i, 1] = f1
        forces[i, 2] = f2
    for e in range(rest, stop):
        i, j, d0, d1, d2, length = connector_vector(x, edges, e)
        dx = length - rest_lengths[e]
        if dx_lo is not None:
            if outside < 0 and not dx_lo[e] <= dx <= dx_hi[e]:
                outside = np.int64(e)  # e may be unsigned (blocks of connectors)
        f = spring_tension(e, dx, dx / rest_lengths[e], K0, a, b)
        if arm_r is not None:
            f1, f2 = arm_forces(e, dx, arm_r, arm_c, arm_prev, dx_prev)
            arm_out[e, 0] = f1  # may alias arm_prev: this connector's old value is already used
            arm_out[e, 1] = f2
            f += f1 + f2
        if tension is not None:
            tension[e] = f
        dx_out[e] = dx
        s = f / length
        forces[i, 0] += s * d0
        forces[i, 1] += s * d1
        forces[i, 2] += s * d2
        forces[j, 0] -= s * d0
        forces[j, 1] -= s * d1
        forces[j, 2] -= s * d2
    return outside


@njit(**JIT)
def connector_lengths(x, edges, e):
    """(x_j - x_i as three vectors [m], their lengths [m]) of connectors ``e .. e+LANES-1``
    (:mod:`particle.lanes`), as :func:`connector_vector` computes them."""
    xi0, xi1, xi2 = gather_rows(x, edges, e, 0)
    xj0, xj1, xj2 = gather_rows(x, edges, e, 1)
    d0 = vsub(xj0, xi0)
    d1 = vsub(xj1, xi1)
    d2 = vsub(xj2, xi2)
    return d0, d1, d2, vsqrt(vadd(vadd(vmul(d0, d0), vmul(d1, d1)), vmul(d2, d2)))


@njit(**JIT)
def connector_lanes(lengths, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev, dx_prev, arm_out,
                    dx_out, dx_lo, dx_hi, e):
    """Connectors ``e .. e+LANES-1`` as lanes (:mod:`particle.lanes`) from their
    :func:`connector_lengths`: the scalar loop of :func:`add_connector_forces` lane-wise, the
    same operations in the same order.

    Stores their elongations (and arm forces); returns the three vectors of the force
    ``s (x_j - x_i)`` [N] they add to particle i (and subtract from j), and a bit mask of
    the lanes outside ``[dx_lo, dx_hi]`` (0 when ``dx_lo`` is None).
    """
    d0, d1, d2, length = lengths
    rest = vload(rest_lengths, e)
    dx = vsub(length, rest)
    outside = 0
    if dx_lo is not None:  # NaN: outside
        outside = ALL_LANES ^ (vle_mask(vload(dx_lo, e), dx) & vle_mask(dx, vload(dx_hi, e)))
    if a is None:
        f = vmul(vload(K0, e), dx)
    else:
        strain = vdiv(dx, rest)
        f = vmul(vadd(vadd(vload(K0, e), vmul(vload(a, e), strain)),
                      vmul(vmul(vload(b, e), strain), strain)), dx)
    if arm_r is not None:  # arm_out may alias arm_prev
        f = vadd(f, arm_pair_lanes(arm_r, arm_c, arm_prev, arm_out, e,
                                   vsub(dx, vload(dx_prev, e))))
    vstore(dx_out, e, dx)
    s = vdiv(f, length)
    return vmul(s, d0), vmul(s, d1), vmul(s, d2), outside


@njit(**JIT)
def add_lane_forces(forces, edges, e, s0, s1, s2, held):
    """forces[i] += s, forces[j] -= s for connectors ``e .. e+LANES-1`` in order, the lanes'
    forces ``s`` (:func:`connector_lanes`).

    Particle i's sum is carried in ``held`` = (particle, its force (3 floats) [N]) while
    consecutive connectors share it (the connectors are sorted by their first end: five
    in six do on the meshes here), and written back when it changes; returns the new
    ``held``. No connector updates its own first end as j, so the carried sum sees the
    same additions in the same order as the force array would.
    """
    for k in range(LANES):
        i = edges[e + k, 0]
        j = edges[e + k, 1]
        node, f0, f1, f2 = held
        if i != node:
            forces[node, 0] = f0
            forces[node, 1] = f1
            forces[node, 2] = f2
            f0, f1, f2 = forces[i, 0], forces[i, 1], forces[i, 2]
        a0, a1, a2 = s0[k], s1[k], s2[k]
        held = (i, f0 + a0, f1 + a1, f2 + a2)
        forces[j, 0] -= a0
        forces[j, 1] -= a1
        forces[j, 2] -= a2
    return held


@njit(**JIT)
def node_force(x, node, node_edges, edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_prev,
               dx_prev, out):
    """Connector force on one particle [N] into ``out`` (3,), from its connectors ``node_edges``.

    Arm forces (skipped if ``arm_r`` is None) are advanced by the recursion but
    not stored (the state is unchanged).
    """
    out[:] = 0.0
    for k in range(node_edges.shape[0]):
        e = node_edges[k]
        i, j, d0, d1, d2, length = connector_vector(x, edges, e)
        dx = length - rest_lengths[e]
        f = spring_tension(e, dx, dx / rest_lengths[e], K0, a, b)
        if arm_r is not None:
            f1, f2 = arm_forces(e, dx, arm_r, arm_c, arm_prev, dx_prev)
            f += f1 + f2
        s = f / length
        if node == j:
            s = -s
        out[0] += s * d0
        out[1] += s * d1
        out[2] += s * d2


@njit(**JIT)
def add_gravity(forces, masses, gravity, nodes):
    """forces[n] += m_n g for the given nodes [N]."""
    for n in nodes:
        for c in range(3):
            forces[n, c] += masses[n] * gravity[c]


@njit(**JIT)
def add_damping(forces, masses, x, x_prev, rate, nodes):
    """Mass-proportional viscous damping: forces[n] -= m_n gamma v_n, v from the last step.

    ``rate`` is gamma/dt [1/s^2]; v = (x - x_prev)/dt is the backward difference.
    """
    for n in nodes:
        for c in range(3):
            forces[n, c] -= masses[n] * rate * (x[n, c] - x_prev[n, c])


@njit(**JIT)
def add_loads(forces, masses, x, x_prev, loads, nodes):
    """The node loads of one explicit step for ``nodes``: ``loads`` = (gravity (3 floats)
    [m/s^2], damping rate gamma/dt [1/s^2], with gravity, with damping)
    (:func:`particle.step_kernels.load_group`): :func:`add_gravity` then
    :func:`add_damping`, each only if its flag is set."""
    gravity, damping_rate, with_gravity, with_damping = loads
    if with_gravity:
        add_gravity(forces, masses, gravity, nodes)
    if with_damping:
        add_damping(forces, masses, x, x_prev, damping_rate, nodes)


def add_volume_pass(x, forces, volume, volume_arms, volume_nodes):
    """In compiled code: forces += the volume term's forces [N] (``volume`` = (tets, rest
    volumes, kv, v_lo, v_hi, volumes out), per tet when ``volume_nodes`` is None, else nodal
    with that scratch: :func:`net_forces`); returns the first tet outside its volume range,
    -1 if none.

    The element is chosen by the type of ``volume_nodes`` when the caller is compiled (an
    overload), not by a branch: numba prunes ``if volume_nodes is None`` only where it is
    None, so a nodal run would otherwise also compile the per-tet pass it never calls
    (~6 s per specialisation on an empty cache)."""
    raise NotImplementedError("add_volume_pass is for compiled code")


@overload(add_volume_pass, jit_options=OVERLOAD_JIT)
def _add_volume_pass(x, forces, volume, volume_arms, volume_nodes):
    if isinstance(volume_nodes, types.NoneType):
        def per_tet(x, forces, volume, volume_arms, volume_nodes):
            bad, _ = add_volume_forces(x, volume[0], volume[1], volume[2], volume[3],
                                       volume[4], forces, volume_arms, volume[5])
            return bad
        return per_tet

    def nodal(x, forces, volume, volume_arms, volume_nodes):
        bad, _ = add_nodal_volume_forces(x, volume[0], volume[1], volume[2], volume[3],
                                         volume[4], forces, volume_arms, volume[5],
                                         volume_nodes)
        return bad
    return nodal


@njit(**JIT)
def net_forces(state, springs, particles, loads, forces, dx_lo, dx_hi, volume, volume_arms,
               volume_nodes):
    """All force terms of one explicit step, composed; commits the arm recursions in place.

    ``state``, ``springs``, ``particles``, ``loads``: the explicit loop's argument groups
    (:func:`particle.step_kernels.run_verlet`). ``volume`` = (tets (T, 4), rest_volumes
    (T,), kv (T,), v_lo (T,), v_hi (T,), the volumes out (T,)) adds the volume term
    (:func:`particle.volume.add_volume_forces`), None compiles it out; ``volume_arms`` its
    arms (the kernels' tuple, outputs aliasing the state: :mod:`particle.volume`), None:
    elastic; ``volume_nodes`` None: the per-tet term, else the nodal term's scratch (its
    rest volumes and kv then the particles',
    :func:`particle.nodal_kernels.add_nodal_volume_forces`).
    Returns (the first connector outside ``[dx_lo, dx_hi]`` (see
    :func:`internal_forces`), the first tet whose volume is outside ``(v_lo, v_hi]``), -1
    for none.
    """
    x, x_prev, arm_force, dx_prev = state
    edges, rest_lengths, K0, a, b, arm_r, arm_c = springs
    masses, _, active = particles
    outside = internal_forces(x, edges, rest_lengths, K0, a, b, arm_r, arm_c, arm_force,
                              dx_prev, forces, None, arm_force, dx_prev, dx_lo, dx_hi)
    bad = -1
    if volume is not None:
        bad = add_volume_pass(x, forces, volume, volume_arms, volume_nodes)
    add_loads(forces, masses, x, x_prev, loads, active)
    return outside, bad

@njit(**JIT)
def assemble_tangent(x, edges, rest_lengths, K0, a, b, arm_stiffness, tension, slots, data):
    """Tangent stiffness -d(forces)/dx into CSC ``data`` through precomputed ``slots``.

    Per connector the 3x3 block is ``s e e^T + (F/l)(I - e e^T)`` with the
    axial tangent ``s = K0 + 2 a eps + 3 b eps^2 (+ sum of arm coefficients
    c_i)`` and the geometric term F/l (F = total tension). ``slots`` (E, 4, 3, 3)
    gives the data index of blocks (i,i), (j,j), (i,j), (j,i), -1 for dofs not
    in the matrix.
    """
    data[:] = 0.0
    blk = np.empty((3, 3))
    for e in range(edges.shape[0]):
        i, j, d0, d1, d2, length = connector_vector(x, edges, e)
        unit = (d0 / length, d1 / length, d2 / length)
        s = spring_tangent(e, (length - rest_lengths[e]) / rest_lengths[e], K0, a, b)
        if arm_stiffness is not None:
            s += arm_stiffness[e]
        g = tension[e] / length
        for p in range(3):
            for q in range(3):
                blk[p, q] = (s - g) * unit[p] * unit[q]
            blk[p, p] += g
        for p in range(3):
            for q in range(3):
                v = blk[p, q]
                for k, sign in ((0, 1.0), (1, 1.0), (2, -1.0), (3, -1.0)):
                    idx = slots[e, k, p, q]
                    if idx >= 0:
                        data[idx] += sign * v
