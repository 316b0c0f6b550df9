"""The haptic step with the volume term: its stability bound, verified strain range, mass
scaling and the ``haptic scale`` benchmark's volume rows."""
import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from forcecal.errors import StabilityError
from particle.haptics import HapticSession
from particle.stability import (EIGENVALUE_MARGIN, connector_stiffness_bound, critical_time_step,
                                largest_eigenvalue, mass_scaled_laplacian)
from particle.mass_scaling import scaled_inertia, stiffness_weights
from particle.model import ModelBuilder
from particle.params import connector_strain_bounds, viscoelastic_params
from tests.particle_models import box_model, top_centre
from particle.volume import signed_volumes, volume_hessian_numpy
from particle.volume_bounds import (_irons_bound, _tet_bounds, node_volume_stiffness_bound,
                                    volume_edge_stiffness_bound, volume_frequency_bound,
                                    volume_ratio_range, volume_scalar_matrix)

PERIOD = 1e-3


def with_kv(model, kv):
    """The model with a volume stiffness kv [Pa] on every tet."""
    return model.with_params(dataclasses.replace(model.params, kv=np.full(model.n_tets, kv)))


def jittered_box(seed=0, jitter=0.25, kv=2e4):
    """A (3, 3, 2) Kuhn box whose inner and top vertices are moved by up to ``jitter`` x the
    cell size (an irregular mesh: tets of unequal size and shape), bottom fixed."""
    box = box_model((3, 3, 2))
    x = box.rest_positions.copy()
    cell = 0.01
    rng = np.random.default_rng(seed)
    movable = ~box.fixed
    x[movable] += jitter * cell * rng.uniform(-1.0, 1.0, (int(movable.sum()), 3))
    builder = ModelBuilder()
    builder.add_particles(x, box.masses, box.fixed)
    builder.add_connectors(box.edges)
    params = dataclasses.replace(viscoelastic_params(box.n_connectors),
                                 kv=np.full(box.n_tets, kv))
    model = builder.finalize(params, tets=box.tets)
    assert np.all(signed_volumes(x, box.tets) > 0.0)
    return model


def volume_eigenvalue(model, x, arms=None):
    """lambda_max(M^{-1/2} K_vol M^{-1/2}) [1/s^2] on the free particles at positions ``x``
    (``arms``: see :func:`mass_scaled_volume_tangent`)."""
    return float(np.linalg.eigvalsh(mass_scaled_volume_tangent(model, x, arms))[-1])


def mass_scaled_volume_tangent(model, x, arms=None):
    """M^{-1/2} K_vol M^{-1/2} [1/s^2] (dense, the free particles' dofs in order) at positions
    ``x``, the volume tangent assembled from the per-tet numpy Hessians; ``arms`` = (the
    arms' step coefficients c_1 + c_2 (T,) [Pa], their summed pressures (T,) [Pa]) or None
    (elastic)."""
    n = model.n_particles
    rows, cols, vals = [], [], []
    for t, tet in enumerate(model.tets):
        extra = () if arms is None else (arms[0][t], arms[1][t])
        h = volume_hessian_numpy(x, tet, model.rest_volumes[t], model.params.kv[t], *extra)
        idx = (3 * tet[:, None] + np.arange(3)).ravel()
        rows.append(np.repeat(idx, 12))
        cols.append(np.tile(idx, 12))
        vals.append(h.ravel())
    k = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(3 * n, 3 * n)).toarray()
    dof = np.repeat(~model.fixed, 3)
    scale = 1.0 / np.sqrt(np.repeat(model.masses, 3)[dof])
    return scale[:, None] * k[np.ix_(dof, dof)] * scale


def strains_and_ratios(model, x):
    d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
    return (np.linalg.norm(d, axis=1) / model.rest_lengths - 1.0,
            signed_volumes(x, model.tets) / model.rest_volumes)


