"""Calibration building blocks against closed-form answers: metrics, linear network,
Van Gelder baseline, parametrisation, Nelder-Mead bookkeeping, initial guess."""
import contextlib
import dataclasses

import numpy as np
import pytest

from calibration.baseline import long_term_young_modulus, van_gelder_params
from calibration.global_fit import fe_initial_slopes, initial_guess
from calibration.metrics import force_vector_errors, point_costs, relative_rms_error
from calibration.network import linear_indentation
from calibration.optimize import gauss_newton, nelder_mead
from calibration.parametrisation import (MAX_LOCAL_FACTOR, GlobalParams, StrainRange,
                                         build_rings, check_feasible, check_offsets,
                                         global_shape, local_params)
from forcecal.errors import ConvergenceError, ParameterError
from forcecal.mesh import TetMesh, box_mesh, check_mesh, fixed_nodes
from forcecal.scene import MaterialSection
from particle.evaluators import normal_force
from particle.model import build_model
from particle.params import ConnectorParams


def test_metrics_closed_form():
    ref = np.array([[1.0, 2.0, 3.0, 4.0], [-2.0, 0.0, 1.0, 0.5]])
    sim = ref + np.array([[0.1], [0.2]])
    # a constant offset c gives RMS = c, divided by max|F_ref|
    np.testing.assert_allclose(relative_rms_error(sim, ref), [0.1 / 4.0, 0.2 / 2.0])
    np.testing.assert_allclose(point_costs(sim, ref), [4 * 0.01, 4 * 0.04])
    with pytest.raises(ParameterError, match="shape"):
        relative_rms_error(sim[:, :3], ref)
    with pytest.raises(ParameterError, match="NaN"):
        relative_rms_error(np.full_like(ref, np.nan), ref)
    with pytest.raises(ParameterError, match="identically zero"):
        relative_rms_error(sim, np.zeros_like(ref))


def test_force_vector_errors_closed_form():
    # two points, 4 samples; normals z and x; normal curves peak at 2 N and 4 N
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    ref = np.zeros((2, 4, 3))
    ref[0, :, 2] = [0.5, 1.0, 1.5, -2.0]
    ref[1, :, 0] = [1.0, 2.0, 3.0, 4.0]
    ref[1, :, 1] = 0.3  # a tangential reaction: not part of the scale
    sim = ref.copy()
    sim[0] += [0.3, 0.0, 0.4]  # |error| 0.5, its tangential part 0.3, at every sample
    sim[1, :2] += [0.0, 0.0, 0.8]  # tangential 0.8 at half the samples: RMS 0.8 / sqrt(2)
    vector, tangential = force_vector_errors(sim, ref, normals)
    np.testing.assert_allclose(vector, [0.5 / 2.0, 0.8 / np.sqrt(2) / 4.0], rtol=1e-14)
    np.testing.assert_allclose(tangential, [0.3 / 2.0, 0.8 / np.sqrt(2) / 4.0], rtol=1e-14)
    # a purely normal error is the normal curve's error, and has no tangential part
    along = ref + 0.1 * normals[:, None, :]
    vector, tangential = force_vector_errors(along, ref, normals)
    np.testing.assert_allclose(vector, relative_rms_error(normal_force(along, normals),
                                                          normal_force(ref, normals)),
                               rtol=1e-14)
    np.testing.assert_allclose(vector, [0.1 / 2.0, 0.1 / 4.0], rtol=1e-14)
    np.testing.assert_allclose(tangential, 0.0, atol=1e-16)
    with pytest.raises(ParameterError, match=r"\(P, S, 3\)"):
        force_vector_errors(sim[..., :2], ref[..., :2], normals)
    with pytest.raises(ParameterError, match="normals"):
        force_vector_errors(sim, ref, normals[:1])
    with pytest.raises(ParameterError, match="NaN"):
        force_vector_errors(np.full_like(ref, np.nan), ref, normals)
    with pytest.raises(ParameterError, match="identically zero"):
        force_vector_errors(sim, ref * [[[1.0, 1.0, 0.0]], [[1.0, 1.0, 1.0]]], normals)


def _one_tet() -> TetMesh:
    return check_mesh(TetMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.3, 1.0]]) * 0.01,
                              np.array([[0, 1, 2, 3]])))


