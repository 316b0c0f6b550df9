"""Stress tests of the particle engine: stability limit, extreme parameters and meshes, long runs.

Each case ends in a checked physical result (energy, force balance, work) or
in a clear refusal (a ForcecalError naming the problem), never NaN; every loop
is bounded (fixed step counts, bisections with a fixed bracket, Newton with
an iteration limit and a bounded number of load-step halvings), so nothing
here can hang.
"""

import numpy as np
import pytest

from forcecal.errors import ConvergenceError, StabilityError
from particle.empirical_limit import bisect, blows_up, empirical_critical_step
from particle.stability_cases import (PARAMETER_SETS, PRESTRAINS, case_model, clamped_cube,
                                      sliver_mesh, stability_meshes)
from particle import kernels
from particle.evaluators import IndentationEvaluator
from particle.integrator import VerletIntegrator, connector_strain_bounds
from particle.stability import (DEFAULT_STRAIN_RANGE, connector_stiffness_bound,
                                critical_time_step, mass_scaled_laplacian,
                                strain_range_for_release)
from particle.model import Model
from particle.statics import EquilibriumSolver, TangentPattern, continuation, gravity_static
from particle.testing import box_model, mechanical_energy, spring_energy, top_centre

GRAVITY = np.array([0.0, 0.0, -9.81])


@pytest.fixture(scope="module")
def meshes():
    return stability_meshes()


@pytest.mark.parametrize("parameter_set", PARAMETER_SETS)
@pytest.mark.parametrize("mesh_name", ["cube 3x3x2", "bar 8x2x2", "plate 4x4x1", "sliver",
                                       "liver h=0.04"])
def test_estimated_limit_never_exceeds_the_empirical_one(meshes, mesh_name, parameter_set,
                                                         record_property):
    model = case_model(*meshes[mesh_name], parameter_set)
    estimate = critical_time_step(model)
    # the bisection returns a step that ran 3000 steps without diverging, within 0.1 % of
    # the first one that diverged: the estimate must not be above it
    empirical = empirical_critical_step(model)
    record_property("ratio", estimate / empirical)
    assert gershgorin_step(model) <= estimate <= empirical
    # and it is not uselessly pessimistic at small strain, except where it must be: the
    # stiff nonlinear set's tangent reaches 33 K0 at strain -0.5, which the bound covers
    assert estimate / empirical > (0.15 if parameter_set == "stiff nonlinear" else 0.5)


def gershgorin_step(model: Model) -> float:
    """2/sqrt(largest row sum) of the estimate's matrix ``M^{-1/2} L_kappa M^{-1/2}``: the
    block-Gershgorin bound the eigenvalue bound replaced (same connector bounds kappa)."""
    lo, hi = connector_strain_bounds(DEFAULT_STRAIN_RANGE, model.n_connectors)
    matrix = mass_scaled_laplacian(model, connector_stiffness_bound(model.params, lo, hi))
    return 2.0 / np.sqrt(abs(matrix).sum(axis=1).max())


@pytest.mark.parametrize("strain", PRESTRAINS)
@pytest.mark.parametrize("parameter_set", PARAMETER_SETS)
def test_estimate_holds_at_every_strain_of_its_range(parameter_set, strain, record_property):
    """A clamped cube held at a uniform strain: the limit of the tangent there, for strains
    across the estimate's range (+-0.5), is never below the estimate."""
    model = clamped_cube(parameter_set)
    estimate = critical_time_step(model)
    empirical = empirical_critical_step(model, prestrain=strain)
    record_property("ratio", estimate / empirical)
    assert estimate <= empirical


@pytest.mark.parametrize("parameter_set", PARAMETER_SETS)
def test_release_range_estimate_never_exceeds_the_limit_of_the_release(parameter_set,
                                                                      record_property):
    """Per-connector ranges: a soft box sagging by up to ~0.1 strain under gravity, the step
    chosen for its release range (margin 0.2, the scene default), against the largest step
    at which the release itself (3000 steps, ~100 of its slowest periods) does not blow up
    (bisection to 0.1 %, as for the other cases)."""
    scale, a, b, g = PARAMETER_SETS[parameter_set]
    model = box_model((3, 3, 2), K0=12.0 * scale, a=a * 12.0, b=b * 12.0, g=g)
    release = strain_range_for_release(model, gravity_static(model, GRAVITY), 0.2)
    estimate = critical_time_step(model, strain_range=release)
    empirical = bisect(lambda dt: blows_up(model, dt, amplitude=0.0, gravity=GRAVITY),
                       0.5 * estimate)
    record_property("ratio", estimate / empirical)
    assert estimate <= empirical
    # the release range is narrower than +-0.5: the estimate is larger than that one's
    assert estimate > critical_time_step(model)