def states_in_range(model, seed, reach):
    """Positions of ``model``: the rest state, random perturbations of the free particles
    (up to 1 mm) and stretches along z from the fixed bottom (0.75 and 1.29), those whose
    connector strains lie in +-``reach``."""
    free = ~model.fixed
    rng = np.random.default_rng(seed)
    states = []
    for amplitude in (0.0, 3e-4, 6e-4, 1e-3):
        for _ in range(3):
            x = model.rest_positions.copy()
            x[free] += amplitude * rng.standard_normal((int(free.sum()), 3))
            states.append(x)
    for stretch in (0.75, 1.29):  # |strain|, |V/V0 - 1| <= 0.29
        x = model.rest_positions.copy()
        x[:, 2] *= stretch
        states.append(x)
    return [x for x in states if np.all(np.abs(strains_and_ratios(model, x)[0]) <= reach)]


@pytest.mark.parametrize("seed", [0, 1])
def test_the_nodal_volume_bound_is_above_the_true_eigenvalue_on_deformed_irregular_meshes(seed):
    """Rigour: at rest and at random states whose strains lie in the range (+-0.3), the largest
    mass-scaled eigenvalue of the assembled volume tangent (exact numpy Hessians) is below
    max_n D_n/m_n; the bound used by the stable step is the smaller of it and Irons' bound."""
    model = jittered_box(seed)
    lo, hi = connector_strain_bounds((-0.3, 0.3), model.n_connectors, model.edges)
    free = ~model.fixed
    nodal = float(np.max(node_volume_stiffness_bound(model, lo, hi)[free] / model.masses[free]))
    irons = _irons_bound(model, *_tet_bounds(model, lo, hi))
    assert volume_frequency_bound(model, lo, hi) == min(nodal, irons)
    states = states_in_range(model, seed, 0.3)
    assert len(states) >= 10
    for x in states:
        assert volume_eigenvalue(model, x) <= nodal
    # on this irregular mesh the nodal bound is the smaller one, and it is not vacuous:
    # within 10x of the true eigenvalue at rest
    assert nodal < irons
    assert nodal < 10.0 * volume_eigenvalue(model, model.rest_positions)


@pytest.mark.parametrize("seed, relaxing", [(0, False), (1, False), (0, True)])
def test_the_spectral_volume_bound_is_above_the_true_eigenvalue_and_below_the_nodal_one(
        seed, relaxing):
    """Rigour of :func:`volume_scalar_matrix`: at rest and at random states whose strains lie in
    +-0.3, the largest mass-scaled eigenvalue of the assembled volume tangent (exact numpy
    Hessians; with the volume arms, their largest step coefficient ``kv1 + kv2`` and random
    summed pressures up to the bound ``(kv1 + kv2)(J_hi - J_lo)``) is below the largest
    eigenvalue of the scalar matrix, whose row sums are the nodal bound: so it is never above
    that one, and on these irregular meshes clearly below it. The stable step takes it."""
    model = jittered_box(seed)
    if relaxing:
        n = model.n_tets
        model = model.with_params(dataclasses.replace(
            model.params, kv1=np.full(n, 1.2e4), bv1=np.full(n, 6e3), kv2=np.full(n, 8e3),
            bv2=np.full(n, 8e4)))
    reach = (-0.3, 0.3)
    lo, hi = connector_strain_bounds(reach, model.n_connectors, model.edges)
    spectral = largest_eigenvalue(volume_scalar_matrix(model, lo, hi))
    free = ~model.fixed
    nodal = float(np.max(node_volume_stiffness_bound(model, lo, hi)[free] / model.masses[free]))
    assert spectral <= nodal * (1.0 + 1e-12)
    assert spectral < 0.8 * nodal
    rng = np.random.default_rng(seed)
    j_lo, j_hi = volume_ratio_range(model, lo, hi)
    states = states_in_range(model, seed, 0.3)
    assert len(states) >= 10
    for x in states:
        arms = None
        if relaxing:
            k = model.params.kv1 + model.params.kv2
            arms = (k, k * (j_hi - j_lo) * rng.uniform(-1.0, 1.0, model.n_tets))
        assert volume_eigenvalue(model, x, arms) <= spectral
    kappa = connector_stiffness_bound(model.params, lo, hi)
    springs = EIGENVALUE_MARGIN * largest_eigenvalue(mass_scaled_laplacian(model, kappa))
    assert critical_time_step(model, strain_range=reach) >= 2.0 / np.sqrt(
        springs + EIGENVALUE_MARGIN * spectral)