def test_linear_network_single_free_vertex_closed_form():
    # vertex 3 indented, 0-2 clamped: each connector c = (i, 3) stretches by e_c . n per unit
    # depth, so the normal force per unit depth is sum_c k_c (e_c . n)^2 and eps_c = e_c . n / L_c
    mesh = _one_tet()
    n = mesh.inward_normals([3])
    k = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    lin = linear_indentation(mesh, np.array([0, 1, 2]), np.array([3]), n, k)
    x = mesh.vertices
    expected_slope, expected_strain = 0.0, np.zeros(6)
    for c, (i, j) in enumerate(mesh.edges):
        if j == 3:
            e = (x[3] - x[i]) / np.linalg.norm(x[3] - x[i])
            expected_slope += k[c] * (e @ n[0]) ** 2
            expected_strain[c] = (e @ n[0]) / mesh.edge_lengths[c]
    assert lin.slope[0] == pytest.approx(expected_slope, rel=1e-12)
    np.testing.assert_allclose(lin.strain[0], expected_strain, rtol=1e-12, atol=1e-12)


def test_linear_network_is_the_particle_models_initial_slope():
    # at rest the particle tangent is sum K0 e e^T (no geometric term), so a 1 um indentation
    # of the nonlinear engine must match the linear slope up to O(depth / edge) = 1e-4
    from particle.evaluators import IndentationEvaluator
    mesh = box_mesh((2, 2, 2), (0.04, 0.04, 0.02))
    fixed = fixed_nodes(mesh, "z", "min", 1e-4)
    nodes = np.array([22, 25])
    normals = mesh.inward_normals(nodes)
    lin = linear_indentation(mesh, fixed, nodes, normals)
    params = ConnectorParams.uniform(len(mesh.edges), K0=25.0, k1=1.0, b1=1.0, k2=1.0, b2=10.0)
    model = build_model(mesh, 1000.0, params, fixed=fixed)
    force = IndentationEvaluator(model, nodes, normals, np.array([1e-6]))(params)[:, 0]
    np.testing.assert_allclose(force / 1e-6, 25.0 * lin.slope, rtol=1e-3)


def test_van_gelder_baseline_matches_dilation_energy_and_prony():
    material = MaterialSection()
    E = long_term_young_modulus(material)
    mu = material.long_term_factor * material.shear_modulus
    assert E == pytest.approx(9 * material.kappa * mu / (3 * material.kappa + mu))
    mesh = box_mesh((2, 3, 2), (0.03, 0.05, 0.02))
    p = van_gelder_params(mesh, material)
    # uniform strain e in every connector stores 1/2 sum K0 (e L)^2 = 3 E V e^2 (six edges per
    # tet), the continuum dilation energy of a nu = 1/4 solid: sum K0 L^2 = 6 E V exactly
    volume = mesh.signed_volumes.sum()
    assert np.sum(p.K0 * mesh.edge_lengths ** 2) == pytest.approx(6 * E * volume, rel=1e-12)
    g_inf = material.long_term_factor
    np.testing.assert_allclose(p.k1 / p.K0, material.prony_g[0] / g_inf)
    np.testing.assert_allclose(p.k2 / p.K0, material.prony_g[1] / g_inf)
    np.testing.assert_allclose(p.tau1, material.prony_tau[0])
    np.testing.assert_allclose(p.tau2, material.prony_tau[1])
    assert not p.a.any() and not p.b.any()
    with pytest.raises(ParameterError, match="exactly two Maxwell arms"):
        van_gelder_params(mesh, MaterialSection(prony_g=(0.3,), prony_tau=(1.0,)))
    swapped = van_gelder_params(mesh, MaterialSection(prony_g=(0.25, 0.35),
                                                      prony_tau=(10.0, 0.5)))
    np.testing.assert_allclose(swapped.tau1, 0.5)  # arm 1 is always the fast one
    np.testing.assert_allclose(swapped.k1, p.k1)


def test_rings_blend_factors_geometrically():
    mesh = box_mesh((2, 2, 2), (0.04, 0.04, 0.02))
    points = np.array([22, 25])  # neighbours: connector 22-25 lies in both rings
    rings = build_rings(mesh, points)
    for p, members in zip(points, rings.members):
        np.testing.assert_array_equal(np.sort(members),
                                      np.nonzero((mesh.edges == p).any(axis=1))[0])
    shared = mesh.edge_index(np.array([22]), np.array([25]))[0]
    rows = np.asarray(rings.weights.sum(axis=1)).ravel()
    in_rings = np.zeros(len(mesh.edges), bool)
    in_rings[np.concatenate(rings.members)] = True
    np.testing.assert_allclose(rows[in_rings], 1.0)
    assert not rows[~in_rings].any()
    g = GlobalParams(K0=10.0, alpha=0.5, beta=2.0, k1=5.0, tau1=0.5, k2=3.0, tau2=10.0)
    strain = StrainRange(-0.2, 0.4)
    zs = np.array([[np.log(2.0), 0.1, 0.0], [np.log(8.0), 0.3, 0.0]])
    zr = np.array([[0.0, np.log(2.0), 0.0, 0.0], [0.0, np.log(0.5), 0.0, 0.0]])
    p = local_params(g, rings, strain, zs, zr)
    # the shared connector: geometric mean of factors 2 and 8 = 4; mean alpha offset 0.2 / s
    assert p.K0[shared] == pytest.approx(40.0)
    assert p.a[shared] / p.K0[shared] == pytest.approx(0.5 + 0.2 / strain.scale)
    assert p.tau1[shared] == pytest.approx(0.5)  # sqrt(2 x 0.5) = 1
    only_first = np.setdiff1d(rings.members[0], rings.members[1])
    np.testing.assert_allclose(p.K0[only_first], 20.0)
    np.testing.assert_allclose(p.K0[~in_rings], 10.0)
    np.testing.assert_allclose(p.b2 / p.k2, 10.0)


