"""Gradient calibration: adjoint sensitivities against finite differences, parameter recovery of a
smooth per-connector truth made by the particle model itself, cross-validated smoothness weight,
springs kept stiff over the gravity range."""
import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from calibration.core import calibrate
from calibration.gradient import (Coordinates, GradientResult, GroupedRows, Validity,
                                  body_candidates, neighbour_laplacian,
                                  shape_smoothness_factors, shared_laplacian)
from calibration.gradient_solver import (BODY_WEIGHT_GRID, WEIGHT_GRID, Linearisation,
                                         Regulariser, compress, cross_validate, folds_of,
                                         leading_vectors)
from calibration.network import linear_indentation
from calibration.parametrisation import GlobalParams, StrainRange
from calibration.synthetic import box_scene, noisy_params, synthetic_reference
from forcecal.errors import ParameterError
from forcecal.indenter import indenter_footprints
from forcecal.problem import build_problem
from forcecal.scene import replace
from forcecal.schedules import indentation_depths, relaxation_schedule
from particle.model import build_model
from particle.params import PARAM_NAMES, VOLUME_ARM_NAMES, ConnectorParams
from particle.sensitivity import IndentationSensitivity, RelaxationSensitivity
from particle.volume import network_bulk_modulus, tet_edge_connectors

GLOBAL = GlobalParams(K0=30.0, alpha=1.0, beta=10.0, k1=26.0, tau1=0.5, k2=19.0, tau2=10.0)
# two top-face points of the box and a punch radius that holds 7 particles around each and
# stays off the clamped base (the box's edges are 10-21 mm)
PUNCH_POINTS, PUNCH_RADIUS = [0, 8], 0.021
SETTINGS = {"static_max_evaluations": 80, "relaxation_max_evaluations": 160, "workers": 1,
            "method": "gradient"}


def _box(directory, n_calibration=4):
    # the paper's cover (+ far points): the recovery levels below were measured on its points
    points = {"calibration": "cover", "n_calibration": n_calibration, "n_held_out": 8}
    return box_scene(directory, test_points=points,
                     indentation={"depth": 0.002}, relaxation={"depth": 0.002},
                     calibration=SETTINGS)


def smooth_truth(problem, amplitude=0.2) -> ConnectorParams:
    """GLOBAL times smooth factors of the connector midpoints: K0 (hence the whole spring
    K(eps)) and each arm with its own linear trend across the box (the spring's shape
    K(eps)/K0, whose alpha and beta are not identifiable one by one, stays GLOBAL's)."""
    mid = problem.mesh.vertices[problem.mesh.edges].mean(axis=1)
    u, v = mid[:, 0] / 0.06 - 0.5, mid[:, 1] / 0.06 - 0.5
    f, g, h = (np.exp(amplitude * w) for w in (u + v, u - v, v))
    K0 = GLOBAL.K0 * f
    return ConnectorParams(K0=K0, a=GLOBAL.alpha * K0, b=GLOBAL.beta * K0, k1=GLOBAL.k1 * g,
                           b1=GLOBAL.k1 * GLOBAL.tau1 * g * h, k2=GLOBAL.k2 / h,
                           b2=GLOBAL.k2 * GLOBAL.tau2 / h)


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    return _box(tmp_path_factory.mktemp("gradient_box"))


def _sensitivity_evaluators(box, volume, punch):
    """Parameters and both sensitivity evaluators on the box: noisy GLOBAL connectors (and a
    non-uniform kv if ``volume``), two top-face points (each held by a flat punch of 7
    particles if ``punch``), Newton converged to 1e-11 of the force scale."""
    problem = build_problem(box)
    n = len(problem.mesh.edges)
    params = noisy_params(GLOBAL, n, sigma=0.1)
    if volume:  # a non-uniform kv of the order of the springs' own bulk modulus
        n_tets = len(problem.mesh.tets)
        rng = np.random.default_rng(5)
        params = dataclasses.replace(params, kv=800.0 * np.exp(rng.normal(0.0, 0.2, n_tets)))
    if volume == "viscoelastic":  # non-uniform arms of the Prony's size, the springs' times
        factors = np.exp(rng.normal(0.0, 0.2, (4, n_tets)))
        k1, k2 = GLOBAL.k1 / GLOBAL.K0 * params.kv, GLOBAL.k2 / GLOBAL.K0 * params.kv
        params = dataclasses.replace(params, kv1=k1 * factors[0],
                                     bv1=GLOBAL.tau1 * k1 * factors[1], kv2=k2 * factors[2],
                                     bv2=GLOBAL.tau2 * k2 * factors[3])
    model = build_model(problem, box.material.density, params)
    times, relax_depths = relaxation_schedule(box.relaxation)
    pick = PUNCH_POINTS if punch else [0, 1]
    nodes, normals = problem.test_points[pick], problem.normals[pick]
    held = (indenter_footprints(problem.mesh, problem.fixed, nodes, normals, "punch",
                                PUNCH_RADIUS) if punch else None)
    if punch:
        assert min(len(h) for h in held) >= 5
    kw = dict(strain_range=(-0.3, 0.3), rtol=1e-11, footprints=held)
    evaluators = {"indentation": IndentationSensitivity(model, nodes, normals,
                                                        indentation_depths(box.indentation), **kw),
                  "relaxation": RelaxationSensitivity(model, nodes, normals, times, relax_depths,
                                                      **kw)}
    return params, evaluators


VARIANTS = pytest.mark.parametrize(
    "volume, punch", [(False, False), (True, False), (True, True), ("viscoelastic", False),
                      ("viscoelastic", True)],
    ids=["springs", "springs+kv", "springs+kv, punch", "springs+viscoelastic kv",
         "springs+viscoelastic kv, punch"])


def _volume_names(volume) -> tuple[str, ...]:
    """The volume term's parameters of a :func:`_sensitivity_evaluators` variant."""
    return (("kv",) if volume else ()) + (VOLUME_ARM_NAMES if volume == "viscoelastic" else ())


def _jacobian_of(sens, name: str) -> np.ndarray:
    """(P', S, M) the derivatives with respect to parameter ``name`` of every element."""
    if name == "kv":
        return sens.kv
    if name in VOLUME_ARM_NAMES:
        return sens.volume_arms[:, :, VOLUME_ARM_NAMES.index(name)]
    return sens.connectors[:, :, PARAM_NAMES.index(name)]


@VARIANTS
def test_sensitivities_match_finite_differences(box, volume, punch):
    """Directional derivatives J v along a random direction of every parameter of every
    connector (and every tet's kv), against 4th-order central differences of the curves.
    Newton is converged to 1e-11 of the force scale so the differences resolve 1e-8.
    ``punch``: two top-face points held by a flat punch of 7 particles each (the output is
    the sum of the held particles' reactions)."""
    params, evaluators = _sensitivity_evaluators(box, volume, punch)
    rng = np.random.default_rng(0)
    for kind, ev in evaluators.items():
        sens = ev.jacobian(params)
        np.testing.assert_array_equal(sens.forces, ev(params))  # the curves __call__ returns
        assert (sens.kv is not None) == bool(volume)
        assert (sens.volume_arms is not None) == (volume == "viscoelastic")
        for name in PARAM_NAMES + _volume_names(volume):
            value = getattr(params, name)
            direction = rng.normal(size=len(value)) * value
            jac = _jacobian_of(sens, name)
            h = 1e-3

            def at(t):
                return ev(dataclasses.replace(params, **{name: value + t * direction}))

            fd = (8 * (at(h) - at(-h)) - (at(2 * h) - at(-2 * h))) / (12 * h)
            exact = np.einsum("pse,e->ps", jac, direction)
            if kind == "indentation" and name not in ("K0", "a", "b", "kv"):
                assert not exact.any() and not fd.any()  # springs only: no arms
                continue
            assert np.abs(exact).max() > 0, (kind, name)
            assert np.abs(fd - exact).max() <= 1e-6 * np.abs(exact).max(), (kind, name)


