"""Compiled (numba) explicit step loop: the Verlet step, its checks, the multi-threaded step.

:func:`run_verlet` advances a state by many steps in one call (the haptic loop's
one kernel dispatch per device period); each step is :func:`explicit_step`:
:func:`particle.kernels.net_forces` then :func:`advance_positions`, with the
divergence, strain-range and volume-range checks riding on those passes.

The step is serial by default (the reference). An opt-in multi-threaded step
(``blocks``, :func:`explicit_step`) splits the connector pass into contiguous blocks, one
per thread, each scattering into its own force buffer (no race, no node -> connector
gather pass), then sums the buffers and advances the positions in blocks of nodes: two
numba parallel regions per step. What it costs is the particles both blocks touch, whose
positions and force-buffer rows the threads exchange every step (cache-line transfers, not
arithmetic): renumbering the particles along the longest axis
(:meth:`particle.model.Model.renumbered`) cuts them about 5-fold on the 12k-connector liver,
where two threads then save about a quarter of a step. A parallel region also waits for a
busy core, up to a scheduler time slice, and costs microseconds even when idle, so on small
meshes (the 1400-connector liver) the serial loop is faster and stays the default. A
scatter-free gather over a node -> connector incidence was slower than the serial scatter.

The connector and tet passes go :data:`~particle.lanes.LANES` items at a time as SIMD
lanes (:mod:`particle.lanes`: the same IEEE operations per item, bit for bit the scalar
loops): the connectors in two stages (the next batch's gathers and square roots issued
before this batch's divisions and scatter) with particle i's sum carried in registers along
its run of connectors, the tets in one stage. Measured on the 12k-connector liver, one core: the
connector pass 91 -> 52 us, the tet pass 108 -> 68 us (elastic), 142 -> 79 us (with arms).
Measured with the lanes and not kept: eight lanes (AVX-512; 1.4x slower than four), two lanes
(1.2x slower), the AVX-512 gather instruction (slower than scalar loads into lanes), a
third stage (divisions a batch ahead of the scatter: slower), gathers two batches ahead
(the same), forces padded to (N, 4) with one vector load and store per particle (the
same), positions padded to (N, 4) and transposed (the same), the arms' pairs used
interleaved (the same), the tets in two stages (3 % faster elastic, 7 % slower with arms),
a tet's range check as a branch in the loop (30 % slower than or-ing the lane masks),
the connector pass in float32 (positions, connector data, arms and forces) with eight lanes
(AVX2, its helpers inlined): 56 -> 47 us on the 12k-connector liver, 1.2x as fast as the
float64 pass, below the 1.3x a float32 variant had to gain to be worth its error (not
inlined: 0.55x; sixteen lanes: 0.6x).
Measured on the scalar loop before the lanes and not kept (each bitwise or round-off
equal): connector data in float32; the sqrt and the division in separate vectorised loops;
particle i's running sum in registers (it pays only once the rest is lanes); float32
positions and arm state; a two-stage software pipeline (7 % faster alone, nothing in a
haptic call); chunks of 256 connectors in three loops (1.6x slower: the scratch traffic);
structure of arrays for the arms and split connector ends; positions and forces in one
(N, 8) buffer; flat arrays with unsigned indices (half the instructions, the same time);
interleaving two halves of the connector list. The passes are neither cache nor memory
bound (the same ns per connector from 1,000 to 12,062 connectors); they appear bound by
the latency of each batch's chain (gathers, square root, division) over the out-of-order
window. What halves the cost of a device period is one substep instead of two: mass
scaling (:mod:`particle.mass_scaling`; the inertia enters only through ``inv_masses``, so
no kernel changes), measured with its error in ``runs/bench/BENCH.md``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

from particle.dispatch import in_place, joined
from particle.kernels import (JIT, OVERLOAD_JIT, add_connector_forces, add_loads,
                              add_volume_pass, net_forces, node_force)
from particle.nodal_kernels import nodal_node_volume_force
from particle.lanes import ALL_LANES, LANES, all_inside, vadd, vle_mask, vload, vmax, vsplat, vsub
from particle.volume import first_volume_outside, node_volume_force

# status codes of run_verlet
OK = 0
NONFINITE = 1
ENERGY = 2
STRAIN = 3
VOLUME = 4
# the final state of a run (after its last step) outside the checked range: the run's result
# is refused, not handed back
STRAIN_END = 5
VOLUME_END = 6


@njit(**JIT)
def advance_positions(x, x_prev, forces, inv_masses, nodes, scale, check, masses):
    """Position update ``x^{n+1} = 2 x^n - x^{n-1} + scale f^n/m`` of ``nodes``.

    Returns ``sum m |x^{n+1} - x^n|^2`` [kg m^2] over ``nodes`` if ``check``
    (0 otherwise): the kinetic energy times ``2 dt^2``, accumulated in the same
    pass (the values are at hand) for the divergence check; a non-finite
    position makes it non-finite.
    """
    energy = 0.0
    for n in nodes:
        v2 = 0.0
        for c in range(3):
            new = 2.0 * x[n, c] - x_prev[n, c] + scale * forces[n, c] * inv_masses[n]
            if check:
                dv = new - x[n, c]
                v2 += dv * dv
            x_prev[n, c] = x[n, c]
            x[n, c] = new
        if check:
            energy += masses[n] * v2
    return energy


@njit(**JIT)
def explicit_step(state, springs, particles, loads, forces, blocks, dx_lo, dx_hi, scale, check,
                  dt, energy_bound, status, volume, volume_arms, volume_nodes):
    """One explicit step in place: :func:`net_forces` at ``x``, then :func:`advance_positions`.

    ``state``, ``springs``, ``particles``, ``loads``: :func:`run_verlet`'s argument groups.
    If ``check``, the divergence check of the new positions: the kinetic
    energy ``sum m |x^{n+1} - x^n|^2 / (2 dt^2)`` [J] must not exceed
    ``energy_bound``, else ``status`` is set (:func:`divergent_node`, the only
    part that looks at the nodes again). Returns (the first connector outside
    ``[dx_lo, dx_hi]`` (-1: none, or ``dx_lo`` None), the first tet whose volume
    at ``x`` is outside its range (-1: none or no volume term)). ``blocks`` None runs the
    serial passes, else the same passes split over threads
    (:func:`parallel_forces`, :func:`parallel_advance`). ``volume_arms``: the volume
    term's arms (:func:`net_forces`), None: elastic; ``volume_nodes``: None (per tet) or the
    nodal term's scratch (:func:`net_forces`).
    """
    x, x_prev, arm_force, dx_prev = state
    masses, inv_masses, active = particles
    if blocks is None:
        outside, bad = net_forces(state, springs, particles, loads, forces, dx_lo, dx_hi,
                                  volume, volume_arms, volume_nodes)
        energy = advance_positions(x, x_prev, forces, inv_masses, active, scale, check, masses)
    else:
        edges, rest_lengths, K0, a, b, arm_r, arm_c = springs
        outside = parallel_forces(x, arm_force, dx_prev, edges, rest_lengths, K0, a, b, arm_r,
                                  arm_c, dx_lo, dx_hi, blocks)
        bad = -1
        if volume is not None:  # serial, into thread 0's buffer (summed by parallel_advance)
            bad = add_volume_pass(x, blocks[0][0], volume, volume_arms, volume_nodes)
        energy = parallel_advance(x, x_prev, forces, inv_masses, masses, active, loads, scale,
                                  check, blocks)
    if check and not 0.5 * energy / (dt * dt) <= energy_bound:
        divergent_node(x, x_prev, active, status)
    return outside, bad


@njit(parallel=True, **JIT)
def parallel_forces(x, arm_force, dx_prev, edges, rest_lengths, K0, a, b, arm_r, arm_c, dx_lo,
                    dx_hi, blocks):
    """The connector pass of :func:`net_forces` split over ``T`` threads (one parallel region).

    ``blocks`` = (thread_forces (T, N, 3), edge_starts (T+1,), node_starts (T+1,)) (see
    :func:`particle.integrator.thread_blocks`): thread t adds connectors
    ``edge_starts[t] .. edge_starts[t+1]-1`` into its own zeroed
    ``thread_forces[t]`` (no two threads write the same memory; arm forces
    and elongations are per connector). Returns the first connector outside
    ``[dx_lo, dx_hi]`` in connector order, as the serial pass.
    """
    thread_forces, edge_starts, _ = blocks
    outside = np.empty(thread_forces.shape[0], np.int64)  # each thread's first, then the first
    for t in prange(thread_forces.shape[0]):
        own = thread_forces[t]
        own[:] = 0.0
        outside[t] = add_connector_forces(x, edges, rest_lengths, K0, a, b, arm_r, arm_c,
                                          arm_force, dx_prev, own, None, arm_force, dx_prev,
                                          dx_lo, dx_hi, edge_starts[t], edge_starts[t + 1])
    for t in range(outside.shape[0]):
        if outside[t] >= 0:
            return outside[t]
    return -1


@njit(**JIT)
def sum_thread_forces(thread_forces, forces, nodes):
    """forces[n] = sum over t of thread_forces[t, n] [N] for ``nodes``, in thread order.

    ``thread_forces`` (T, N, 3), ``forces`` (N, 3).
    """
    for n in nodes:
        f0 = thread_forces[0, n, 0]
        f1 = thread_forces[0, n, 1]
        f2 = thread_forces[0, n, 2]
        for k in range(1, thread_forces.shape[0]):  # three scalars: 2x faster than a c loop
            f0 += thread_forces[k, n, 0]
            f1 += thread_forces[k, n, 1]
            f2 += thread_forces[k, n, 2]
        forces[n, 0] = f0
        forces[n, 1] = f1
        forces[n, 2] = f2


@njit(parallel=True, **JIT)
def parallel_advance(x, x_prev, forces, inv_masses, masses, active, loads, scale, check, blocks):
    """Reduction of the thread forces, the node loads and the position update, split over nodes.

    Thread t takes the active nodes ``active[node_starts[t] .. node_starts[t+1]-1]``:
    ``forces[n] = sum_t thread_forces[t, n]`` (in thread order, a fixed
    summation order: the result does not depend on the scheduling), then
    :func:`add_gravity`, :func:`add_damping` and :func:`advance_positions` of
    those nodes (:func:`add_loads`). Returns the summed energy of :func:`advance_positions`.
    """
    thread_forces, _, node_starts = blocks
    energy = np.empty(thread_forces.shape[0])  # each thread's, summed in thread order
    (gx, gy, gz), damping_rate, with_gravity, with_damping = loads  # a parallel loop takes
    for t in prange(thread_forces.shape[0]):  # scalars, not a tuple of tuples
        nodes = active[node_starts[t]:node_starts[t + 1]]
        sum_thread_forces(thread_forces, forces, nodes)
        add_loads(forces, masses, x, x_prev, ((gx, gy, gz), damping_rate, with_gravity,
                                              with_damping), nodes)
        energy[t] = advance_positions(x, x_prev, forces, inv_masses, nodes, scale, check, masses)
    total = 0.0
    for t in range(energy.shape[0]):
        total += energy[t]
    return total


@njit(**JIT)
def divergent_node(x, x_prev, active, status):
    """status[0, 2] = (NONFINITE, the first node with a non-finite position), else (ENERGY,
    the fastest node)."""
    fastest = np.int64(-1)
    fastest_v2 = -1.0
    for n in active:
        v2 = 0.0
        for c in range(3):
            if not math.isfinite(x[n, c]):
                status[0] = NONFINITE
                status[2] = n
                return
            dv = x[n, c] - x_prev[n, c]
            v2 += dv * dv
        if v2 > fastest_v2:
            fastest_v2 = v2
            fastest = np.int64(n)
    status[0] = ENERGY
    status[2] = fastest


@njit(**JIT)
def first_length_outside(x, edges, rest_lengths, dx_lo, dx_hi):
    """The first connector whose elongation at ``x`` is outside ``[dx_lo, dx_hi]`` (E,) [m]
    (-1: none): the check of a run's final state, the only strain check not riding on a force
    pass. Squared lengths are compared with the squared bounds (no sqrt, no division); a bound
    ``L0 + dx_lo <= 0`` (strain <= -1) admits any length."""
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        d0 = x[j, 0] - x[i, 0]
        d1 = x[j, 1] - x[i, 1]
        d2 = x[j, 2] - x[i, 2]
        l2 = d0 * d0 + d1 * d1 + d2 * d2
        lo = rest_lengths[e] + dx_lo[e]
        hi = rest_lengths[e] + dx_hi[e]
        if not (l2 <= hi * hi and (lo <= 0.0 or l2 >= lo * lo)):  # NaN: outside
            return np.int64(e)  # e may be unsigned (index views)
    return np.int64(-1)


@njit(**JIT)
def largest_move(x, x_prev):
    """An upper bound of max over the particles of |x - x_prev| [m]: sqrt(3) x the largest
    coordinate change (lane-wise over the flat arrays); NaN if a position is not finite
    (the final-state checks then take their exact pass)."""
    flat, flat_prev = x.reshape(-1), x_prev.reshape(-1)
    n = flat.shape[0]
    rest = n // LANES * LANES
    largest = vsplat(0.0)
    finite = ALL_LANES
    for k in range(0, rest, LANES):
        d = vsub(vload(flat, k), vload(flat_prev, k))
        finite &= vle_mask(d, d)  # NaN: cleared
        largest = vmax(largest, vmax(d, vsub(vsplat(0.0), d)))
    move = 0.0
    for k in range(LANES):
        move = max(move, largest[k])
    for k in range(rest, n):
        d = abs(flat[k] - flat_prev[k])
        if not d <= move:  # NaN propagates
            move = d
    if finite != ALL_LANES:
        return np.nan
    return math.sqrt(3.0) * move


@njit(**JIT)
def longest_connector(rest_lengths, dx_prev):
    """max of ``rest_lengths + dx_prev`` [m] (lane-wise; NaN lanes ignored: a NaN
    elongation comes from a NaN position, which :func:`largest_move` reports)."""
    n = dx_prev.shape[0]
    rest = n // LANES * LANES
    longest = vsplat(0.0)
    for e in range(0, rest, LANES):
        longest = vmax(vadd(vload(rest_lengths, e), vload(dx_prev, e)), longest)
    out = 0.0
    for k in range(LANES):
        out = max(out, longest[k])
    for e in range(rest, n):
        out = max(out, rest_lengths[e] + dx_prev[e])
    return out


@njit(**JIT)
def final_volume_check(x, x_prev, rest_lengths, dx_prev, volume):
    """The first tet whose volume at ``x`` (a run's final state) is outside ``(v_lo, v_hi]``,
    -1 if none; ``volume`` is the loop's volume group, whose last array holds the volumes
    [m^3] the last step's force pass computed at ``x_prev``, where the connectors'
    elongations were ``dx_prev`` (E,) [m].

    Every tet edge is a connector (a model invariant), none longer than ``L = max(L0 +
    dx_prev)`` at ``x_prev``, and no particle moved more than ``D``
    (:func:`largest_move`): each edge vector changed by at most ``2 D``, so no volume (a
    sixth of the triple product of three edge vectors) by more than ``((L + 2 D)^3 -
    L^3) / 6``. When every stored volume is that much, plus ``1e-13 (L + 2 D)^3`` for the
    round-off of both computed volumes, inside its range, passes over contiguous arrays
    decide (no gathers); otherwise the exact pass :func:`first_volume_outside`.
    """
    tets, _, _, v_lo, v_hi, volumes = volume
    longest = longest_connector(rest_lengths, dx_prev)
    reach = longest + 2.0 * largest_move(x, x_prev)
    margin = (reach * reach * reach - longest * longest * longest) / 6.0
    margin += 1e-13 * reach * reach * reach
    if all_inside(volumes, v_lo, v_hi, margin):
        return np.int64(-1)
    return first_volume_outside(x, tets, v_lo, v_hi)


@njit(**JIT)
def final_strain_check(x, x_prev, edges, rest_lengths, dx_prev, dx_lo, dx_hi):
    """The first connector whose elongation at ``x`` (a run's final state) is outside
    ``[dx_lo, dx_hi]`` (E,) [m], -1 if none; ``x_prev`` (N, 3) are the positions the last
    step started from and ``dx_prev`` (E,) the elongations there (stored by its force pass).

    No particle moved more than ``D`` (:func:`largest_move`) in that step, so no
    connector's length changed by more than 2 D: when every ``dx_prev`` is 2 D inside its
    range, so is the final state, which passes over contiguous arrays decide (lane-wise,
    no gathers; 4 us on the 12k-connector liver, the exact pass 22 us); otherwise (a
    connector near its bound, or a large last move) the exact pass
    :func:`first_length_outside`.
    """
    if all_inside(dx_prev, dx_lo, dx_hi, 2.0 * largest_move(x, x_prev)):
        return np.int64(-1)
    return first_length_outside(x, edges, rest_lengths, dx_lo, dx_hi)


@njit(**JIT)
def prescribe(x, x_prev, nodes, times, positions, t):
    """Move prescribed nodes to their piecewise-linear keyframe position at time t."""
    k = np.searchsorted(times, t)
    for p in range(nodes.shape[0]):
        n = nodes[p]
        for c in range(3):
            if k == 0:
                target = positions[0, p, c]
            elif k >= times.shape[0]:
                target = positions[times.shape[0] - 1, p, c]
            else:
                w = (t - times[k - 1]) / (times[k] - times[k - 1])
                target = (1.0 - w) * positions[k - 1, p, c] + w * positions[k, p, c]
            x_prev[n, c] = x[n, c]
            x[n, c] = target


def spring_group(*, edges, rest_lengths, K0, a, b, arm_r, arm_c) -> tuple[tuple, tuple]:
    """:func:`run_verlet`'s ``connectors`` = (the connector ends (E, 2) (an index view), rest
    lengths (E,) [m], spring coefficients K0 (E,) [N/m]) and ``connector_terms`` = (a, b
    (E,) [N/m] (None: linear), the arms' recursion coefficients r, c (E, 2) (None: no
    arms)); the kernels' ``springs`` are the two joined."""
    return (edges, rest_lengths, K0), (a, b, arm_r, arm_c)