def test_a_punch_ring_is_the_connectors_leaving_its_footprint():
    """A punch moves its footprint rigidly: connectors with both ends in it carry no force in
    that point's experiment and are not in its ring; the connectors with one end in it are.
    The vertex indenter's footprint is the point itself: its ring is the first ring."""
    mesh = box_mesh((3, 3, 2), (0.03, 0.03, 0.02))
    e = mesh.edges
    centre = 22
    first_ring = np.nonzero((e == centre).any(axis=1))[0]
    footprint = np.unique(e[first_ring])  # the centre and its neighbours
    rings = build_rings(mesh, np.array([centre]), [footprint])
    inside = np.isin(e, footprint)
    np.testing.assert_array_equal(rings.members[0], np.nonzero(inside.sum(axis=1) == 1)[0])
    # none of the centre's own connectors is loaded by the punch (all end in the footprint)
    assert not np.isin(first_ring, rings.members[0]).any()
    vertex = build_rings(mesh, np.array([centre]), [np.array([centre])])
    np.testing.assert_array_equal(vertex.members[0], first_ring)
    with pytest.raises(ValueError, match="1 footprints for 2 points"):
        build_rings(mesh, np.array([centre, 4]), [footprint])


def test_local_offsets_stay_within_a_bounded_factor_of_the_global_values():
    bound = np.log(MAX_LOCAL_FACTOR)
    check_offsets("static", [0.99 * bound, 50.0, -50.0])  # alpha/beta offsets are additive
    check_offsets("relaxation", [-0.99 * bound, 0.0, 0.99 * bound, 0.0])
    with pytest.raises(ParameterError,
                       match=r"local static offset 0 is a factor 1e\+04, outside \[1/100, 100\]"):
        check_offsets("static", [2 * bound, 0.0, 0.0])
    with pytest.raises(ParameterError, match=r"relaxation offset 2 is a factor 1e-40"):
        check_offsets("relaxation", [0.0, 0.0, np.log(1e-40), 0.0])
    with pytest.raises(ParameterError, match="offset 1"):
        check_offsets("relaxation", [0.0, np.nan, 0.0, 0.0])


def test_feasibility_refuses_soft_springs_and_swapped_arms():
    strain = StrainRange(-0.3, 0.3)
    ok = GlobalParams(K0=10.0, alpha=0.0, beta=0.0, k1=1.0, tau1=0.5, k2=1.0, tau2=10.0)
    check_feasible(ok.connector_params(5), strain, 1.0)
    # K(eps)/K0 = 1 - 4 eps reaches 0 at eps = 0.25 < 0.3
    soft = GlobalParams(**{**ok.as_dict(), "alpha": -4.0})
    with pytest.raises(ParameterError, match="K\\(eps\\)"):
        check_feasible(soft.connector_params(5), strain, 1.0)
    # K(eps)/K0 = 1 - eps: the tangent 1 - 2 eps falls to 0.4 at eps = 0.3, below a floor of 5 N/m
    softish = GlobalParams(**{**ok.as_dict(), "alpha": -1.0}).connector_params(5)
    check_feasible(softish, strain, 3.0)
    with pytest.raises(ParameterError, match=r"tangent stiffness .* reaches 4 N/m < the floor "
                       r"5 N/m in the strain range \[-0\.3, 0\.3\] \(5 connectors\)"):
        check_feasible(softish, strain, 5.0)
    # K(eps)/K0 = 1 - 2 eps stays positive (0.4 at eps = 0.3) but its force K eps L0 stops
    # rising at eps = 0.25 (tangent 1 - 4 eps): infeasible even without a floor
    snapping = GlobalParams(**{**ok.as_dict(), "alpha": -2.0}).connector_params(5)
    with pytest.raises(ParameterError, match=r"reaches -2 N/m < the floor 0 N/m"):
        check_feasible(snapping, strain, 0.0)
    swapped = GlobalParams(**{**ok.as_dict(), "tau1": 20.0})
    with pytest.raises(ParameterError, match="tau1 >= tau2"):
        check_feasible(swapped.connector_params(5), strain, 1.0)