@VARIANTS
def test_compiled_adjoint_pass_matches_its_numpy_twin(box, volume, punch):
    """The adjoint pass with the kernels of particle.sensitivity_kernels (sample-major
    adjoints, live samples only) equals the plain numpy/scipy one to round-off."""
    params, evaluators = _sensitivity_evaluators(box, volume, punch)
    for kind, ev in evaluators.items():
        sens = ev.jacobian(params)
        ev.numpy_twin = True
        twin = ev.jacobian(params)
        np.testing.assert_array_equal(sens.forces, twin.forces)
        pairs = [(_jacobian_of(sens, name), _jacobian_of(twin, name), name)
                 for name in PARAM_NAMES + _volume_names(volume)]
        for got, want, name in pairs:
            if kind == "indentation" and name not in ("K0", "a", "b", "kv"):
                assert not got.any() and not want.any()
                continue
            assert np.abs(want).max() > 0, (kind, name)
            assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max(), (kind, name)


@pytest.mark.parametrize("volume, punch", [(False, False), (True, True)],
                         ids=["springs", "springs+kv, punch"])
def test_force_component_sensitivities(box, volume, punch):
    """The indenter force's components along x, y, z (``directions``: 3 S outputs per point,
    direction-major; ``calibration.force_components = "vector"``): the curves are the force
    vectors' components, the derivatives match 4th-order central differences of them (1e-6,
    as above) and the numpy twin (round-off), and along each point's normal they add up
    to the normal curve's derivatives (round-off)."""
    params, evaluators = _sensitivity_evaluators(box, volume, punch)
    axes = np.eye(3)
    rng = np.random.default_rng(1)
    for kind, ev in evaluators.items():
        sens = ev.jacobian(params, directions=axes)
        n_points, n_samples = len(ev.nodes), len(ev.depths)

        def components(p):
            return ev.force_vectors(p).transpose(0, 2, 1).reshape(n_points, 3 * n_samples)

        np.testing.assert_array_equal(sens.forces, components(params))
        normal = ev.jacobian(params)
        along = np.einsum("pdsqe,pd->psqe",
                          sens.connectors.reshape(n_points, 3, n_samples, *normal.connectors
                                                  .shape[2:]), ev.normals)
        scale = np.abs(normal.connectors).max()
        assert np.abs(along - normal.connectors).max() <= 1e-12 * scale, kind
        ev.numpy_twin = True
        twin = ev.jacobian(params, directions=axes)
        ev.numpy_twin = False
        assert np.abs(twin.connectors - sens.connectors).max() <= 1e-12 * scale, kind
        names = ("K0", "k1") if kind == "relaxation" else ("K0",)
        for name in names + (("kv",) if volume else ()):
            value = getattr(params, name)
            direction = rng.normal(size=len(value)) * value
            jac = sens.kv if name == "kv" else sens.connectors[:, :, PARAM_NAMES.index(name)]
            h = 1e-3

            def at(t):
                return components(dataclasses.replace(params, **{name: value + t * direction}))

            fd = (8 * (at(h) - at(-h)) - (at(2 * h) - at(-2 * h))) / (12 * h)
            exact = np.einsum("pse,e->ps", jac, direction)
            for axis in range(3):  # every component moves, not just the normal one
                assert np.abs(exact[:, axis * n_samples:(axis + 1) * n_samples]).max() > 0
            assert np.abs(fd - exact).max() <= 1e-6 * np.abs(exact).max(), (kind, name)
        if volume:
            assert np.abs(twin.kv - sens.kv).max() <= 1e-12 * np.abs(sens.kv).max(), kind


def test_jacobian_reuses_the_forward_pass_of_equal_parameters(box):
    """A Jacobian at the parameters of the last curves starts from their recorded path
    (no forward solve: the fit's linearisation after an accepted trial); at other
    parameters, or after ``forget``, it solves again. Either way the derivatives are
    those of a fresh evaluator to round-off."""
    params, evaluators = _sensitivity_evaluators(box, True, True)
    other = dataclasses.replace(params, K0=params.K0 * 1.1)
    for kind, ev in evaluators.items():
        fresh = ev.jacobian(params)
        solves = []
        ev.force_vectors = lambda p, pts=None, ev=ev: solves.append(1) or type(ev).force_vectors(
            ev, p, pts)
        curves = ev(params)
        sens = ev.jacobian(dataclasses.replace(params))  # equal values, another object
        assert len(solves) == 1, kind  # the __call__ only
        np.testing.assert_array_equal(sens.forces, curves)
        ev(other)
        again = ev.jacobian(params)
        ev.forget()
        cold = ev.jacobian(params)
        assert len(solves) == 4, kind  # other, then params after other, then after forget
        for got in (sens, again, cold):
            scale = np.abs(fresh.connectors).max()
            assert np.abs(got.connectors - fresh.connectors).max() <= 1e-9 * scale, kind
            assert np.abs(got.kv - fresh.kv).max() <= 1e-9 * np.abs(fresh.kv).max(), kind


def test_pattern_kernels_match_the_sparse_pattern_matrix(box):
    """G beta, G^T lam and the kv partials of the kernels against the scipy pattern matrix
    and the numpy twin, at a randomly deformed state of the box (clamped base: connectors
    with a fixed end)."""
    from particle import sensitivity_kernels as kern
    from particle.sensitivity import _Geometry, volume_partials_numpy, volume_pattern_matrix
    from particle.statics import TangentPattern
    problem = build_problem(box)
    params = dataclasses.replace(GLOBAL.connector_params(len(problem.mesh.edges)),
                                 kv=np.full(len(problem.mesh.tets), 800.0))
    model = build_model(problem, box.material.density, params)
    rng = np.random.default_rng(3)
    x = model.rest_positions + rng.normal(0.0, 3e-4, model.rest_positions.shape)
    pat = TangentPattern.of(model)
    assert (pat.node_dof < 0).any()
    geo = _Geometry(model, x)
    unit, dx = np.empty((model.n_connectors, 3)), np.empty(model.n_connectors)
    kern.connector_geometry(x, model.edges, model.rest_lengths, unit, dx)
    np.testing.assert_allclose(unit, geo.unit, rtol=0, atol=1e-15)
    np.testing.assert_allclose(dx, geo.dx, rtol=0, atol=1e-15 * np.abs(geo.dx).max())
    G = geo.pattern_matrix(pat)
    end_dofs = pat.node_dof[model.edges]
    beta = rng.normal(size=(3, model.n_connectors))
    lam = rng.normal(size=(3, pat.n_dofs))
    got = np.empty((3, pat.n_dofs))
    kern.pattern_product(end_dofs, geo.unit, beta, got)
    np.testing.assert_array_equal(got, (G @ beta.T).T)
    tau = np.empty((3, model.n_connectors))
    kern.pattern_transpose_product(end_dofs, geo.unit, lam, tau)
    np.testing.assert_array_equal(tau, (G.T @ lam.T).T)
    cols = np.array([0, 2])
    jac_kv = np.zeros((3, model.n_tets))
    pressure, strain = np.empty((2, model.n_tets)), np.empty(model.n_tets)
    tet_dofs = pat.node_dof[model.tets]
    kern.add_volume_partials(x, model.tets, tet_dofs, model.rest_volumes, cols, lam[cols],
                             jac_kv, pressure, strain)
    want = volume_partials_numpy(model, x, pat, lam.T)
    assert not jac_kv[1].any()
    np.testing.assert_allclose(jac_kv[cols], want[cols], rtol=0,
                               atol=1e-12 * np.abs(want).max())
    # the tets' pressure adjoints and the forces of pressures: the volume pattern matrix
    H = volume_pattern_matrix(model, x, pat)
    want = (H.T @ lam[cols].T).T
    np.testing.assert_allclose(pressure, want, rtol=0, atol=1e-12 * np.abs(want).max())
    gamma = rng.normal(size=(2, model.n_tets))
    got = rng.normal(size=(2, pat.n_dofs))
    want = got + (H @ (gamma / model.rest_volumes).T).T
    kern.add_volume_pattern_product(x, model.tets, tet_dofs, model.rest_volumes, gamma, got)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("n_tets", [0, 4])
