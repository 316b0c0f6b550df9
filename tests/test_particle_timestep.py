"""The explicit step's stability bound against closed forms, and the strain-range monitoring.

The estimator on general meshes (the Gershgorin bound's step <= the estimate <= the
limit found by bisection) is tested in ``tests/test_stability_particle.py``.
"""
import warnings

import numpy as np
import pytest

from forcecal.errors import ParameterError, StabilityError
from particle.experiments import gravity_dynamic
from particle.integrator import VerletIntegrator
from particle.stability import (DENSE_EIGEN_LIMIT, EIGENVALUE_MARGIN, critical_time_step,
                                strain_range_for_release, strain_range_of_states)
from particle.model import Model, ModelBuilder
from particle.params import ConnectorParams, viscoelastic_params
from particle.statics import gravity_static
from tests.particle_models import box_model, two_particle_model
from pipelines.bench.empirical_limit import blows_up

GRAVITY = np.array([0.0, 0.0, -9.81])
ELASTIC = dict(g=(1e-12, 1e-12))  # Maxwell arms of negligible stiffness: a purely elastic model


def chain(n_free: int, K0: float = 50.0, mass: float = 0.01, spacing: float = 0.01) -> Model:
    """n_free + 1 particles on the x axis, the first fixed, neighbours joined: a fixed-free chain."""
    builder = ModelBuilder()
    builder.add_particles(spacing * np.column_stack([np.arange(n_free + 1.0),
                                                     np.zeros((n_free + 1, 2))]),
                          np.full(n_free + 1, mass), np.arange(n_free + 1) == 0)
    builder.add_connectors(np.column_stack([np.arange(n_free), np.arange(1, n_free + 1)]))
    return builder.finalize(viscoelastic_params(n_free, K0, **ELASTIC))


def chain_critical_step(n_free: int, K0: float, mass: float) -> float:
    """2/omega_max of the chain's axial vibration, closed form: the fixed-free chain's matrix
    (K0/m) tridiag(-1, 2, -1) with a 1 in its last diagonal entry has the eigenvalues
    4 (K0/m) sin^2((2j - 1) pi / (2 (2n + 1))), j = 1..n."""
    omega2 = 4.0 * K0 / mass * np.sin((2 * n_free - 1) * np.pi / (2 * (2 * n_free + 1))) ** 2
    return 2.0 / np.sqrt(omega2)


@pytest.mark.parametrize("n_free", [40, DENSE_EIGEN_LIMIT + 200])  # dense and Lanczos paths
def test_the_bound_is_exact_on_a_chain_and_the_chain_blows_up_just_above_it(n_free):
    """A straight chain at rest: every connector's tangent block is K0 e e^T with the same e,
    so the stiffness is exactly the Laplacian bound's axial part and the bound is the true
    limit (times 1/sqrt(EIGENVALUE_MARGIN)). Tolerances: the strain range +-1e-9 and the
    1e-12 arms change kappa by < 1e-8 relative; Lanczos converges to the top eigenvalue
    within its relative tolerance 1e-10, but the chain's top eigenvalues are only ~1e-6
    apart at this length, so 1e-5 leaves room for a neighbouring Ritz value."""
    K0, mass = 50.0, 0.01
    model = chain(n_free, K0, mass)
    exact = chain_critical_step(n_free, K0, mass)
    bound = critical_time_step(model, strain_range=(-1e-9, 1e-9))
    assert bound == pytest.approx(exact / np.sqrt(EIGENVALUE_MARGIN), rel=1e-5)
    assert bound < exact
    if n_free <= DENSE_EIGEN_LIMIT:  # the run itself: stable just below the limit, not above
        # 0.1 % above the limit the top mode grows by 1 + sqrt(8e-3) per step: 1e11 in 300
        assert not blows_up(model, 0.999 * exact, steps=500)
        assert blows_up(model, 1.001 * exact, steps=500)