def test_a_local_update_softening_a_ring_below_the_floor_is_infeasible():
    """Ring offsets act on the connectors of a calibration point only: scaling point 0's
    K0 by 0.08 puts its ring at 8 % of the global K0, below the default floor (10 %), while
    0.12 stays feasible; so is an alpha offset that makes the ring's tangent dip below it."""
    mesh = box_mesh((2, 2, 2), (0.02, 0.02, 0.02))
    rings = build_rings(mesh, np.array([13, 4]))
    glob = GlobalParams(K0=10.0, alpha=0.0, beta=0.0, k1=5.0, tau1=0.5, k2=3.0, tau2=10.0)
    strain = StrainRange(-0.2, 0.4)
    floor = 0.1 * glob.K0
    zr = np.zeros((2, 4))

    def static_offsets(log_factor: float, dalpha: float) -> np.ndarray:
        z = np.zeros((2, 3))
        z[0] = [log_factor, dalpha * strain.scale, 0.0]
        return z

    only_first = np.setdiff1d(rings.members[0], rings.members[1])
    feasible = local_params(glob, rings, strain, static_offsets(np.log(0.12), 0.0), zr)
    assert feasible.K0[only_first] == pytest.approx(1.2)
    check_feasible(feasible, strain, floor)
    with pytest.raises(ParameterError, match=r"reaches 0\.8 N/m < the floor 1 N/m"):
        check_feasible(local_params(glob, rings, strain, static_offsets(np.log(0.08), 0.0), zr),
                       strain, floor)
    # K0 x 0.5 with alpha -1.5 on point 0's own connectors: K(eps) = 5 (1 - 1.5 eps) stays
    # positive (2 N/m at eps = 0.4) but the tangent 5 (1 - 3 eps) reaches -1 N/m; the shared
    # connectors get half the offsets and keep a tangent above 2.8 N/m
    with pytest.raises(ParameterError, match=r"reaches -1 N/m < the floor 1 N/m"):
        check_feasible(local_params(glob, rings, strain, static_offsets(np.log(0.5), -1.5), zr),
                       strain, floor)


def test_local_tuning_keeps_springs_stiff_on_the_gravity_range():
    """Beyond the experiments' strains, local tuning keeps each spring's tangent on its gravity
    release range above the floor, or above the global spring's own minimum there where that
    is lower: K(eps)/K0 = 1 - eps^2 has the tangent 1 - 3 eps^2, 0.88 K0 at eps = 0.2 but
    0.25 K0 at eps = -0.5 (a connector whose release range reaches -0.5)."""
    from calibration.core import local_validity
    from calibration.gradient import Validity
    from calibration.local import LocalParametrisation
    mesh = box_mesh((2, 2, 2), (0.02, 0.02, 0.02))
    rings = build_rings(mesh, np.array([13, 4]))
    glob = GlobalParams(K0=10.0, alpha=0.0, beta=-1.0, k1=5.0, tau1=0.5, k2=3.0, tau2=10.0)
    strain = StrainRange(-0.2, 0.2)
    n = len(mesh.edges)
    low, high = np.full(n, -0.2), np.full(n, 0.2)
    deep = rings.members[0][:2]  # two connectors of point 0's ring reach -0.5 under gravity
    low[deep] = -0.5
    validity = local_validity(Validity(low, high, 5.0, glob.K0, strain.scale),
                              glob.connector_params(n), 10.0)
    np.testing.assert_allclose(validity[2][deep], 2.5)  # the global spring's 0.25 K0 < floor
    np.testing.assert_allclose(np.delete(validity[2], deep), 5.0)
    # the ceiling: 10 x the global spring's largest tangent on each range, K0 at eps = 0
    np.testing.assert_allclose(validity[3], 100.0)
    local = LocalParametrisation(glob, rings, strain, 1.0, np.zeros((2, 3)), np.zeros((2, 4)),
                                 validity)
    local.check(local.params())  # the start is feasible by construction
    stiffer = local.with_offsets("static", [[np.log(1.5), 0.0, 0.0], [0.0, 0.0, 0.0]])
    stiffer.check(stiffer.params())
    # K0 x 0.9 on point 0's ring: the deep connectors' tangent 2.25 N/m < 2.5 N/m
    softer = local.with_offsets("static", [[np.log(0.9), 0.0, 0.0], [0.0, 0.0, 0.0]])
    check_feasible(softer.params(), strain, 1.0)  # fine on the experiments' strains
    with pytest.raises(ParameterError, match=rf"connector {deep[0]}: spring tangent stiffness "
                       r"K0 \+ 2 a eps \+ 3 b eps\^2 reaches 2\.25 N/m < the floor 2\.5 N/m on its "
                       r"validity range \[-0\.5, 0\.2\]"):
        softer.check(softer.params())