def test_coordinates_chain_rule(n_tets):
    """Coordinates <-> parameters round trip, and the chain rule against differences."""
    n = 5
    coords = Coordinates(0.1, n, n_tets)
    start = GLOBAL.connector_params(n)
    if n_tets:
        start = dataclasses.replace(start, kv=np.full(n_tets, 900.0))
    theta = coords.theta_of(start) + np.random.default_rng(1).normal(0, 0.1, coords.size)
    p = coords.params(theta)
    np.testing.assert_allclose(coords.theta_of(p), theta, rtol=1e-12, atol=1e-14)
    rng = np.random.default_rng(2)
    jac_p = rng.normal(size=(3, 7, n))  # any linear functional of the parameters
    jac_kv = rng.normal(size=(3, n_tets)) if n_tets else None

    def value(t):
        q = coords.params(t)
        out = np.einsum("sqe,qe->s", jac_p, np.array([getattr(q, m) for m in PARAM_NAMES]))
        return out + (jac_kv @ q.kv if n_tets else 0.0)

    got = coords.chain(jac_p, jac_kv, p)
    for i in range(coords.size):
        d = np.zeros(coords.size)
        d[i] = 1e-6
        fd = (value(theta + d) - value(theta - d)) / 2e-6
        np.testing.assert_allclose(got[:, i], fd, rtol=1e-6, atol=1e-9)


def test_coordinates_with_a_fixed_kv_carry_it_and_fit_the_connectors_only():
    """``calibration.kv_per_tet = false``: no kv coordinates, every parameter set carries the
    global kv as it is."""
    n = 5
    kv = np.array([900.0])
    coords = Coordinates(0.1, n, 0, {"kv": kv})
    start = dataclasses.replace(GLOBAL.connector_params(n), kv=kv)
    assert coords.size == 7 * n
    theta = coords.theta_of(start) + np.random.default_rng(1).normal(0, 0.1, coords.size)
    p = coords.params(theta)
    assert p.kv.tolist() == [900.0]
    np.testing.assert_allclose(coords.theta_of(p), theta, rtol=1e-12, atol=1e-14)
    jac_p = np.random.default_rng(2).normal(size=(3, 7, n))
    assert coords.chain(jac_p, np.ones((3, 4)), p).shape == (3, 7 * n)  # kv's ignored


def test_pulled_back_fit_moves_along_the_fits_coordinates():
    """The gravity check's pull-back of a gradient fit (calibration.gravity_check): a fraction
    f of the way from the global fit in the fit's coordinates: 1 is the fit, 0 the global
    fit, and K0, k_i, tau_i, kv move geometrically, alpha s and beta s^2 linearly."""
    n, n_tets = 5, 3
    coords = Coordinates(0.1, n, n_tets)
    start = dataclasses.replace(GLOBAL.connector_params(n), kv=np.full(n_tets, 900.0))
    theta0 = coords.theta_of(start)
    theta = theta0 + np.random.default_rng(3).normal(0, 0.3, coords.size)
    fit = coords.params(theta)
    state = dataclasses.make_dataclass("State", ["theta"])(theta)
    result = GradientResult(fit, 1.0, (1.0,), np.zeros((1, 1)), state, 1, (1.0,), coords, theta0)
    assert result.pulled_back(1.0) is fit
    back = result.pulled_back(0.0)
    for name in (*PARAM_NAMES, "kv"):
        np.testing.assert_allclose(getattr(back, name), getattr(start, name), rtol=1e-12,
                                   atol=1e-12)
    half = result.pulled_back(0.5)
    for name in ("K0", "k1", "k2", "kv"):
        np.testing.assert_allclose(getattr(half, name),
                                   np.sqrt(getattr(start, name) * getattr(fit, name)), rtol=1e-12)
    np.testing.assert_allclose(half.a / half.K0, 0.5 * (start.a / start.K0 + fit.a / fit.K0),
                               rtol=1e-12)


def _recovery(problem, truth: ConnectorParams, result):
    """What the recovery tests check, per experiment (indentation, relaxation): the calibrated
    curves' largest error at the calibration points, and at the held-out points as a fraction
    of the global fit's; per connector the largest relative error of K(eps) over the strains
    the experiments reach (linear network at full depth); the arms' median relative errors.

    The connectors between two clamped particles (33 of the box's 197) are left out of the
    spring errors: they never change length, so no experiment (nor gravity) tests their K and
    their fitted values are whatever the smoothness prior fills in (4.5 % median, 10.5 % max
    with ``shape_smoothness`` 100, where they held the maximum)."""
    got = result.connectors["calibrated"]
    n_cal = len(problem.calibration)
    errors = {v: result.variants[v].errors for v in ("global", "calibrated")}
    experiments = ("indentation", "relaxation")
    calibrated = [errors["calibrated"][e][:n_cal].max() for e in experiments]
    held_out_ratio = [errors["calibrated"][e][n_cal:].max() / errors["global"][e][n_cal:].max()
                      for e in experiments]
    reach = np.abs(linear_indentation(problem.mesh, problem.fixed, problem.test_points,
                                      problem.normals).strain[:n_cal]).max(axis=0)
    eps = np.linspace(-1.0, 1.0, 21)[None, :] * (0.002 * reach)[:, None]
    K = lambda p: p.K0[:, None] + p.a[:, None] * eps + p.b[:, None] * eps ** 2  # noqa: E731
    clamped = np.zeros(len(problem.mesh.vertices), dtype=bool)
    clamped[problem.fixed] = True
    tested = ~clamped[problem.mesh.edges].all(axis=1)
    assert np.all(reach[tested] > 0) and not reach[~tested].any()
    spring = np.abs(K(got) / K(truth) - 1.0).max(axis=1)[tested]
    arms = {name: float(np.median(np.abs(getattr(got, name) / getattr(truth, name) - 1.0)))
            for name in ("k1", "tau1", "k2", "tau2")}
    return calibrated, held_out_ratio, spring, arms


def _recovery_run(d, volume: bool | str, **settings):
    """Smooth non-uniform truth on the box (:func:`smooth_truth`; with ``volume`` plus a
    smooth per-tet kv around the springs' own bulk modulus, and with ``"viscoelastic"``
    smooth per-tet volume arms around the Prony ratios, with the springs' global times), 20
    calibration points (every free surface vertex but the 8 held out), fitted by the
    gradient method from a short global fit with the ``[calibration]`` ``settings``."""
    scene = replace(_box(d, n_calibration=20),
                    calibration={"static_max_evaluations": 40, "relaxation_max_evaluations": 60,
                                 **settings})
    if volume:
        scene = replace(scene, particle={"volume": volume})
    problem = build_problem(scene)
    truth = smooth_truth(problem)
    if volume:
        centre = problem.mesh.vertices[problem.mesh.tets].mean(axis=1)
        u, v = centre[:, 0] / 0.06 - 0.5, centre[:, 1] / 0.06 - 0.5
        kv = network_bulk_modulus(problem.mesh, GLOBAL.K0) * np.exp(0.2 * (u - 0.5 * v))
        truth = dataclasses.replace(truth, kv=kv)
    if volume == "viscoelastic":
        kv1, kv2 = 0.5 * kv * np.exp(0.2 * (v - u)), 0.9 * kv * np.exp(0.2 * (u + v))
        truth = dataclasses.replace(truth, kv1=kv1, bv1=GLOBAL.tau1 * kv1, kv2=kv2,
                                    bv2=GLOBAL.tau2 * kv2)
    synthetic_reference(scene, truth, d / "reference.h5")
    result = calibrate(scene, d / "reference.h5", d / "params.h5", progress=False)
    return scene, problem, truth, result


@pytest.fixture(scope="module")
def recovered(tmp_path_factory):
    """:func:`_recovery_run` of the springs, default settings."""
    return _recovery_run(tmp_path_factory.mktemp("recovery"), volume=False)