def test_per_connector_ranges_give_each_connector_its_own_bound():
    """Two free particles hanging in a chain: only the first connector may be strained, so only
    its kappa grows; the per-connector bound lies between the uniform narrow and wide ones."""
    model = chain(2, K0=50.0, mass=0.01)
    params = ConnectorParams.uniform(2, K0=50.0, a=0.0, b=5000.0, k1=1e-9, b1=1e-9, k2=1e-9,
                                     b2=1e-8)
    model = model.with_params(params)
    narrow = critical_time_step(model, strain_range=(0.0, 0.0))
    wide = critical_time_step(model, strain_range=(0.0, 0.3))
    mixed = critical_time_step(model, strain_range=(np.zeros(2), np.array([0.3, 0.0])))
    assert wide < mixed < narrow
    # closed form for the mixed case: tangent 50 + 3 * 5000 * 0.3^2 = 1400 N/m on the first
    # connector, 50 N/m on the second; kappa/m on the 2x2 matrix [[k1 + k2, -k2], [-k2, k2]]
    k1, k2 = 1400.0, 50.0
    lam = np.linalg.eigvalsh(np.array([[k1 + k2, -k2], [-k2, k2]]) / 0.01)[-1]
    assert mixed == pytest.approx(2.0 / np.sqrt(EIGENVALUE_MARGIN * lam), rel=1e-9)


def test_strain_bounds_of_the_wrong_shape_or_order_are_refused():
    model = chain(3)
    with pytest.raises(ParameterError, match=r"shape \(2,\): expected one number or one per "
                       r"connector \(3,\)"):
        critical_time_step(model, strain_range=(np.zeros(2), 0.1))
    with pytest.raises(ParameterError, match=r"connector 1 \(particles 1-2\): strain range "
                       r"\[0\.2, 0\.1\] must be finite, ordered and above -1"):
        critical_time_step(model, strain_range=(np.array([0.0, 0.2, 0.0]), 0.1))
    with pytest.raises(ParameterError, match="above -1"):
        VerletIntegrator(strain_range=(-1.0, 0.1)).prepare(model, 1e-5)


def test_release_range_is_twice_the_static_strain_widened_by_the_margin():
    """One particle hanging under a fixed one on a linear spring: static elongation m g/K0,
    so the release range is [-m, 2 m g/(K0 L) + m]; the elastic release from rest then
    oscillates between 0 and exactly twice the static strain (position Verlet's discrete
    oscillator started with the Taylor step is x_n = x_s (1 - cos(n theta))), so a run
    monitored on that range with a margin of 1e-9 does not stop, while one whose range ends
    at the static strain does."""
    K0, L, mass = 50.0, 0.02, 0.01
    model = two_particle_model(L, mass, viscoelastic_params(1, K0, **ELASTIC), (0.0, 0.0, -1.0))
    static = gravity_static(model, GRAVITY)
    eps = mass * 9.81 / (K0 * L)
    lo, hi = strain_range_for_release(model, static, 0.05)
    np.testing.assert_allclose([lo[0], hi[0]], [-0.05, 2 * eps + 0.05], rtol=1e-9)
    # a static compression of 0.4: twice that minus the margin (-0.85) is capped at half the
    # static length, (-0.4 - 1)/2 = -0.7; a compression of 0.1 is not capped
    for compression, expected in ((0.4, -0.7), (0.1, -0.25)):
        lo, hi = strain_range_for_release(model, [[0.0, 0.0, 0.0], [0.0, 0.0, compression * L]],
                                          0.05)
        np.testing.assert_allclose([lo[0], hi[0]], [expected, 0.05], rtol=1e-12)
    period = 2 * np.pi * np.sqrt(mass / K0)
    times = np.linspace(0.0, 3 * period, 301)
    release = strain_range_for_release(model, static, 1e-9)
    dt = 0.9 * critical_time_step(model, strain_range=release)
    u = gravity_dynamic(model, GRAVITY, times[-1], dt, times, strain_range=release)
    strain = -u[:, 1, 2] / L
    assert strain.max() == pytest.approx(2 * eps, rel=1e-3)  # the samples come close to the top
    with pytest.raises(StabilityError, match=r"connector 0 \(particles 0-1\) reached strain "
                       r"0\.\d+ at t = .* s, outside \[-1e-09, 0\.0981\]"):
        gravity_dynamic(model, GRAVITY, times[-1], dt, times,
                        strain_range=strain_range_for_release(model, 0.5 * static, 1e-9))