def test_tiny_masses_scale_the_limit_by_the_square_root_of_the_density(meshes):
    """omega^2 ~ k/m: a density 1e-6 times smaller gives a 1e-3 times smaller limit,
    for the estimate exactly (it is a closed-form bound) and for the bisection within
    its tolerance (0.1 % each)."""
    mesh, fixed = meshes["cube 3x3x2"]
    normal = case_model(mesh, fixed, "strong arms")
    tiny = case_model(mesh, fixed, "strong arms", density=1060e-6)
    assert critical_time_step(tiny) == pytest.approx(1e-3 * critical_time_step(normal),
                                                     rel=1e-12)
    assert empirical_critical_step(tiny) == pytest.approx(
        1e-3 * empirical_critical_step(normal), rel=2e-3)


# --------------------------------------------------------------------------- energy

def assert_energy_bounded(model: Model, seconds: float, chunks: int, *,
                          monitored: bool = True) -> np.ndarray:
    """Release under gravity with half the estimated limit as the step; check energy.

    After each of ``chunks`` pieces of the run the total energy must not exceed 2 % of
    the largest stored energy seen: Verlet's energy error at omega dt <= 1 stays below
    (omega dt)^2/8 of the energy of the fastest modes, which hold a small part of the
    stored energy; a growing instability would pass that bound within a few chunks.
    ``monitored=False`` runs without the strain-range monitoring (only the divergence
    guard), for a run meant to leave the range the step was verified for.
    Returns the totals [J].
    """
    dt = 0.5 * critical_time_step(model)
    steps = max(1, round(seconds / dt / chunks))
    state, integrator = model.state(), VerletIntegrator()
    total, stored = np.empty(chunks), np.empty(chunks)
    for k in range(chunks):
        integrator.simulate(model, state, dt, steps, gravity=GRAVITY, _check_dt=monitored)
        total[k], stored[k] = mechanical_energy(model, state, GRAVITY)
    assert np.all(np.isfinite(state.x))
    assert total.max() <= 0.02 * stored.max()
    return total


def clamps_carry_the_weight(model: Model, displacement: np.ndarray) -> None:
    """Connector forces recomputed at the sagged state: on the free particles they cancel
    gravity, so the forces the clamped particles feel add up to the weight of the free ones."""
    p = model.params
    x = model.rest_positions + displacement
    forces = np.empty_like(x)
    kernels.internal_forces(x, model.edges, model.rest_lengths, p.K0, p.a, p.b, None, None,
                            None, None, forces, np.empty(model.n_connectors), None,
                            np.empty(model.n_connectors))
    weight = model.masses[model.free_nodes].sum() * GRAVITY
    # Newton stops at 1e-10 of the weight: 1e-8 leaves room for summation round-off
    np.testing.assert_allclose(forces[model.fixed].sum(axis=0), weight, rtol=0,
                               atol=1e-8 * np.linalg.norm(weight))


# --------------------------------------------------------------------------- stress cases

def test_stiff_springs_sag_like_normal_ones_under_a_thousandth_of_the_load():
    """Every force is linear in the parameters, so 1000 x K0 (and a, b, k_i, b_i) under g
    has exactly the equilibrium of 1 x K0 under g/1000: the same sag, to Newton's tolerance."""
    normal = box_model((3, 3, 2), K0=50.0, a=-20.0, b=300.0)
    stiff = box_model((3, 3, 2), K0=50e3, a=-20e3, b=300e3)
    sag_stiff = gravity_static(stiff, GRAVITY)
    clamps_carry_the_weight(stiff, sag_stiff)
    np.testing.assert_allclose(sag_stiff, gravity_static(normal, GRAVITY / 1000), rtol=0,
                               atol=1e-7 * np.abs(sag_stiff).max())
    assert_energy_bounded(stiff, 0.02, 8)  # 1600 steps of 6 us