def test_gradient_recovers_smooth_truth(recovered):
    """Measured (box, 20 calibration points, 197 connectors x 7 parameters): calibration curves
    to 0.08 % / 0.09 % (max), held-out to 2.5 % / 1.6 % where the global fit has 10.8 % / 4.8 %;
    K(eps) over each connector's strains reached (linear network at full depth) within 4.5 %
    (median) and 11.9 % (max) of the truth, K0 within 2.7 % (median), the arms' k_i, tau_i within
    0.6-2.7 % (median). A goal of 2 % on every connector's K(eps) is not reached: 20 surface
    curves (1000 samples, far fewer independent ones) do not determine 1148 per-connector
    parameters; the smoothness prior fills in what they leave open (asserted with ~1.5x margins)."""
    scene, problem, truth, result = recovered
    got = result.connectors["calibrated"]
    calibrated, held_out_ratio, spring, arms = _recovery(problem, truth, result)
    assert max(calibrated) < 0.002 and max(held_out_ratio) < 0.5
    assert np.median(spring) < 0.07 and spring.max() < 0.2
    assert max(arms.values()) < 0.05, arms
    assert 0 < result.gradient["weight"] < max(result.gradient["grid"])
    # every spring stays above the stiffness floor on the calibrated strain range (no gravity
    # run in a synthetic reference, so that is the range the fit kept)
    n = len(got.K0)
    Validity(np.full(n, result.strain.low), np.full(n, result.strain.high),
             0.1 * result.global_params.K0, result.global_params.K0, result.strain.scale
             ).check(got)


@pytest.fixture(scope="module")
def recovered_volume(tmp_path_factory):
    """:func:`_recovery_run` with the volume term (kv globally, then per tet with the
    connectors), default settings."""
    return _recovery_run(tmp_path_factory.mktemp("recovery_volume"), volume=True)


def test_gradient_recovers_smooth_truth_with_the_volume_term(recovered_volume):
    """A smooth per-connector + kv truth. Measured (box, 20 calibration points, 197
    connectors x 7 + 108 tets = 1487 parameters): calibration curves to 0.13 % / 0.09 %
    (max), held-out to 1.8 % / 1.2 % where the global fit has 3.9 % / 4.0 %; kv within
    1.8 % (median) and 10 % (max) of the truth, the arms' k_i, tau_i within 0.8-3.3 %
    (median), but K(eps) only within 8.7 % (median) and 33 % (max): a connector's spring and
    its tets' kv both stiffen the same surface curves, which pin their sum better than
    either (springs alone: 4.5 % / 11.9 %, the test above). A goal of 2 % on K(eps) is
    missed; asserted at the measured levels with ~1.3-1.5x margins."""
    scene, problem, truth, result = recovered_volume
    _assert_recovered_with_kv(problem, truth, result, held_out=0.6, kv=(0.025, 0.15),
                              spring=(0.11, 0.45), arms=0.05)
    assert 0 < result.gradient["weight"] < max(result.gradient["grid"])


def test_gradient_recovers_smooth_truth_with_the_viscoelastic_volume_term(tmp_path):
    """The same truth with smooth per-tet volume arms (kv1 around 0.5 kv, kv2 around 0.9 kv,
    each with its own trend, the springs' global times; the start: the Prony ratios 0.875
    and 0.625). Measured (box, 20 calibration points, 197 connectors x 7 + 108 tets x 3 =
    1703 parameters): calibration curves to 0.14 % / 0.11 % (max), held-out 0.50x / 0.29x
    the global fit's, kv within 1.9 % (median) and 11 % (max) of the truth, the volume arms'
    kv1, kv2 within 3.4 % / 3.6 % (median) and 10 % / 11 % (max), the springs' arms within
    1.7-3.5 % (median), K(eps) 9.0 % / 35 %: as with the elastic term, surface curves pin a
    connector's spring and its tets' volume term as a sum. Asserted with ~1.3-1.5x margins."""
    scene, problem, truth, result = _recovery_run(tmp_path, "viscoelastic")
    _assert_recovered_with_kv(problem, truth, result, held_out=0.7, kv=(0.03, 0.16),
                              spring=(0.13, 0.5), arms=0.05)
    got = result.connectors["calibrated"]
    for name in ("kv1", "kv2"):
        error = np.abs(getattr(got, name) / getattr(truth, name) - 1.0)
        assert np.median(error) < 0.05 and error.max() < 0.16, name
    # the volume arms' times are the global fit's (not fitted per tet)
    np.testing.assert_allclose(got.volume_arm_tau, [[result.global_params.tau1,
                                                     result.global_params.tau2]] * len(got.kv),
                               rtol=1e-12)


def _assert_recovered_with_kv(problem, truth, result, *, held_out, kv, spring, arms):
    """:func:`_recovery` within these bounds: calibration curves within 0.2 % (max),
    held-out within ``held_out`` x the global fit's, kv and K(eps) within (median, max)
    relative errors ``kv`` and ``spring``, the arms' medians within ``arms``."""
    calibrated, held_out_ratio, spring_error, arms_error = _recovery(problem, truth, result)
    assert max(calibrated) < 0.002 and max(held_out_ratio) < held_out
    kv_error = np.abs(result.connectors["calibrated"].kv / truth.kv - 1.0)
    assert np.median(kv_error) < kv[0] and kv_error.max() < kv[1]
    assert np.median(spring_error) < spring[0] and spring_error.max() < spring[1]
    assert max(arms_error.values()) < arms, arms_error


def test_the_force_vector_recovers_the_truth_with_the_volume_term(tmp_path):
    """``calibration.force_components = "vector"`` on the same truth as the test above (the
    synthetic reference's force vectors, made by the particle model itself). Measured: the
    calibration curves to 0.09 % / 0.12 % (max), held-out 0.38x / 0.26x the global fit's,
    kv within 1.4 % (median) and 8.4 % (max) of the truth (normal force alone: 1.8 / 10 %),
    the arms within 0.6-2.4 %, K(eps) within 6.6 % (median, against 8.7 %) and 39 % (max,
    against 33 %): the tangential reactions help tell a spring from its tets' kv, but do
    not pin every connector (the cross-validation picks the grid's smallest smoothness
    weight, 1e-4, with three times the rows). Asserted with ~1.3-1.5x margins."""
    scene, problem, truth, result = _recovery_run(tmp_path, volume=True,
                                                  force_components="vector")
    assert result.settings["calibration"]["force_components"] == "vector"
    _assert_recovered_with_kv(problem, truth, result, held_out=0.5, kv=(0.02, 0.12),
                              spring=(0.09, 0.55), arms=0.04)


@pytest.mark.parametrize("volume", [False, True], ids=["springs", "springs+kv"])
def test_one_spring_shape_recovers_the_truth_whose_shape_is_one(tmp_path, volume):
    """The truth of :func:`smooth_truth` gives every connector the same spring shape
    ``K(eps)/K0`` (a material's strain stiffening), and the uniform global fit does not find
    it (alpha -4.7, beta -25 against 1 and 10: one shape makes up for the non-uniform K0).
    ``calibration.shape_smoothness = 100`` (smoothness of alpha, beta 100x the others',
    their common value free) lets the fit move every shape together. Measured:

    * springs: K(eps) within 1.73 % (median, within a goal of 2 %) and 7.0 % (max, a connector
      strained 16x less than the most strained: the least strained fifth 4.1 % median) of
      the truth, against 4.5 % / 11.9 % by default; the median shape alpha 0.996, beta 9.87;
      calibration curves 0.002 % (max), held-out 0.21x / 0.30x the global fit's; the fit
      converges (the same result with 30 or 60 iterations), so what is left is what 20
      surface curves do not determine, filled in by the smoothness prior;
    * springs + kv (30 iterations: with 12 the fit stops on its way, K(eps) 6.5 %, held-out
      0.93x): K(eps) 2.9 % / 7.4 %, kv 1.1 % / 5.9 %, against 8.7 % / 33 % and 1.8 % / 10 %
      by default; held-out 0.48x / 0.30x the global fit's (0.47x / 0.29x by default).

    Asserted with ~1.3-1.5x margins. Not the scenes' default: on the punch scene the fold
    cross-validation of whole calibrations finds no difference (docs/calibration.md)."""
    settings = {"shape_smoothness": 100.0}
    if volume:
        settings["gradient_max_iterations"] = 30
    scene, problem, truth, result = _recovery_run(tmp_path, volume, **settings)
    calibrated, held_out_ratio, spring, arms = _recovery(problem, truth, result)
    assert max(calibrated) < 0.002 and max(held_out_ratio) < 0.6
    got = result.connectors["calibrated"]
    assert np.ptp(got.a / got.K0) < 0.2 * abs(result.global_params.alpha)  # nearly one shape
    if volume:
        kv_error = np.abs(got.kv / truth.kv - 1.0)
        assert np.median(kv_error) < 0.015 and kv_error.max() < 0.08
        assert np.median(spring) < 0.04 and spring.max() < 0.11
    else:
        assert np.median(spring) < 0.025 and spring.max() < 0.1
    assert max(arms.values()) < 0.03, arms