def test_the_nodal_bound_follows_the_closed_form_of_one_free_vertex():
    """One free vertex (the others fixed): H = kv/V0 g g^T on it (d^2V/dp3^2 = 0), so at the
    rest state with a zero-width strain range the bound is exactly kv/V0 |g_3|^2 / m_3."""
    builder = ModelBuilder()
    tet = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.003, 0.018, 0.0],
                    [0.004, 0.006, 0.017]])
    builder.add_particles(tet, np.full(4, 1e-3), np.array([True, True, True, False]))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    params = dataclasses.replace(viscoelastic_params(6), kv=np.array([3000.0]))
    model = builder.finalize(params, tets=np.array([[0, 1, 2, 3]]))
    zero = np.zeros(6)
    g3 = np.cross(tet[1] - tet[0], tet[2] - tet[0]) / 6.0
    expected = 3000.0 / model.rest_volumes[0] * float(g3 @ g3) / 1e-3
    assert node_volume_stiffness_bound(model, zero, zero)[3] / 1e-3 == pytest.approx(
        expected, rel=1e-12)
    assert volume_eigenvalue(model, tet) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_edge_bound_of_the_volume_term_is_above_its_tangent_on_deformed_irregular_meshes(
        seed):
    """Rigour in the Loewner order: at the states of the nodal bound's test, ``L_w (x) I_3 -
    K_vol`` (``w`` per connector, mass-scaled) has no negative eigenvalue (beyond round-off),
    and the stable step, which takes the smaller of this bound (added to the connectors'
    ``kappa``) and the springs' bound plus the volume term's own, is at least the latter's."""
    model = jittered_box(seed)
    reach = (-0.3, 0.3)
    lo, hi = connector_strain_bounds(reach, model.n_connectors, model.edges)
    bound = np.kron(mass_scaled_laplacian(model, volume_edge_stiffness_bound(model, lo, hi)
                                          ).toarray(), np.eye(3))
    states = states_in_range(model, seed, 0.3)
    assert len(states) >= 10
    for x in states:
        tangent = mass_scaled_volume_tangent(model, x)
        gap = np.linalg.eigvalsh(bound - tangent)[0]
        assert gap >= -1e-12 * np.abs(tangent).max()
    kappa = connector_stiffness_bound(model.params, lo, hi)
    separate = (EIGENVALUE_MARGIN * largest_eigenvalue(mass_scaled_laplacian(model, kappa))
                + volume_frequency_bound(model, lo, hi))
    assert critical_time_step(model, strain_range=reach) >= 2.0 / np.sqrt(separate)


def test_the_edge_bound_is_exact_for_a_regular_tet_at_rest():
    """Four free particles of equal mass on a regular tet, zero-width strain range: the
    tangent is the rank-one ``kv/V0 g g^T`` (J = 1), with eigenvalue ``kv/V0 |g|^2/m``, and
    the Laplacian of the six equal edge weights has ``4 w/m``: the same, since removing the
    rigid translation loses nothing on one tet."""
    builder = ModelBuilder()
    side = 0.02
    tet = side / np.sqrt(8.0) * np.array([[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, -1.0, -1.0],
                                          [-1.0, -1.0, 1.0]])
    builder.add_particles(tet, np.full(4, 1e-3), np.zeros(4, dtype=bool))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    params = dataclasses.replace(viscoelastic_params(6), kv=np.array([3000.0]))
    model = builder.finalize(params, tets=np.array([[0, 1, 2, 3]]))
    zero = np.zeros(6)
    w = volume_edge_stiffness_bound(model, zero, zero)
    np.testing.assert_allclose(w, w[0], rtol=1e-12)
    face = np.sqrt(3.0) / 4.0 * side ** 2  # each |g_a| is a face's area over 3
    exact = 3000.0 / model.rest_volumes[0] * 4.0 * (face / 3.0) ** 2 / 1e-3
    assert volume_eigenvalue(model, tet) == pytest.approx(exact, rel=1e-12)
    assert largest_eigenvalue(mass_scaled_laplacian(model, w)) == pytest.approx(exact, rel=1e-12)