def test_a_release_stays_in_its_range_and_a_too_narrow_range_stops_the_run():
    """A viscoelastic, nonlinear box released under gravity: with the release range of its
    static sag (margin 0.05) the monitored run completes and every recorded strain lies in
    the range; with the range of a tenth of that deflection (the arms make the first swing
    reach ~0.8 of the static strain) the run stops, naming a connector, its strain, the
    range, the time and what to do."""
    model = box_model((3, 3, 2), K0=10.0, a=-4.0, b=60.0)  # sags by up to 12 % strain
    static = gravity_static(model, GRAVITY)
    release = strain_range_for_release(model, static, 0.05)
    dt = 0.9 * critical_time_step(model, strain_range=release)
    times = np.linspace(0.0, 0.3, 61)
    u = gravity_dynamic(model, GRAVITY, times[-1], dt, times, strain_range=release)
    x = model.rest_positions + u
    strain = (np.linalg.norm(x[:, model.edges[:, 1]] - x[:, model.edges[:, 0]], axis=2)
              / model.rest_lengths - 1.0)
    assert np.all(strain >= release[0]) and np.all(strain <= release[1])
    assert np.abs(strain).max() > 0.05  # the release really strains the box beyond the margin
    narrow = strain_range_for_release(model, 0.1 * static, 0.0)
    dt = 0.9 * critical_time_step(model, strain_range=narrow)
    with pytest.raises(StabilityError, match=r"connector \d+ \(particles \d+-\d+\) reached strain "
                       r"-?[\d.e-]+ at t = [\d.e-]+ s, outside \[-?[\d.e-]+, [\d.e-]+\], the range "
                       r"the step dt = .* s was verified stable for .* particle\.strain_margin"):
        gravity_dynamic(model, GRAVITY, times[-1], dt, times, strain_range=narrow)


def test_unmonitored_runs_are_only_the_unchecked_ones():
    """A step that is not checked (the tests' _check_dt=False) is not monitored either: the
    same too-narrow range then only feeds the divergence guard."""
    model = box_model((3, 3, 2))
    integrator = VerletIntegrator(strain_range=(-1e-6, 1e-6))
    dt = 0.5 * integrator.critical_time_step(model)
    with pytest.raises(StabilityError, match=r"outside \[-1e-06, 1e-06\]"):
        integrator.simulate(model, model.state(), dt, 200, gravity=GRAVITY)
    state = model.state()
    integrator.simulate(model, state, dt, 200, gravity=GRAVITY, _check_dt=False)
    assert np.all(np.isfinite(state.x))


def test_stiffness_extremes_of_tiny_quadratic_coefficients_raise_no_warning():
    """b = 1e-300 used to give a vertex -a/(2b) that overflowed (numpy RuntimeWarning); the
    vertex is now only computed where it lies inside the range, so the extremes are the
    end values of the (numerically linear) K(eps) without any warning."""
    p = ConnectorParams.uniform(3, K0=10.0, a=5.0, b=1e-300, k1=1.0, b1=1.0, k2=1.0, b2=10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kmin, kmax = p.extreme_stiffness((-0.5, 0.5))
        tmin, tmax = p.extreme_tangent_stiffness((-0.5, 0.5))
    np.testing.assert_allclose([kmin[0], kmax[0], tmin[0], tmax[0]], [7.5, 12.5, 5.0, 15.0])


def test_the_strain_range_of_static_states_is_each_strain_widened_with_rest_in_it():
    """Stretched by 0.3 and compressed by 0.9 in two states, margin 0.2: ``[max(-0.9 - 0.2,
    (-0.9 - 1) / 2), 0.3 + 0.2]`` = [-0.95, 0.5] (no overshoot: the states are where the model
    is used); the stretched state alone: [0, 0.5] (rest, strain 0, is in every range)."""
    L = 0.02
    model = two_particle_model(L, 0.01, viscoelastic_params(1, 50.0), (0.0, 0.0, -1.0))
    states = np.zeros((2, 2, 3))
    states[0, 1, 2], states[1, 1, 2] = -0.3 * L, 0.9 * L
    lo, hi = strain_range_of_states(model, states, 0.2)
    np.testing.assert_allclose([lo[0], hi[0]], [-0.95, 0.5], rtol=1e-12)
    lo, hi = strain_range_of_states(model, states[:1], 0.2)
    np.testing.assert_allclose([lo[0], hi[0]], [0.0, 0.5], atol=1e-12)
    with pytest.raises(ParameterError, match="margin"):
        strain_range_of_states(model, states, -0.1)