def test_a_global_kv_stays_global_while_the_connectors_are_fitted(tmp_path):
    """``calibration.kv_per_tet = false`` on the volume truth of :func:`recovered_volume` but
    with one kv for every tet (the springs' own bulk modulus): the gradient fit moves every
    connector and keeps the global fit's kv (2.6 % below the truth after its 40 evaluations),
    one value, in the calibrated parameters. Measured: calibration curves 0.12 % / 0.09 %
    (max) where the global fit has 6.4 % / 5.2 %, held-out 1.6 % / 1.2 % where it has 4.0 % /
    4.0 %; asserted with ~1.5-3x margins."""
    scene = replace(_box(tmp_path, n_calibration=20), particle={"volume": True},
                    calibration={"static_max_evaluations": 40, "relaxation_max_evaluations": 60,
                                 "kv_per_tet": False})
    problem = build_problem(scene)
    truth = dataclasses.replace(smooth_truth(problem), kv=np.array(
        [network_bulk_modulus(problem.mesh, GLOBAL.K0)]))
    synthetic_reference(scene, truth, tmp_path / "reference.h5")
    result = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5", progress=False)
    got = result.connectors["calibrated"]
    assert got.kv.tolist() == [result.global_params.kv]
    assert np.ptp(np.log(got.K0)) > 0.1  # the connectors did move apart
    n_cal = len(problem.calibration)
    for experiment in ("indentation", "relaxation"):
        errors = {v: result.variants[v].errors[experiment] for v in ("global", "calibrated")}
        assert errors["calibrated"][:n_cal].max() < 0.05 * errors["global"][:n_cal].max()
        assert errors["calibrated"][n_cal:].max() < 0.6 * errors["global"][n_cal:].max()


def test_the_prior_ratio_trades_smoothness_for_the_pull_towards_the_global_fit(recovered,
                                                                              tmp_path):
    """``calibration.prior_ratio`` reaches the regulariser ``lambda (L + rho I)``: the fit of
    :func:`recovered` again with rho = 1e6 instead of 1e-3. Cross-validation then picks the
    smallest weight, and the pull towards the global fit dominates the smoothness: log K0
    deviates from the global fit 9x less (norm 0.17 against 1.62) and 9x more roughly
    (``d^T L d / d^T d`` 0.59 against 0.065). Asserted with ~2x margins."""
    _, problem, _, default = recovered
    scene = replace(_box(tmp_path, n_calibration=20),
                    calibration={"static_max_evaluations": 40, "relaxation_max_evaluations": 60,
                                 "prior_ratio": 1e6})
    synthetic_reference(scene, smooth_truth(problem), tmp_path / "reference.h5")
    strong = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5", progress=False)
    lap = neighbour_laplacian(problem.mesh.edges, problem.mesh.n_vertices)

    def deviation(result):
        d = np.log(result.connectors["calibrated"].K0 / result.global_params.K0)
        return np.linalg.norm(d), d @ (lap @ d) / (d @ d)

    (norm, rough), (norm_strong, rough_strong) = deviation(default), deviation(strong)
    assert norm_strong < 0.2 * norm and rough_strong > 4.0 * rough


def _linear_case(problem, seed: int = 3):
    """A smooth truth seen through random point-local sensitivities (12 points x 40 samples,
    like relaxation curves), with noise of 0.3 x the signal: (truth (7 E,), Jacobian,
    residuals at theta = 0, rows per point, regulariser)."""
    edges = problem.mesh.edges
    n = len(edges)
    lap = neighbour_laplacian(edges, problem.mesh.n_vertices)
    rng = np.random.default_rng(seed)
    mid = problem.mesh.vertices[edges].mean(axis=1)
    truth = np.zeros((7, n))
    truth[0] = 0.3 * np.sin(np.pi * mid[:, 0] / 0.06) * np.cos(np.pi * mid[:, 1] / 0.06)
    theta0 = np.zeros(7 * n)
    n_points, rows = 12, 40
    J = np.zeros((n_points * rows, 7 * n))
    centres = rng.choice(problem.mesh.n_vertices, n_points, replace=False)
    for p, c in enumerate(centres):  # each point senses the connectors around one vertex
        near = np.exp(-np.sum((mid - problem.mesh.vertices[c]) ** 2, axis=1) / 0.02 ** 2)
        J[p * rows:(p + 1) * rows, :n] = 0.05 * rng.normal(size=(rows, n)) * near
    signal = J @ truth.ravel()
    r = -signal + 0.3 * signal.std() * rng.normal(size=len(J))  # residuals at theta0 = 0
    return truth.ravel(), J, r, rows, Regulariser(lap, theta0)


def test_cross_validation_picks_a_finite_weight(box):
    """Linear synthetic case (:func:`_linear_case`). Too little smoothing fits the noise and
    too much flattens the truth; both predict the held-back folds worse than the weight CV
    picks (inside the grid)."""
    truth, J, r, rows, reg = _linear_case(build_problem(box))
    n_points = len(r) // rows
    weight, body_weight, costs = cross_validate(
        Linearisation.of(reg.theta0, r, J, reg), np.repeat(np.arange(n_points), rows), reg,
        folds_of(n_points, 4))
    assert costs.shape[0] == 1 and body_weight == 0.0  # no whole-body rows: no body weight
    costs = costs[0]
    best = int(np.argmin(costs))
    assert 0 < best < len(costs) - 1
    # measured: the ends of the grid predict the folds 3.8x and 6.0x worse than weight 1
    assert costs[0] > 2.0 * costs[best] and costs[-1] > 2.0 * costs[best]


def test_cross_validation_scores_are_refits_without_each_group(box):
    """The scores against brute force: for each group left out (a fold of points, a
    whole-body item, one never trained), the regularised Gauss-Newton step fitted to the
    other rows (body rows weighted, the prior centred at theta0) by a dense solve of its
    normal equations, its prediction of the group's rows squared (body items scaled by
    points / items). Equal to 1e-8 (the block-inverse identity is exact)."""
    _, J, r, rows, reg = _linear_case(build_problem(box))
    rng = np.random.default_rng(7)
    n_points = 4  # of the 12: the dense solves stay small
    J, r = J[:n_points * rows], r[:n_points * rows]
    J_body = 0.03 * rng.standard_normal((3 * 4, J.shape[1]))
    r_body = 0.05 * rng.standard_normal(len(J_body))
    groups = np.r_[np.repeat(np.arange(n_points), rows), -1 - np.repeat(np.arange(3), 4)]
    trained = np.r_[np.ones(len(r), bool), np.repeat([True, True, False], 4)]
    theta = reg.theta0 + 0.01 * rng.standard_normal(len(reg.theta0))
    lin = Linearisation.of(theta, np.r_[r, r_body], np.vstack([J, J_body]), reg)
    folds = folds_of(n_points, 2)
    grid, body_grid = (0.1, 3.0), (0.0, 2.0)
    _, _, costs = cross_validate(lin, groups, reg, folds, grid, body_grid, trained)
    A1 = reg.metric.toarray()
    body = groups < 0
    tests = [(np.isin(groups, f) & ~body, 1.0) for f in folds]
    tests += [(groups == -1 - k, n_points / 3) for k in range(3)]
    for b, w in enumerate(body_grid):
        for g, alpha in enumerate(grid):
            total = 0.0
            for test, share in tests:
                weight = np.where(body, w, 1.0) * trained * ~test  # rows that train
                Jw = lin.J * np.sqrt(weight)[:, None]
                d = np.linalg.solve(Jw.T @ Jw + alpha * A1,
                                    -(Jw.T @ (np.sqrt(weight) * lin.r)
                                      + alpha * A1 @ (theta - reg.theta0)))
                predicted = lin.r[test] + lin.J[test] @ d
                total += share * float(predicted @ predicted)
            assert costs[b, g] == pytest.approx(total, rel=1e-8)