def test_local_tuning_keeps_springs_below_a_ceiling_over_the_global_spring():
    """A ring may stiffen up to calibration.stiffness_ceiling times the global spring's largest
    tangent on each connector's range, not beyond: with K(eps)/K0 = 1 + 5 eps^2 on [-0.2, 0.2]
    the global tangent peaks at 1.6 K0 = 16 N/m, so the ceiling 10 is 160 N/m; a K0 factor of 9
    on a ring stays below it (144 N/m), a steep quadratic offset s^2 dbeta = 2 (b/K0 = 55, the
    tangent 1 + 3 x 55 x 0.04 = 7.6 K0, 76 N/m at the global K0) times a K0 factor 2.5 (190
    N/m) does not."""
    from calibration.core import local_validity
    from calibration.gradient import Validity
    from calibration.local import LocalParametrisation
    mesh = box_mesh((2, 2, 2), (0.02, 0.02, 0.02))
    rings = build_rings(mesh, np.array([13, 4]))
    glob = GlobalParams(K0=10.0, alpha=0.0, beta=5.0, k1=5.0, tau1=0.5, k2=3.0, tau2=10.0)
    strain = StrainRange(-0.2, 0.2)
    n = len(mesh.edges)
    validity = local_validity(Validity(np.full(n, -0.2), np.full(n, 0.2), 1.0, glob.K0,
                                       strain.scale), glob.connector_params(n), 10.0)
    np.testing.assert_allclose(validity[3], 160.0)
    local = LocalParametrisation(glob, rings, strain, 1.0, np.zeros((2, 3)), np.zeros((2, 4)),
                                 validity)
    stiffer = local.with_offsets("static", [[np.log(9.0), 0.0, 0.0], [0.0, 0.0, 0.0]])
    stiffer.check(stiffer.params())
    steep = local.with_offsets("static", [[np.log(2.5), 0.0, 2.0], [0.0, 0.0, 0.0]])
    ring = rings.members[0][0]
    with pytest.raises(ParameterError, match=rf"connector {ring}: spring tangent stiffness K0 "
                       r"\+ 2 a eps \+ 3 b eps\^2 reaches 190 N/m > the ceiling 160 N/m on its "
                       r"validity range \[-0\.2, 0\.2\]"):
        steep.check(steep.params())


def test_nelder_mead_records_history_and_converges():
    target = np.array([1.0, -2.0])
    fit = nelder_mead(lambda x: float(np.sum((x - target) ** 2) + 0.5), np.zeros(2),
                      np.full(2, 0.5), name="quadratic", xatol=1e-6, fatol=1e-10,
                      max_evaluations=1000)
    np.testing.assert_allclose(fit.x, target, atol=1e-5)
    assert fit.converged and not fit.warnings
    assert fit.initial_cost == pytest.approx(5.5)
    assert fit.evaluations == len(fit.history.evaluation_cost)
    assert fit.history.evaluation_cost.min() == fit.cost
    assert np.all(np.diff(fit.history.iteration_cost) <= 0)
    assert np.all(np.diff(fit.history.iteration_evaluations) >= 0)


def test_nelder_mead_warns_on_budget_and_no_progress():
    fit = nelder_mead(lambda x: float(np.sum(x ** 2)), np.ones(3), np.full(3, 0.1),
                      name="tiny budget", xatol=1e-9, fatol=1e-12, max_evaluations=6)
    assert not fit.converged and fit.evaluations <= 8
    assert any("budget of 6 evaluations" in w for w in fit.warnings)
    flat = nelder_mead(lambda x: 1.0, np.zeros(2), np.full(2, 0.1), name="flat", xatol=1e-3,
                       fatol=1e-6, max_evaluations=50)
    assert any("did not reduce the cost" in w for w in flat.warnings)