def particle_group(*, masses, inv_masses, active) -> tuple:
    """:func:`run_verlet`'s ``particles``: masses (N,) [kg] (gravity, damping, the energy
    check), the inverse inertia (N,) [1/kg] of the position update, the nodes it moves."""
    return (masses, inv_masses, active)


def load_group(*, gravity, damping_rate) -> tuple:
    """:func:`run_verlet`'s ``loads``: (gravity (3 floats) [m/s^2], the damping rate
    gamma/dt [1/s^2], with gravity, with damping) from ``gravity`` (3,) and
    ``damping_rate``, each None: none. Flags, not Nones, so that one compiled loop serves
    every combination; floats, not an array, because every array argument costs the
    kernel call an unboxing (about 0.1 us)."""
    gx, gy, gz = (0.0, 0.0, 0.0) if gravity is None else (float(g) for g in gravity)
    return ((gx, gy, gz), 0.0 if damping_rate is None else float(damping_rate),
            gravity is not None, damping_rate is not None)


@njit(**JIT)
def record_positions(x, rec_nodes, rec_steps, rec_out, slot, step):
    """Store the positions of ``rec_nodes`` in ``rec_out[slot]`` for every slot from ``slot``
    whose ``rec_steps`` is ``step``; returns the next slot (``rec_nodes`` None: none)."""
    if rec_nodes is None:
        return slot
    while slot < rec_steps.shape[0] and rec_steps[slot] == step:
        for r in range(rec_nodes.shape[0]):
            rec_out[slot, r] = x[rec_nodes[r]]
        slot += 1
    return slot