def test_left_out_residual_makes_compressed_scores_those_of_the_whole_rows(box):
    """The candidates' scores on compressed rows plus their ``left_out``
    (:attr:`GroupedRows.scored_left_out`) equal the scores of the uncompressed rows (to
    1e-9): each point's and item's Jacobian has rank <= the rows kept, so the compression
    moves no prediction and leaves out a residual no step changes. Without the constant the
    two differ (by ~0.4 of the score here): what two models' scores would carry."""
    _, J, r, rows, reg = _linear_case(build_problem(box))
    rng = np.random.default_rng(5)
    n_points, keep, items, per_item = 4, 6, 3, 8
    low_rank = [rng.standard_normal((rows, 3)) @ J[p * rows:p * rows + 3]
                for p in range(n_points)]  # rank 3 per point
    J_points, r_points = np.vstack(low_rank), r[:n_points * rows]
    J_body = np.vstack([rng.standard_normal((per_item, 2)) @ (0.03 * rng.standard_normal(
        (2, J.shape[1]))) for _ in range(items)])  # rank 2 per item
    r_body = 0.05 * rng.standard_normal(items * per_item)
    groups = np.r_[np.repeat(np.arange(n_points), rows), -1 - np.repeat(np.arange(items),
                                                                          per_item)]
    whole = GroupedRows(np.r_[r_points, r_body], np.vstack([J_points, J_body]), 0.0, 0.0,
                        groups, np.ones(len(groups), bool))
    r_c, J_c, left = compress(r_points, J_points, rows, keep)
    rb_c, Jb_c, body_left = compress(r_body, J_body, per_item, keep // 2)
    compressed = GroupedRows(np.r_[r_c, rb_c], np.vstack([J_c, Jb_c]), left, body_left,
                             np.r_[np.repeat(np.arange(n_points), keep),
                                   -1 - np.repeat(np.arange(items), keep // 2)],
                             np.ones(n_points * keep + items * (keep // 2), bool), body_left)
    theta = reg.theta0 + 0.01 * rng.standard_normal(len(reg.theta0))
    kinds = ["loads", "modes", "loaded_modes"]
    folds, grid, body_grid = folds_of(n_points, 2), (0.1, 3.0), (0.0, 2.0)
    scores = [body_candidates(Linearisation.of(theta, g.r, g.J, reg, g.left), g, reg, folds,
                              grid, body_grid, kinds) for g in (whole, compressed)]
    assert compressed.scored_left_out == pytest.approx(left + n_points / items * body_left)
    for name, exact in scores[0].items():
        assert exact["left_out"] == 0.0
        approx = scores[1][name]
        assert approx["score"] + approx["left_out"] == pytest.approx(exact["score"], rel=1e-9)
        assert approx["score"] < 0.9 * exact["score"]


@pytest.mark.parametrize("consistent", [True, False], ids=["same truth", "noise"])
def test_cross_validation_weighs_whole_body_data_that_predict_the_rest(box, consistent):
    """The linear case plus 4 whole-body items of 8 rows, each a smooth global functional of
    the connectors' K0 (a cosine over the box, as a load or a mode weighs the whole body).
    Made by the same truth (with 5 % noise) they predict each other and the points' folds
    better when fitted: measured, the score is 2.8x lower at the chosen body weight 3 than
    without them (asserted: > 0 and 2x); made of noise, fitting them predicts nothing: the
    best score is within 1.2 % of the score without them (asserted 3 %; the weight picked,
    0.1, is chance). The rows of items of another kind (``trained`` False) are predicted,
    never fitted: with every item so, the weight is 0."""
    problem = build_problem(box)
    truth, J, r, rows, reg = _linear_case(problem)
    n_points, n = len(r) // rows, len(problem.mesh.edges)
    mid = problem.mesh.vertices[problem.mesh.edges].mean(axis=1)
    rng = np.random.default_rng(11)
    items, per_item = 4, 8
    wave = rng.uniform(0.0, 2.0 * np.pi / 0.06, size=(items * per_item, 2))
    phase = rng.uniform(0.0, 2.0 * np.pi, items * per_item)
    J_body = np.zeros((items * per_item, J.shape[1]))
    J_body[:, :n] = 0.03 * np.cos(wave @ mid[:, :2].T + phase[:, None])
    signal = J_body @ truth
    r_body = (-signal + 0.05 * signal.std() * rng.normal(size=len(signal)) if consistent
              else signal.std() * rng.normal(size=len(signal)))
    groups = np.r_[np.repeat(np.arange(n_points), rows), -1 - np.repeat(np.arange(items),
                                                                          per_item)]
    lin = Linearisation.of(reg.theta0, np.r_[r, r_body], np.vstack([J, J_body]), reg)
    grid = BODY_WEIGHT_GRID
    weight, body_weight, costs = cross_validate(lin, groups, reg, folds_of(n_points, 4),
                                                body_grid=grid)
    assert costs.shape == (len(grid), len(WEIGHT_GRID)) and grid[0] == 0.0
    if consistent:
        assert body_weight > 0 and costs.min() < costs[0].min() / 2.0
    else:
        assert costs.min() > 0.97 * costs[0].min()
    _, unused, _ = cross_validate(lin, groups, reg, folds_of(n_points, 4), body_grid=grid,
                                  trained=groups >= 0)
    assert unused == 0.0


@pytest.mark.parametrize("smoothness", [None, shape_smoothness_factors(100.0)],
                         ids=["one block", "shape x100"])
def test_regulariser_solve_and_sandwich_are_the_metric_inverse_on_both_paths(box, monkeypatch,
                                                                            smoothness):
    # the block solve (seven connector coordinates sharing one block, or three runs of blocks
    # when the shape's two have their own smoothness factor, then the tets) against a sparse
    # LU of the whole metric, for dense and sparse right-hand sides, with the blocks inverted
    # densely (the default at this size) and by their own sparse LU
    from scipy.sparse.linalg import splu
    import calibration.gradient_solver as solver

    mesh = build_problem(box).mesh
    size = 7 * len(mesh.edges) + len(mesh.tets)
    rng = np.random.default_rng(5)
    dense = rng.normal(size=(size, 9))
    sparse = sp.random(size, 6, density=0.01, random_state=6, format="csc")
    for limit in (solver.DENSE_INVERSE_LIMIT, 0):
        monkeypatch.setattr(solver, "DENSE_INVERSE_LIMIT", limit)
        reg = Regulariser(neighbour_laplacian(mesh.edges, mesh.n_vertices), np.zeros(size),
                          shared_laplacian(mesh.tets, mesh.n_vertices, 3), smoothness=smoothness)
        assert len(reg._blocks) == (2 if smoothness is None else 4)
        e, lap = len(mesh.edges), reg.laplacian
        for q, factor in enumerate(np.ones(7) if smoothness is None else smoothness):
            block = reg.metric[q * e:(q + 1) * e, q * e:(q + 1) * e]
            want = (factor * lap + reg.prior_ratio * sp.identity(e)) / e
            assert abs(block - want).max() <= 1e-14 * abs(want).max()
        lu = splu(reg.metric)
        want = lu.solve(dense)
        got = reg.solve(dense)
        assert np.max(np.abs(got - want)) <= 1e-10 * np.max(np.abs(want))
        # the sparse rows' R A1^-1 R^T, solved only on the blocks they touch
        want = sparse.T @ lu.solve(sparse.toarray())
        got = reg.sandwich(sparse.T)
        assert np.max(np.abs(got - want)) <= 1e-10 * np.max(np.abs(want))


def test_split_prior_penalises_moving_stiffness_between_springs_and_kv_only(box, monkeypatch):
    """``sigma S^T S / P``: K0 and kv raised together by one log step (what the curves and
    the sag both see as a stiffer body) costs what it costs without the split prior; moving
    stiffness from every spring to every kv (K0 up by c, kv down by c) costs sigma (2c)^2
    more, exactly; one connector's K0 alone up by c costs sigma c^2 n_c / (6 T), n_c the tets
    having it as an edge (counted from the tets' vertices: the pairs are the mesh's). The
    coupled metric is inverted as one block, densely or by sparse LU."""
    from scipy.sparse.linalg import splu
    import calibration.gradient_solver as solver

    mesh = build_problem(box).mesh
    e, t = len(mesh.edges), len(mesh.tets)
    size = 7 * e + t
    args = (neighbour_laplacian(mesh.edges, mesh.n_vertices), np.zeros(size),
            shared_laplacian(mesh.tets, mesh.n_vertices, 3))
    pairs = tet_edge_connectors(mesh.tets, mesh.edges)
    plain = Regulariser(*args)
    sigma, c, weight = 3.0, 0.2, 0.7
    split = Regulariser(*args, tet_edges=pairs, split_prior=sigma)
    together, apart = np.zeros(size), np.zeros(size)
    together[:e], together[7 * e:] = c, c
    apart[:e], apart[7 * e:] = c, -c
    assert split.value(together, weight) == pytest.approx(plain.value(together, weight),
                                                          rel=1e-12)
    assert split.value(apart, weight) - plain.value(apart, weight) == pytest.approx(
        weight * sigma * (2 * c) ** 2, rel=1e-12)
    for one in (0, e // 2, e - 1):
        alone = np.zeros(size)
        alone[one] = c
        n_c = sum(set(mesh.edges[one]) <= set(tet) for tet in mesh.tets.tolist())
        assert n_c > 0
        assert split.value(alone, weight) - plain.value(alone, weight) == pytest.approx(
            weight * sigma * c ** 2 * n_c / (6 * t), rel=1e-12)
    assert len(Regulariser(*args, tet_edges=pairs, split_prior=0.0)._blocks) == 2
    rng = np.random.default_rng(7)
    dense = rng.normal(size=(size, 5))
    sparse = sp.random(size, 4, density=0.01, random_state=8, format="csc")
    for limit in (solver.DENSE_INVERSE_LIMIT, 0):
        monkeypatch.setattr(solver, "DENSE_INVERSE_LIMIT", limit)
        reg = Regulariser(*args, tet_edges=pairs, split_prior=sigma)
        assert len(reg._blocks) == 1
        lu = splu(reg.metric)
        want = lu.solve(dense)
        assert np.max(np.abs(reg.solve(dense) - want)) <= 1e-10 * np.max(np.abs(want))
        want = sparse.T @ lu.solve(sparse.toarray())
        assert np.max(np.abs(reg.sandwich(sparse.T) - want)) <= 1e-10 * np.max(np.abs(want))


def test_settings_that_act_on_nothing_are_reported():
    """A split prior without per-tet kv, and fitting the force vector with the paper's
    method, each get a warning (in params.h5 and the report) instead of silently nothing."""
    from calibration.core import unused_settings
    from forcecal.scene import CalibrationSection

    on = CalibrationSection(method="gradient", split_prior=1.0, force_components="vector")
    assert unused_settings(on, volume=True) == []
    assert unused_settings(dataclasses.replace(on, split_prior=0.0), volume=False) == []
    for settings, volume in ((on, False), (dataclasses.replace(on, kv_per_tet=False), True)):
        (warning,) = unused_settings(settings, volume)
        assert "split_prior = 1 has no effect" in warning
    split, vector = unused_settings(dataclasses.replace(on, method="paper"), True)
    assert "split_prior = 1 has no effect" in split
    assert 'force_components = "vector" has no effect' in vector


def test_vector_data_fit_each_component_relative_to_the_normal_curve():
    """``force_components = "vector"``: a point's rows are its force's x, y, z curves
    (direction-major), each scaled by the normal curve's maximum, so the squared residual
    norm is the force vector's squared relative RMS error."""
    from calibration.gradient import Data

    rng = np.random.default_rng(3)
    vectors = rng.normal(size=(2, 4, 3))
    normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
    normal = np.einsum("psc,pc->ps", vectors, normals)
    data = Data.of({"indentation": normal}, {"indentation": vectors})
    np.testing.assert_array_equal(data.reference["indentation"][1, 4:8], vectors[1, :, 1])
    np.testing.assert_array_equal(data.weight["indentation"],
                                  1.0 / (np.abs(normal).max(axis=1) * 2.0))
    simulated = vectors + rng.normal(size=vectors.shape) * 1e-2
    r = data.residuals({"indentation": data.components(simulated)}, np.arange(2))
    assert r.shape == (24,)
    for p in range(2):
        want = (np.sqrt(np.mean(np.sum((simulated[p] - vectors[p]) ** 2, axis=1)))
                / np.abs(normal[p]).max())
        assert np.linalg.norm(r[12 * p:12 * (p + 1)]) == pytest.approx(want, rel=1e-12)
    assert Data.of({"indentation": normal}).directions is None


def test_validity_refuses_soft_springs():
    n = 3
    low, high = np.full(n, -0.3), np.full(n, 0.1)
    validity = Validity(low, high, floor=3.0, K0_global=30.0, scale=0.1)
    linear = dataclasses.replace(GLOBAL, alpha=0.0, beta=0.0)
    good = linear.connector_params(n)
    validity.check(good)
    soft = dataclasses.replace(good, a=np.array([0.0, 0.0, 150.0]))  # tangent 30 - 90 at -0.3
    with pytest.raises(ParameterError, match="connector 2"):
        validity.check(soft)
    theta = Coordinates(0.1, n).theta_of(good)
    theta[n + 2] = 0.5  # alpha s = 0.5: tangent 1 + 10 eps < 2 x floor / K0 at eps = -0.3
    h, jac = validity.hinge(theta)
    assert h[:5].max() == 0 and h[10:].max() > 0 and jac.shape == (15, 21)


def test_gradient_fit_resumes_from_its_checkpoint(box):
    """A fit whose every stage is in the checkpoint returns the same parameters without
    computing a single Jacobian; one whose last round is missing recomputes only that."""
    from calibration.gradient import fit_gradient, gradient_backend
    from calibration.pool import Experiments, Pool

    problem = build_problem(box)
    n = len(problem.mesh.edges)
    truth = smooth_truth(problem)
    depths = indentation_depths(box.indentation)
    times, relax_depths = relaxation_schedule(box.relaxation)
    strain = StrainRange(-0.2, 0.05)
    experiments = Experiments(problem, box.material.density, depths, times, relax_depths,
                              strain.bounds)
    cal = np.arange(len(problem.calibration))
    validity = Validity(np.full(n, strain.low), np.full(n, strain.high), 0.1 * GLOBAL.K0,
                        GLOBAL.K0, strain.scale)
    with Pool(experiments, truth, backend=gradient_backend, workers=1) as pool:
        reference = {k: pool.curves(k, truth, cal) for k in ("indentation", "relaxation")}
        store: dict = {}

        def fit(saved):
            return fit_gradient(pool, GLOBAL, strain, reference, validity, problem.mesh.edges,
                                problem.mesh.n_vertices, folds=2, max_iterations=3,
                                checkpoint_get=saved.get, checkpoint_put=saved.__setitem__)

        first = fit(store)
        again = fit(dict(store))
        assert again.jacobians == 0
        for name in PARAM_NAMES:
            np.testing.assert_array_equal(getattr(again.params, name),
                                          getattr(first.params, name))
        partial = {k: v for k, v in store.items() if not k.endswith("_1")}
        resumed = fit(partial)
        assert 0 < resumed.jacobians < first.jacobians
        assert resumed.weights == first.weights


def test_validity_range_covers_the_gravity_release_of_the_fe_sag(box):
    """Each connector's range = the experiments' range united with twice the strain of the FE
    static sag widened by the margin (what the gravity release verifies)."""
    from types import SimpleNamespace

    from calibration.core import spring_validity
    from particle.stability import strain_range_for_release
    from particle.statics import gravity_static

    problem = build_problem(box)
    glob = dataclasses.replace(GLOBAL, alpha=0.0, beta=0.0)
    n = len(problem.mesh.edges)
    model = build_model(problem, box.material.density, glob.connector_params(n))
    sag = gravity_static(model, np.array([0.0, 0.0, -9.81]))
    ref = SimpleNamespace(problem=problem, material=box.material,
                          gravity=SimpleNamespace(static_displacement=sag))
    strain = StrainRange(-0.05, 0.02)
    validity = spring_validity(ref, glob, strain, 0.1, 0.2)
    lo, hi = strain_range_for_release(model, sag, 0.2)
    np.testing.assert_array_equal(validity.low, np.minimum(lo, strain.low))
    np.testing.assert_array_equal(validity.high, np.maximum(hi, strain.high))
    assert validity.low.min() < strain.low and validity.high.max() > strain.high
    assert validity.floor == pytest.approx(0.1 * glob.K0)
    without = spring_validity(SimpleNamespace(problem=problem, material=box.material,
                                                gravity=None), glob, strain, 0.1, 0.2)
    assert np.all(without.low == strain.low) and np.all(without.high == strain.high)


def test_validity_range_covers_the_states_of_the_fitted_body_loads(box):
    """With the FE's states under the fitted body loads, each connector's range is also united
    with their strains widened by the margin; only a gradient fit of loads or their modes
    passes them (:func:`calibration.core.fitted_loads`)."""
    from types import SimpleNamespace

    from calibration.core import fitted_loads, spring_validity
    from particle.stability import strain_range_of_states
    from particle.statics import gravity_static

    problem = build_problem(box)
    glob = dataclasses.replace(GLOBAL, alpha=0.0, beta=0.0)
    n = len(problem.mesh.edges)
    model = build_model(problem, box.material.density, glob.connector_params(n))
    states = np.stack([gravity_static(model, np.array(g)) for g in ([9.81, 0.0, 0.0],
                                                                    [0.0, 9.81, 0.0])])
    ref = SimpleNamespace(problem=problem, material=box.material, gravity=None,
                          body=SimpleNamespace(load_accelerations=np.eye(3)[:2] * 9.81,
                                               load_displacement=states))
    strain = StrainRange(-0.05, 0.02)
    validity = spring_validity(ref, glob, strain, 0.1, 0.2, loads=states)
    lo, hi = strain_range_of_states(model, states, 0.2)
    np.testing.assert_array_equal(validity.low, np.minimum(lo, strain.low))
    np.testing.assert_array_equal(validity.high, np.maximum(hi, strain.high))
    assert validity.high.max() > strain.high

    def scene(method="gradient", body_data="modes+loaded_modes", runs_body=True):
        return SimpleNamespace(calibration=SimpleNamespace(method=method, body_data=body_data),
                               runs=lambda e: runs_body or e != "body")

    assert fitted_loads(scene(), ref) is states
    assert fitted_loads(scene(body_data="loads"), ref) is states
    assert fitted_loads(scene(body_data="modes+free_modes"), ref) is None
    assert fitted_loads(scene(method="paper"), ref) is None
    assert fitted_loads(scene(runs_body=False), ref) is None
    assert fitted_loads(scene(), SimpleNamespace(body=None)) is None


@pytest.mark.parametrize("indenter", ["vertex", "punch"])
def test_every_backend_indents_alike(box, indenter):
    """The gradient fit's evaluators (with adjoints) and the particle engine's return the same
    curves for the same experiments: with a punch both hold its whole footprint. (They once
    did not: the gradient backend indented the test vertex alone, and a punch scene was fitted
    to vertex curves.)"""
    from calibration.gradient import gradient_backend
    from calibration.pool import Experiments, particle_backend

    problem = build_problem(box)
    params = noisy_params(GLOBAL, len(problem.mesh.edges), sigma=0.1)
    points = np.array(PUNCH_POINTS)
    nodes = problem.test_points
    held = None
    if indenter == "punch":  # the punch at the two top-face points, the vertex elsewhere
        punches = indenter_footprints(problem.mesh, problem.fixed, nodes[points],
                                      problem.normals[points], "punch", PUNCH_RADIUS)
        held = [nodes[k:k + 1] for k in range(len(nodes))]
        for k, footprint in zip(points, punches):
            held[k] = footprint
        held = tuple(held)
    times, relax_depths = relaxation_schedule(box.relaxation)
    experiments = Experiments(problem, box.material.density, indentation_depths(box.indentation),
                              times, relax_depths, (-0.3, 0.3), held)
    curves = {name: {kind: ev(params) for kind, ev in backend(experiments, points, params).items()}
              for name, backend in (("particle", particle_backend),
                                    ("gradient", gradient_backend))}
    for kind in ("indentation", "relaxation"):
        a, b = curves["particle"][kind], curves["gradient"][kind]
        # both solve the same equilibria to the Newton tolerance (1e-8 of the force)
        np.testing.assert_allclose(b, a, rtol=1e-7, atol=1e-7 * np.abs(a).max())
    if held is not None:  # a punch of 7 particles pushes back harder than its centre alone
        vertex = particle_backend(dataclasses.replace(experiments, footprints=None), points,
                                  params)["indentation"](params)
        assert np.all(curves["gradient"]["indentation"][:, -1] > 2 * vertex[:, -1])


def test_hinge_rows_products_equal_the_dense_ones(box):
    """Linearisation.of with the hinge rows kept sparse (``hinge``) gives the products, the
    prediction and the damped step of the all-dense computation, to round-off."""
    problem = build_problem(box)
    n = len(problem.mesh.edges)
    rng = np.random.default_rng(3)
    reg = Regulariser(neighbour_laplacian(problem.mesh.edges, problem.mesh.n_vertices),
                      np.zeros(7 * n))
    theta = 0.1 * rng.normal(size=7 * n)
    data = rng.normal(size=(24, 7 * n))
    hinge = np.zeros((30, 7 * n))
    for row, e in enumerate(rng.choice(n, 30)):  # a hinge row: one connector's K0, alpha, beta
        hinge[row, [e, n + e, 2 * n + e]] = rng.normal(size=3)
    J, r = np.vstack([data, hinge]), rng.normal(size=54)
    dense = Linearisation.of(theta, r, J, reg)
    split = Linearisation.of(theta, r, data, reg, hinge=sp.csr_matrix(hinge))
    scale = np.abs(dense.C).max()
    np.testing.assert_allclose(split.C, dense.C, rtol=0, atol=1e-12 * scale)
    # the step solves with (alpha I + C), whose condition number (4e5 here) amplifies C's
    # round-off: 1e-8 of the step's size
    step = dense.step(reg, 0.3, 1.0)
    np.testing.assert_allclose(split.step(reg, 0.3, 1.0), step, rtol=0,
                               atol=1e-8 * np.abs(step).max())
    predicted = dense.predict(step)
    np.testing.assert_allclose(split.predict(step), predicted, rtol=0,
                               atol=1e-12 * np.abs(predicted).max())


def test_the_leading_vectors_are_the_largest_eigenpairs_in_an_order_blas_takes():
    """:func:`compress` projects a point's rows on ``leading_vectors(J J^T, k)``: the
    eigenvectors of the k largest eigenvalues, largest first (each ``G u = lambda u`` to
    round-off of the largest, orthonormal), in a C-ordered array. A reversed view of eigh's
    columns has a negative stride, which numpy's matmul does not hand to BLAS: its own loop
    made the projection of a liver punch point's (150, 12,455) rows 40x slower."""
    rng = np.random.default_rng(3)
    J = rng.standard_normal((30, 200)) * np.geomspace(1.0, 1e-3, 30)[:, None]
    gram = J @ J.T
    U = leading_vectors(gram, 5)
    values = np.linalg.eigvalsh(gram)[::-1][:5]
    assert U.shape == (30, 5) and U.flags.c_contiguous
    np.testing.assert_allclose(gram @ U, U * values, rtol=0, atol=1e-12 * values[0])
    np.testing.assert_allclose(U.T @ U, np.eye(5), rtol=0, atol=1e-13)
    r = rng.standard_normal(30)
    r_kept, J_kept, left = compress(r, J, 30, 5)
    np.testing.assert_allclose(r_kept, U.T @ r, rtol=1e-14)
    assert left == pytest.approx(r @ r - r_kept @ r_kept)