def test_nelder_mead_infeasible_points_cost_inf():
    def cost(x):
        if x[0] < 0.2:
            raise ParameterError("x below 0.2")
        return float((x[0] - 0.1) ** 2)
    fit = nelder_mead(cost, np.array([1.0]), np.array([0.5]), name="bounded", xatol=1e-6,
                      fatol=1e-12, max_evaluations=200)
    assert np.isinf(fit.history.evaluation_cost).any()
    assert fit.x[0] == pytest.approx(0.2, abs=1e-4)  # the feasible optimum is the bound
    # an infeasible start moves to the feasible point of the initial simplex, and says so
    moved = nelder_mead(cost, np.array([0.0]), np.array([0.5]), name="bad start", xatol=1e-6,
                        fatol=1e-12, max_evaluations=200)
    assert moved.x[0] == pytest.approx(0.2, abs=1e-4)
    assert moved.initial_cost == pytest.approx(0.16)  # at 0.5, the first feasible candidate
    assert any("starting point [0.0] is infeasible (x below 0.2); started from the feasible "
               "point [0.5]" in w for w in moved.warnings)
    # further out only where no nearer candidate is feasible: -0.5, 0.5 fail, 1.0 does not
    far = nelder_mead(lambda x: cost(x - 0.6), np.array([0.0]), np.array([0.5]), name="far",
                      xatol=1e-3, fatol=1e-6, max_evaluations=50)
    assert "feasible point [1.0]" in far.warnings[0]
    with pytest.raises(ConvergenceError, match="starting point .* infeasible: x below 0.2 .and "
                       "so is every point up to 4 initial steps"):
        nelder_mead(lambda x: cost(x - 10.0), np.array([0.0]), np.array([0.5]),
                    name="bad start", xatol=1e-3, fatol=1e-6, max_evaluations=10)


def test_gauss_newton_fits_a_relaxation_curve_to_round_off():
    # a two-term exponential decay, the shape of the relaxation curves, in log coordinates;
    # exact data: the optimum is the truth (cost 0) and Gauss-Newton converges quadratically
    t = np.linspace(0.0, 5.0, 40)
    truth = np.log([2.0, 0.4, 1.0, 3.0])

    def curve(y):
        a1, tau1, a2, tau2 = np.exp(y)
        return a1 * np.exp(-t / tau1) + a2 * np.exp(-t / tau2)

    data = curve(truth)

    def residuals(y):
        return curve(y) - data

    fit = gauss_newton(residuals, truth + np.array([0.3, -0.2, 0.2, 0.3]), np.full(4, 0.3),
                       name="decay", xatol=1e-9, fatol=1e-14, max_evaluations=200)
    assert fit.converged and not fit.warnings
    # the forward-difference Jacobian slows the last steps, not the optimum: 1e-8 in log
    np.testing.assert_allclose(fit.x, truth, atol=1e-8)
    assert fit.cost < 1e-16 * fit.initial_cost
    # measured: 26 evaluations; Nelder-Mead from the same start needs 396 for xatol 1e-9
    assert fit.evaluations == len(fit.history.evaluation_cost) < 60
    assert np.all(np.diff(fit.history.iteration_cost) < 0)


def test_gauss_newton_rejects_infeasible_trials_and_warns_on_budget():
    def residuals(x):
        if x[0] < 0.2:
            raise ParameterError("x below 0.2")
        return np.array([x[0] - 0.1, 0.0])
    fit = gauss_newton(residuals, np.array([1.0]), np.array([0.5]), name="bounded", xatol=1e-9,
                       fatol=1e-14, max_evaluations=200)
    assert np.isinf(fit.history.evaluation_cost).any()
    assert 0.2 <= fit.x[0] < 0.21 and fit.cost < fit.initial_cost
    short = gauss_newton(lambda x: np.exp(x) - 1.0, np.ones(2), np.ones(2), name="tiny budget",
                         xatol=1e-12, fatol=1e-16, max_evaluations=5)
    assert not short.converged and any("budget of 5 evaluations" in w for w in short.warnings)
    with pytest.raises(ConvergenceError, match="starting point .* infeasible"):
        gauss_newton(residuals, np.array([0.0]), np.array([0.5]), name="bad start",
                     xatol=1e-3, fatol=1e-6, max_evaluations=10)


def test_gauss_newton_holds_a_coordinate_infeasible_on_both_sides():
    # the start lies on the feasible region's boundary both ways along x[1] (as a ring's
    # spring tangent at its ceiling at both ends of its strain range): the fit holds x[1]
    # and minimises along x[0], instead of stopping the calibration
    def residuals(x):
        if x[1] != 0.5:
            raise ParameterError("x[1] must stay 0.5")
        return np.array([x[0] - 0.3, x[1] - 1.0])
    fit = gauss_newton(residuals, np.array([1.0, 0.5]), np.array([0.5, 0.5]), name="corner",
                       xatol=1e-9, fatol=1e-14, max_evaluations=100)
    assert fit.x[1] == 0.5 and fit.x[0] == pytest.approx(0.3, abs=1e-8)
    assert fit.cost == pytest.approx(0.25, rel=1e-12)