def test_very_soft_springs_refuse_the_sag_and_fall_without_creating_energy():
    soft = box_model((3, 3, 2), K0=0.05)  # 0.2 mN per 10 % strain against a 0.3 N weight
    with pytest.raises(ConvergenceError, match=r"gravity load .* failed after repeated halving"):
        gravity_static(soft, GRAVITY)
    # the box collapses through its clamps: a monitored run stops when the first connector
    # leaves the range its step was verified for (+-0.5) ...
    with pytest.raises(StabilityError, match=r"connector \d+ \(particles \d+-\d+\) reached "
                       r"strain .* outside \[-0\.5, 0\.5\]"):
        assert_energy_bounded(soft, 1.0, 10)
    # ... and, watched by the divergence guard only, the fall creates no energy
    assert_energy_bounded(soft, 1.0, 10, monitored=False)


def test_strongly_nonlinear_springs_indented_by_half_a_connector_store_the_indenter_work():
    """50 % compressive indentation with b = 1000 K0: the work of the indenter force,
    int F dd, equals the springs' energy at the final equilibrium (elastic, path-free)."""
    model = box_model((3, 3, 2), K0=50.0, a=0.0, b=50e3)
    node = top_centre(model)
    length = model.incident_min_length([node])[0]
    normal = np.array([0.0, 0.0, -1.0])
    depths = np.linspace(0.0, 0.5 * length, 41)
    force = IndentationEvaluator(model, [node], [normal], depths[1:])(model.params)[0]
    # Simpson on 40 intervals of a smooth curve: error ~ h^4 |F''''|, well below 1e-4 here
    h = depths[1]
    f = np.r_[0.0, force]
    work = h / 3 * (f[0] + f[-1] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum())
    solver = EquilibriumSolver(model, [node], TangentPattern.of(model))

    def step(x, _, d):
        guess = x.copy()
        guess[node] = model.rest_positions[node] + d * normal
        return solver.solve(guess, model.params).x

    final = continuation(step, model.rest_positions.copy(), 0.0, depths[-1])
    assert work == pytest.approx(spring_energy(model, final), rel=1e-4)
    assert np.all(np.diff(force) > 0)  # stiffening: the force keeps rising


def test_indenting_deeper_than_the_connector_follows_the_snap_through():
    # pushed 1.5 connector lengths down, the top centre of a 3 x 3 x 2 box passes a fold
    # (its ring snaps through): the curve follows the model to the state it snaps to, as a
    # slow damped push does (EquilibriumSolver.settle), instead of ending the calibration;
    # depths that collapse connectors are refused before any work (calibration.reach)
    model = box_model((3, 3, 2))
    node = top_centre(model)
    length = model.incident_min_length([node])[0]
    evaluator = IndentationEvaluator(model, [node], [[0.0, 0.0, -1.0]],
                                     np.linspace(0.1, 1.5, 15) * length)
    curve = evaluator(model.params)[0]
    assert np.all(np.isfinite(curve)) and np.all(curve > 0.0)
    fold = int(np.argmax(curve))
    assert 0 < fold < len(curve) - 1
    assert np.all(np.diff(curve[:fold + 1]) > 0.0)  # stiff up to the fold
    assert curve[fold + 1] < 0.9 * curve[fold]  # the snap releases load (measured 0.84x)
    low, high = evaluator.strain_extremes()[0]
    assert -1.0 < low < 0.0 < high  # no connector collapsed on the way


@pytest.mark.parametrize("parameter_set", ["linear", "stiff nonlinear"])
def test_sliver_mesh_sags_with_balanced_forces_and_bounded_energy(parameter_set):
    mesh = sliver_mesh(height=1e-4)  # four vertices within 2 um of a plane
    model = case_model(mesh, np.array([0, 5]), parameter_set)
    clamps_carry_the_weight(model, gravity_static(model, GRAVITY))
    assert_energy_bounded(model, 0.5, 10)


def test_a_million_connector_steps_keep_the_energy_bounded():
    model = box_model((3, 3, 2), a=-20.0, b=300.0)  # nonlinear springs, arms, gravity
    steps = 30 * max(1, round(3.0 / (0.5 * critical_time_step(model)) / 30))
    assert steps * model.n_connectors >= 1e6
    energy = assert_energy_bounded(model, 3.0, 30)
    # the arms dissipate: the last tenth of the run holds less energy than the first
    assert energy[-3:].max() < energy[:3].max()