def test_a_session_on_a_narrower_strain_range_takes_a_larger_step_and_verifies_it():
    """strain_range: the limit is the one of that range (larger with the volume term); a dt
    above it is refused with the limit in the message; a drag that leaves the range stops
    with a StabilityError naming the connector, the state never NaN."""
    model = with_kv(box_model((3, 3, 2), K0=200.0), 2e4)
    narrow = (-0.1, 0.1)
    wide_limit = critical_time_step(model)
    narrow_limit = critical_time_step(model, strain_range=narrow)
    assert narrow_limit > 1.3 * wide_limit  # 1.47x here
    HapticSession(model, narrow_limit, period=narrow_limit, strain_range=narrow)
    with pytest.raises(StabilityError, match=rf"above the stability limit {narrow_limit:.4g} s"):
        HapticSession(model, 1.01 * narrow_limit, period=1.01 * narrow_limit,
                      strain_range=narrow)
    with pytest.raises(StabilityError, match=rf"above the stability limit {wide_limit:.4g} s"):
        HapticSession(model, narrow_limit, period=narrow_limit)  # default range +-0.5
    session = HapticSession(model, 0.9 * narrow_limit, strain_range=narrow)
    node = top_centre(model)
    x0 = model.rest_positions[node]
    session.step(node, x0 + [0.0, 0.0, -5e-4])  # 5 % of a 10 mm edge: inside the range
    with pytest.raises(StabilityError, match=r"connector \d+ \(particles \d+-\d+\) reached "
                                             r"strain .* outside \[-0.1, 0.1\]"):
        for _ in range(20):
            session.step(node, x0 + [0.0, 0.0, -3e-3])  # 30 %: beyond it
    assert np.all(np.isfinite(session.state.x))


def test_mass_scaling_with_the_volume_term_puts_mass_where_it_stiffens_and_is_verified():
    """The weights include the volume term's per-particle bound; the scaled inertia makes
    one substep per period stable (the session accepts it, a 1 % longer period is refused
    with the limit)."""
    model = with_kv(box_model((3, 3, 2), K0=200.0), 2e4)
    springs = box_model((3, 3, 2), K0=200.0)
    lo, hi = connector_strain_bounds((-0.5, 0.5), model.n_connectors, model.edges)
    assert np.allclose(stiffness_weights(model) - stiffness_weights(springs),
                       node_volume_stiffness_bound(model, lo, hi), rtol=1e-12)
    dt = 0.9 * PERIOD
    assert critical_time_step(model) < dt / 3  # needs mass scaling for one substep
    inertia = scaled_inertia(model, PERIOD / 0.9)
    session = HapticSession(model, PERIOD, inertia=inertia)
    assert session.substeps == 1
    node = top_centre(model)
    force = session.step(node, model.rest_positions[node] + [0.0, 0.0, -5e-4])
    assert np.all(np.isfinite(force)) and force[2] > 0.0  # the tissue pushes the tool back up
    with pytest.raises(StabilityError, match=r"above the stability limit"):
        HapticSession(model, 1.2 * PERIOD / 0.9, period=1.2 * PERIOD / 0.9, inertia=inertia)