def test_gauss_newton_finishes_on_a_boundary_with_nelder_mead():
    # minimise |x - (2, 2)|^2 on the unit disc: the optimum is on the boundary at (1, 1)/sqrt 2.
    # Every Gauss-Newton step points at (2, 2), out of the disc; damping only shortens it,
    # so the fit stops where its path meets the circle (as a local spring fit stops at the
    # stiffness floor); the Nelder-Mead finish slides along the circle to the optimum
    def residuals(x, radius=1.0):
        if x @ x > radius ** 2:
            raise ParameterError("outside the disc")
        return x - 2.0
    optimum = 2.0 * (2.0 - np.sqrt(0.5)) ** 2
    kw = dict(name="disc", xatol=1e-3, fatol=1e-6, max_evaluations=300)
    start, scale = np.array([-0.5, 0.2]), np.full(2, 0.2)
    stuck = gauss_newton(residuals, start, scale, **kw)
    assert stuck.cost > 1.05 * optimum  # measured 3.616 against 3.343
    fit = gauss_newton(residuals, start, scale, bound_finish=0.5, **kw)
    assert fit.converged and not fit.warnings
    assert fit.cost == pytest.approx(optimum, rel=1e-4)
    np.testing.assert_allclose(fit.x, np.sqrt(0.5), atol=1e-3)
    # one history: the finish's evaluations follow Gauss-Newton's, within the budget
    costs = fit.history.evaluation_cost
    assert stuck.evaluations < fit.evaluations == len(costs) <= 300
    np.testing.assert_array_equal(costs[:stuck.evaluations], stuck.history.evaluation_cost)
    assert fit.cost == costs[np.isfinite(costs)].min()
    assert np.all(np.diff(fit.history.iteration_evaluations) >= 0)
    assert np.all(np.diff(fit.history.iteration_cost) <= 0)
    # a fit that never leaves the region is not touched
    def inside(x):
        return residuals(x, radius=10.0)
    free = gauss_newton(inside, start, scale, **kw)
    same = gauss_newton(inside, start, scale, bound_finish=0.5, **kw)
    np.testing.assert_array_equal(free.x, same.x)
    assert free.evaluations == same.evaluations


def test_van_gelder_global_shape_is_the_baselines_spread_with_mean_one():
    material = MaterialSection()
    mesh = box_mesh((2, 3, 2), (0.03, 0.05, 0.02))
    assert global_shape(mesh, "uniform") is None
    shape = global_shape(mesh, "van_gelder")
    baseline = van_gelder_params(mesh, material)
    np.testing.assert_allclose(shape, baseline.K0 / baseline.K0.mean(), rtol=1e-12)
    # one global set with that shape: every connector scaled, K(eps)/K0 and the times shared
    glob = GlobalParams(K0=10.0, alpha=0.5, beta=2.0, k1=5.0, tau1=0.5, k2=3.0, tau2=10.0,
                        kv=7.0)
    p = glob.connector_params(len(mesh.edges), shape)
    np.testing.assert_allclose(p.K0, 10.0 * shape, rtol=1e-14)
    np.testing.assert_allclose(p.a / p.K0, 0.5, rtol=1e-14)
    np.testing.assert_allclose(p.b1 / p.k1, 0.5, rtol=1e-14)
    np.testing.assert_allclose(p.k2, 3.0 * shape, rtol=1e-14)
    np.testing.assert_array_equal(p.kv, [7.0])  # the volume term is not spread
    # the initial guess: K0 scales the shaped unit network; kv starts at the bulk modulus of
    # the shaped network, sum K0 w L^2 / (9 V)
    top = int(np.argmax(mesh.vertices[:, 2]))
    unit = linear_indentation(mesh, fixed_nodes(mesh, "z", "min", 1e-9), np.array([top]),
                              np.array([[0.0, 0.0, -1.0]]), stiffness=shape)
    g = initial_guess(material, 42.0 * unit.slope, unit.slope, mesh, shape)
    assert g.K0 == pytest.approx(42.0)
    volume = mesh.signed_volumes.sum()
    expected = 42.0 * np.sum(shape * mesh.edge_lengths ** 2) / (9.0 * volume)
    assert g.kv == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ParameterError, match="unknown calibration.global_shape"):
        global_shape(mesh, "voronoi")
    with pytest.raises(ParameterError, match="finite positive factors"):
        glob.connector_params(len(mesh.edges), np.r_[shape[:-1], 0.0])
    with pytest.raises(ParameterError, match="finite positive factors"):
        glob.connector_params(len(mesh.edges) + 1, shape)