@njit(**JIT)
def final_state_check(x, x_prev, edges, rest_lengths, dx_prev, dx_lo, dx_hi, volume):
    """(code, id) of a run's final state: (VOLUME_END, the first tet outside ``(v_lo,
    v_hi]``), else (STRAIN_END, the first connector outside ``[dx_lo, dx_hi]``), id -1 when
    none is (``volume`` None, ``dx_lo`` empty: that check is not made)."""
    code, bad = OK, np.int64(-1)
    if volume is not None:
        code, bad = VOLUME_END, final_volume_check(x, x_prev, rest_lengths, dx_prev, volume)
    if bad < 0 and dx_lo.shape[0] > 0:
        code, bad = STRAIN_END, final_strain_check(x, x_prev, edges, rest_lengths, dx_prev,
                                                   dx_lo, dx_hi)
    return code, bad


@njit(**JIT)
def probe_force(state, springs, probe_node, probe_edges, probe_out, probe_tets, volume,
                volume_arms, volume_nodes):
    """The force on ``probe_node`` at the final state into ``probe_out`` (``probe_node`` < 0:
    nothing): its connectors (:func:`node_force`) and, with the volume term, its tets
    ``probe_tets`` (:func:`add_probe_volume_force`)."""
    if probe_node < 0:
        return
    x, _, arm_force, dx_prev = state
    edges, rest_lengths, K0, a, b, arm_r, arm_c = springs
    node_force(x, probe_node, probe_edges, edges, rest_lengths, K0, a, b, arm_r, arm_c,
               arm_force, dx_prev, probe_out)
    if volume is not None:
        add_probe_volume_force(x, probe_node, probe_tets, volume, volume_arms, volume_nodes,
                               probe_out)