def test_the_haptic_scale_volume_rows_state_substeps_errors_and_cost():
    """The benchmark's volume rows on a small box: float64 is the errors' reference (0), the
    narrower strain range and mass scaling take fewer substeps with small or stated errors,
    and volume_cost compares the volume term's time per call with springs-only."""
    from pipelines.bench.haptic import (BAND, ENVELOPE, FOLLOWING, mesh_rows, volume_cost,
                                        volume_rows)

    model = box_model((3, 3, 2), K0=200.0)
    gravity = np.array([0.0, 0.0, -9.81])
    node, tracked = top_centre(model), int(model.free_nodes[-1])
    rows = volume_rows("box", model, node, tracked, gravity, kv=3e4, calls=1000)
    by = {r["variant"]: r for r in rows}
    narrow = ENVELOPE
    assert set(by) == {"float64", narrow, FOLLOWING, "mass-scaled 1", "mass-scaled 2"}
    assert all(r["terms"] == "springs + arms + volume" and r["tets"] == model.n_tets
               for r in rows)
    ref = by["float64"]
    assert ref["error_drag"] == 0.0 and ref["error_release"] == 0.0 and ref["substeps"] > 2
    assert by[narrow]["substeps"] < ref["substeps"]
    reach = by[narrow]["strain_range"][1]  # 1.2 x the drag's largest |strain|, to 0.05
    assert by[narrow]["strain_range"] == [-reach, reach] and 0.0 < reach < 0.5
    assert 0.0 < by[narrow]["error_drag"] < 1e-2  # a smaller step of the same physics
    # the bands that follow the state: fewer substeps, the same physics at another step
    following = by[FOLLOWING]
    assert following["band"] == BAND and following["substeps"] < ref["substeps"]
    assert 0.0 < following["error_drag"] < 1e-2 and 0.0 < following["error_release"] < 1e-2
    for k in (1, 2):
        assert by[f"mass-scaled {k}"]["substeps"] == k
        assert by[f"mass-scaled {k}"]["added_mass"] > 0.0
        assert 0.0 < by[f"mass-scaled {k}"]["error_drag"] < 1.0
    cost = volume_cost(mesh_rows("box", model, node, tracked, gravity, calls=1000) + rows)
    assert len(cost) == 1 and cost[0]["substeps"][1] == ref["substeps"]
    assert cost[0]["ratio_median"] > 0.0


def test_the_relaxing_volume_rows_take_the_connectors_prony_split_and_the_volume_goal():
    """``volume_model`` with a Prony split puts ``g_i/(1 - g_1 - g_2) kv`` in each arm
    (``bv_i = tau_i kv_i``), so the instantaneous stiffness is ``kv/(1 - g_1 - g_2)`` and the
    stable step shorter than the elastic term's; the goals table reads a relaxing row against
    the volume goal (200 us), a springs row against 100 us, each met only by the p99 of at
    least GOAL_CALLS calls."""
    from pipelines.bench.haptic import (GOAL_CALLS, GOAL_US, RELAXING, SPRINGS, VOLUME_GOAL_US,
                                        goal_rows, volume_model)

    model = box_model((3, 3, 2), K0=200.0)
    elastic = volume_model(model, 3e4)
    relaxing = volume_model(model, 3e4, ((0.35, 0.25), (0.5, 10.0)))
    p = relaxing.params
    np.testing.assert_allclose(p.kv1, 0.35 / 0.4 * 3e4, rtol=1e-15)
    np.testing.assert_allclose(p.kv2, 0.25 / 0.4 * 3e4, rtol=1e-15)
    np.testing.assert_allclose(p.volume_arm_tau, np.tile([0.5, 10.0], (model.n_tets, 1)),
                               rtol=1e-15)
    np.testing.assert_allclose(p.volume_instantaneous, 3e4 / 0.4, rtol=1e-15)
    assert elastic.params.kv1 is None
    assert critical_time_step(relaxing) < critical_time_step(elastic)
    row = {"mesh": "m", "connectors": 12_062, "variant": "float64", "substeps": 4,
           "median_us": 150.0, "p99_us": 180.0, "error_drag": 0.0, "error_release": 0.0,
           "calls": GOAL_CALLS}
    rows = [dict(row, terms=SPRINGS, goal_us=GOAL_US), dict(row, terms=RELAXING,
                                                             goal_us=VOLUME_GOAL_US)]
    goals = goal_rows({"haptic_scale": {"rows": rows}})
    assert [g[1] for g in goals] == [f"<= {goal} us (p99 of >= {GOAL_CALLS} calls)"
                                     for goal in (100, 200)]
    assert [g[3] for g in goals] == ["**missed**", "**met**"]
    assert "relaxing volume term" in goals[1][0]
    fewer = [dict(r, calls=2000) for r in rows]
    assert [g[3] for g in goal_rows({"haptic_scale": {"rows": fewer}})] == [
        "**missed**", "**open** (2000 calls)"]