def test_initial_guess_is_exact_on_linear_data():
    # F = s d + c d^2 sampled exactly: the two-sample quadratic recovers s
    depths = np.linspace(0.5e-3, 5e-3, 10)
    s, c = np.array([3.0, 5.0]), np.array([100.0, -40.0])
    forces = s[:, None] * depths + c[:, None] * depths ** 2
    np.testing.assert_allclose(fe_initial_slopes(depths, forces), s, rtol=1e-12)
    unit = np.array([0.1, 0.2])
    g = initial_guess(MaterialSection(), 42.0 * unit, unit)
    assert g.K0 == pytest.approx(42.0)
    assert (g.alpha, g.beta) == (0.0, 0.0)
    assert g.k1 == pytest.approx(42.0 * 0.35 / 0.4) and g.tau2 == 10.0


class _SpringCurves:
    """A stand-in evaluation pool: each point's static curve is one spring's force
    K(eps) eps = K0 eps + a eps^2 + b eps^3 at strains ``eps`` (linear in K0, as the
    network's curves are)."""

    def __init__(self, eps):
        self.eps = eps
        self.rtol = None  # the Newton tolerance a fit asked for (None: the evaluators' own)
        self.tolerances = set()  # ... at every curve evaluated

    @contextlib.contextmanager
    def newton_tolerance(self, rtol):
        self.rtol = rtol
        yield
        self.rtol = None

    def curves(self, kind, params, points):
        self.tolerances.add(self.rtol)
        e = self.eps
        row = params.K0[0] * e + params.a[0] * e ** 2 + params.b[0] * e ** 3
        return np.tile(row, (len(points), 1))


def test_global_static_fit_keeps_the_spring_stiff_on_its_feasible_range():
    """A softening truth (beta = -20: tangent 0.4 K0 at eps = 0.1, negative from 0.13) seen
    on strains up to 0.1: fitted on the experiments' range alone the global spring follows
    it; on a feasible range reaching 0.3 (a gravity release), its tangent stays above the
    floor there, as the gradient fit and local tuning then demand of every spring."""
    from calibration.global_fit import fit_static
    from forcecal.scene import CalibrationSection

    eps = np.linspace(0.01, 0.1, 10)
    truth = GlobalParams(K0=30.0, alpha=0.0, beta=-20.0, k1=26.0, tau1=0.5, k2=19.0,
                         tau2=10.0)
    reference = _SpringCurves(eps).curves("indentation", truth.connector_params(1), [0, 1])
    start = dataclasses.replace(truth, K0=25.0, beta=0.0)
    strain, wide = StrainRange(-0.05, 0.1), StrainRange(-0.05, 0.3)
    settings = CalibrationSection(static_max_evaluations=400)
    free, _ = fit_static(_SpringCurves(eps), start, strain, reference, 1, settings,
                         progress=False)
    held, _ = fit_static(_SpringCurves(eps), start, strain, reference, 1, settings,
                         feasible=wide, progress=False)
    # recovered to twice xatol (1e-3 in beta s^2, s = 0.1: 0.1 in beta): the truth is feasible
    assert free.beta == pytest.approx(-20.0, abs=0.2)
    low, _ = held.connector_params(1).extreme_tangent_stiffness(wide.bounds)
    assert low[0] / held.K0 >= 0.1 - 1e-12  # calibration.stiffness_floor, relative to K0
    low_free, _ = free.connector_params(1).extreme_tangent_stiffness(wide.bounds)
    assert low_free[0] < 0  # ... which the experiments' range alone would have allowed


@pytest.mark.parametrize("optimizer", ["nelder-mead", "gauss-newton"])
def test_nelder_mead_fits_compare_curves_at_their_looser_newton_tolerance(optimizer):
    """Nelder-Mead only ranks costs: its curves are solved to NELDER_MEAD_RTOL; Gauss-Newton
    differentiates them (difference quotients) and keeps the evaluators' own tolerance."""
    from calibration.global_fit import NELDER_MEAD_RTOL, fit_static
    from forcecal.scene import CalibrationSection

    eps = np.linspace(0.01, 0.1, 10)
    truth = GlobalParams(K0=30.0, alpha=0.0, beta=5.0, k1=26.0, tau1=0.5, k2=19.0, tau2=10.0)
    pool = _SpringCurves(eps)
    reference = pool.curves("indentation", truth.connector_params(1), [0, 1])
    pool.tolerances.clear()
    fit_static(pool, dataclasses.replace(truth, K0=25.0, beta=0.0), StrainRange(-0.05, 0.1),
               reference, 1, CalibrationSection(), optimizer=optimizer, progress=False)
    assert pool.tolerances == {NELDER_MEAD_RTOL if optimizer == "nelder-mead" else None}
    assert pool.rtol is None  # the block ended