def add_probe_volume_force(x, node, tets, volume, volume_arms, volume_nodes, out):
    """In compiled code: out (3,) += the volume term's force [N] on particle ``node`` from its
    tets ``tets`` (:func:`particle.volume.node_volume_force`), or with ``volume_nodes`` not
    None from its two-ring of tets (:func:`particle.nodal_kernels.nodal_node_volume_force`);
    chosen by type as :func:`particle.kernels.add_volume_pass` is."""
    raise NotImplementedError("add_probe_volume_force is for compiled code")


@overload(add_probe_volume_force, jit_options=OVERLOAD_JIT)
def _add_probe_volume_force(x, node, tets, volume, volume_arms, volume_nodes, out):
    if isinstance(volume_nodes, types.NoneType):
        def per_tet(x, node, tets, volume, volume_arms, volume_nodes, out):
            node_volume_force(x, node, tets, volume[0], volume[1], volume[2], volume_arms, out)
        return per_tet

    def nodal(x, node, tets, volume, volume_arms, volume_nodes, out):
        nodal_node_volume_force(x, node, tets, volume[0], volume[1], volume[2], volume_arms,
                                volume_nodes[0], out)
    return nodal


@njit(**JIT)
def run_verlet(state, connectors, connector_terms, particles, loads, stepping, prescribed,
               recording, checks, probe, scratch, volume_term, volume_checks, volume_arm_state,
               volume_nodes):
    """Advance ``n_steps`` position-Verlet steps in place; returns status (code, step, id).

    The arguments come in groups (tuples, in this order; a group in the wrong place does
    not compile), built by :class:`particle.integrator.Run`, none with more than four arrays
    (:mod:`particle.dispatch`: numba 0.56 types larger ones in Python on most calls); the
    loop joins them into the kernels' groups:

    * ``state`` = (x, x_prev (N, 3) [m], arm_force (E, 2) [N], dx_prev (E,) [m]), updated
      in place;
    * ``connectors``, ``connector_terms`` (:func:`spring_group`; joined: the kernels'
      ``springs``), ``particles`` (:func:`particle_group`), ``loads`` (:func:`load_group`);
    * ``stepping`` = (dt [s], n_steps, startup, t0 [s]);
    * ``prescribed`` = (nodes (k,), keyframe times (K,) [s], positions (K, k, 3) [m]);
    * ``recording`` = (rec_nodes, rec_steps, rec_out), each None: no recording (compiled
      out: three empty arrays would cost the haptic loop's call their unboxing);
    * ``checks`` = (check_every, energy_bound [J], dx_lo, dx_hi (E,) [m] or (0,): none);
    * ``probe`` = (probe_node, probe_edges, probe_out (3,), probe_tets), probe_node < 0:
      no probe;
    * ``scratch`` = (forces (N, 3), blocks: None or the multi-threaded step's work split);
    * ``volume_term`` = (tets, rest_volumes, kv), ``volume_checks`` = (v_lo, v_hi, volumes
      out), joined: the kernels' ``volume``; ``volume_arm_state`` = (r, c, pressures,
      volume strains), the state's arrays updated in place (the kernels' ``volume_arms``
      with outputs aliasing them: :func:`particle.dispatch.in_place`); each None: no
      volume term, no volume arms; ``volume_nodes`` None: the volume term is per tet, else
      nodal (:mod:`particle.nodal_volume`): (volumes (N,), pressures (N,)) scratch, the
      ``volume_term``'s rest volumes and kv the particles' and the arms' state one row per
      particle; the tets' volume range is checked as for the per-tet term.

    ``x^{n+1} = 2 x^n - x^{n-1} + dt^2 f^n/m`` for the ``active`` nodes (free
    and not prescribed); if ``startup``, the first step uses half the
    acceleration term, i.e. the Taylor start ``x^1 = x^0 + dt^2/2 a^0`` of a
    state at rest (``x_prev = x``). Prescribed nodes follow their keyframes.
    Positions of ``rec_nodes`` are stored in ``rec_out[s]`` after step
    ``rec_steps[s]`` (0 = the initial state). Every ``check_every`` steps and
    after the last one the run stops with a non-zero code if positions are
    non-finite or the kinetic energy exceeds ``energy_bound`` (id = the
    particle), or, unless ``dx_lo`` is empty, a connector's elongation at the
    step before is outside ``[dx_lo, dx_hi]`` (E,) [m] (id = the connector).
    Unless ``probe_node`` < 0, a run that ends normally writes the
    connector force on ``probe_node`` at the final state into it (see
    :func:`node_force`; ``probe_edges`` are the node's connectors).
    ``blocks`` None: every step is serial; else the work split and scratch of
    a multi-threaded step (see :func:`explicit_step`). The volume term (compiled out
    without it) with its Maxwell arms (:mod:`particle.volume`; compiled out without them):
    a tet whose volume leaves
    ``(v_lo, v_hi]`` at any step (``v_lo`` >= 0, so an inverted tet always does) stops
    the run at once with code VOLUME (step = the step whose start positions it was found
    at, id = the tet); ``probe_tets`` are the probe node's tets.

    The checks ride on the force and position passes of the checked steps
    (no extra pass over the model), so a checked step costs about an unchecked one;
    they see the positions each step starts from, so the final state (after the last
    step and its prescribed motion) gets one more pass of its own: a run that ends
    with a tet outside ``(v_lo, v_hi]`` stops with code VOLUME_END, one that ends with
    a connector outside ``[dx_lo, dx_hi]`` with STRAIN_END (step = ``n_steps``, id =
    the tet or connector), before the probe force is computed.
    """
    springs = connectors + connector_terms
    volume = joined(volume_term, volume_checks)
    volume_arms = in_place(volume_arm_state)
    x, x_prev, _, dx_prev = state
    edges, rest_lengths = springs[0], springs[1]
    dt, n_steps, startup, t0 = stepping
    presc_nodes, presc_times, presc_pos = prescribed
    rec_nodes, rec_steps, rec_out = recording
    check_every, energy_bound, dx_lo, dx_hi = checks
    monitored = dx_lo.shape[0] > 0
    probe_node, probe_edges, probe_out, probe_tets = probe
    forces, blocks = scratch
    status = np.zeros(3, dtype=np.int64)
    slot = record_positions(x, rec_nodes, rec_steps, rec_out, 0, 0)
    h2 = dt * dt
    for step in range(n_steps):
        check = (step + 1) % check_every == 0 or step + 1 == n_steps
        scale = 0.5 * h2 if (startup and step == 0) else h2
        if check and monitored:
            outside, inverted = explicit_step(
                state, springs, particles, loads, forces, blocks, dx_lo, dx_hi, scale, True,
                dt, energy_bound, status, volume, volume_arms, volume_nodes)
        else:  # the strain range compiled out of the connector pass
            outside, inverted = explicit_step(
                state, springs, particles, loads, forces, blocks, None, None, scale, check,
                dt, energy_bound, status, volume, volume_arms, volume_nodes)
        if volume is not None and inverted >= 0:
            status[0] = VOLUME
            status[1] = step  # the tet was inverted at the positions the step started from
            status[2] = inverted
            return status
        prescribe(x, x_prev, presc_nodes, presc_times, presc_pos, t0 + (step + 1) * dt)
        slot = record_positions(x, rec_nodes, rec_steps, rec_out, slot, step + 1)
        if check:
            if status[0] == OK and outside >= 0:
                status[0] = STRAIN
                status[2] = outside
            if status[0] != OK:
                status[1] = step + 1
                return status
    if n_steps > 0:  # the final state: the steps above checked the positions they started from
        code, bad = final_state_check(x, x_prev, edges, rest_lengths, dx_prev, dx_lo, dx_hi,
                                      volume)
        if bad >= 0:
            status[0] = code
            status[1] = n_steps
            status[2] = bad
            return status
    probe_force(state, springs, probe_node, probe_edges, probe_out, probe_tets, volume,
                volume_arms, volume_nodes)
    return status