@pytest.mark.parametrize("jump", [3.0, 30.0])  # x the mean connector length
def test_a_step_ending_with_a_tet_outside_its_volume_range_is_refused_by_that_call(jump):
    """The volume range is checked on each substep's start positions, and on the state a
    call ends in: with one substep per call only the latter sees the tool's jump, and the
    call that made it raises, naming a tet that is out of range (or inverted) there."""
    model = with_kv(box_model((3, 3, 2)), 2e4)
    node = top_centre(model)
    dt = 0.5 * critical_time_step(model)
    session = HapticSession(model, dt, period=dt)
    assert session.substeps == 1
    x0 = model.rest_positions[node]
    session.step(node, x0)
    move = jump * float(model.rest_lengths.mean())
    with pytest.raises(StabilityError, match=rf"haptic step moving tool particle {node} .*: "
                       r"tet \d+ \(particles \d+-\d+-\d+-\d+\) (reached volume ratio|inverted)"
                       r".* after step 1 \(t = .* s\) of the explicit run") as err:
        session.step(node, x0 + [0.0, 0.0, -move])
    t = int(str(err.value).split(": tet ")[1].split()[0])
    ratio = signed_volumes(session.state.x, model.tets[t:t + 1])[0] / model.rest_volumes[t]
    lo, hi = session._run(node)[0].volume_ratio_range
    assert not lo[t] < ratio <= hi[t]


def test_the_final_volume_check_matches_numpy():
    """volume.first_volume_outside (the final state's check) names the first tet whose
    volume is outside (v_lo, v_hi], as numpy's signed volumes do."""
    from particle import kernels
    from particle.volume import first_volume_outside
    model = jittered_box()
    tets = kernels.index_view(model.tets)
    v_lo, v_hi = 0.7 * model.rest_volumes, 1.3 * model.rest_volumes
    rng = np.random.default_rng(5)
    seen = set()
    for amplitude in (1e-5, 3e-4, 1e-3, 3e-3):
        for _ in range(20):
            x = model.rest_positions + amplitude * rng.standard_normal((model.n_particles, 3))
            v = signed_volumes(x, model.tets)
            bad = np.nonzero(~((v > v_lo) & (v <= v_hi)))[0]
            got = first_volume_outside(x, tets, v_lo, v_hi)
            assert got == (bad[0] if len(bad) else -1)
            seen.add(got >= 0)
    assert seen == {False, True}


def test_the_final_volume_check_by_the_displacement_bound_matches_the_exact_pass():
    """step_kernels.final_volume_check (the bound from the stored volumes, the longest
    connector and the largest move, else the exact pass) names the tet first_volume_outside
    names, from small moves (the bound decides) to large ones (the exact pass), and a
    non-finite position is never inside."""
    from particle import kernels, step_kernels
    from particle.volume import add_volume_forces, first_volume_outside
    model = jittered_box()
    tets = kernels.index_view(model.tets)
    v_lo, v_hi = 0.7 * model.rest_volumes, 1.3 * model.rest_volumes
    rng = np.random.default_rng(8)
    seen = set()
    for amplitude in (1e-6, 1e-5, 3e-4, 1e-3, 3e-3):
        for _ in range(20):
            x_prev = model.rest_positions + amplitude * rng.standard_normal(
                (model.n_particles, 3))
            x = x_prev + 0.3 * amplitude * rng.standard_normal(x_prev.shape)
            # the stored volumes and elongations at x_prev, as the last step's passes leave them
            volumes = np.empty(model.n_tets)
            add_volume_forces(x_prev, tets, model.rest_volumes, model.params.kv,
                              np.zeros(model.n_tets), np.full(model.n_tets, np.inf),
                              np.zeros_like(x_prev), None, volumes)
            d = x_prev[model.edges[:, 1]] - x_prev[model.edges[:, 0]]
            dx_prev = np.linalg.norm(d, axis=1) - model.rest_lengths
            volume = (tets, model.rest_volumes, model.params.kv, v_lo, v_hi, volumes)
            got = step_kernels.final_volume_check(x, x_prev, model.rest_lengths, dx_prev,
                                                  volume)
            assert got == first_volume_outside(x, tets, v_lo, v_hi)
            seen.add(got >= 0)
    assert seen == {False, True}
    x[3, 0] = np.nan
    assert step_kernels.final_volume_check(x, x_prev, model.rest_lengths, dx_prev, volume) >= 0
