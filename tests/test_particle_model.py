"""Particle model data structures: parameters, builder, Model, State, and their refusals."""
import dataclasses
import pickle

import numpy as np
import pytest

from forcecal.errors import MeshError, ParameterError
from forcecal.mesh import TetMesh, box_mesh
from particle.integrator import VerletIntegrator
from particle.stability import critical_time_step
from particle.model import ModelBuilder, build_model, spatial_order
from particle.params import ConnectorParams, viscoelastic_params
from tests.particle_models import box_model


def test_uniform_params_shapes_and_relaxation_times():
    p = ConnectorParams.uniform(4, K0=10.0, a=1.0, b=2.0, k1=3.0, b1=1.5, k2=4.0, b2=40.0)
    assert p.n_connectors == 4
    np.testing.assert_array_equal(p.tau1, 0.5)
    np.testing.assert_array_equal(p.tau2, 10.0)
    assert p.arm_stiffness.shape == (4, 2) and not p.is_linear
    with pytest.raises(ValueError):
        p.K0[0] = 1.0  # immutable: calibration must build new instances
    q = dataclasses.replace(p, a=np.zeros(4), b=np.zeros(4))
    assert q.is_linear


def test_params_of_different_lengths_are_refused():
    with pytest.raises(ParameterError, match="one length"):
        ConnectorParams(K0=np.ones(3), a=np.zeros(3), b=np.zeros(3), k1=np.ones(2),
                        b1=np.ones(3), k2=np.ones(3), b2=np.ones(3))


@pytest.mark.parametrize("name, value, message", [
    ("K0", 0.0, "K0 = 0 must be > 0"),
    ("K0", -5.0, "K0 = -5 must be > 0"),
    ("k1", 0.0, "k1 = 0 must be > 0"),
    ("k2", -1.0, "k2 = -1 must be > 0"),
    ("b1", 0.0, "b1 = 0 must be > 0"),
    ("b2", -2.0, "b2 = -2 must be > 0"),
    ("a", np.nan, "a = nan is not finite"),
    ("b2", np.inf, "b2 = inf is not finite"),
])
def test_validate_names_the_first_bad_connector(name, value, message):
    p = viscoelastic_params(5)
    values = getattr(p, name).copy()
    values[3] = value
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 7], [4, 5]])
    with pytest.raises(ParameterError, match=f"connector 3 \\(particles 3-7\\): {message}"):
        dataclasses.replace(p, **{name: values}).validate(edges=edges)


def test_validate_checks_the_quadratic_minimum_inside_the_range():
    # K(eps) = 10 - 40 eps + 50 eps^2 is 10 at both ends of [0, 0.8] and has its minimum
    # 2 at eps = 0.4: valid. Lowering K0 to 7 makes the minimum -1 while both ends stay at
    # 7: only the analytic minimum catches it.
    ok = viscoelastic_params(1, K0=10.0, a=-40.0, b=50.0)
    kmin, kmax = ok.extreme_stiffness((0.0, 0.8))
    assert kmin[0] == pytest.approx(2.0) and kmax[0] == pytest.approx(10.0)
    ok.validate((0.0, 0.8))
    bad = viscoelastic_params(1, K0=7.0, a=-40.0, b=50.0)
    with pytest.raises(ParameterError, match=r"connector 0: spring stiffness .* reaches -1 N/m"):
        bad.validate((0.0, 0.8))
    # the same parameters are fine where the parabola stays positive
    bad.validate((-0.2, 0.1))


def test_validate_refuses_a_nonsense_strain_range():
    with pytest.raises(ParameterError, match=r"strain range \[0\.5, 0\.1\] must be finite, "
                                             "ordered and above -1"):
        viscoelastic_params(2).validate((0.5, 0.1))
    with pytest.raises(ParameterError, match="strain range"):
        viscoelastic_params(2).validate((-1.5, 0.1))
    edges = np.array([[0, 1], [1, 2]])
    with pytest.raises(ParameterError, match=r"connector 1 \(particles 1-2\): strain range "
                                             r"\[0\.2, 0\.1\]"):
        viscoelastic_params(2).validate((np.array([0.0, 0.2]), 0.1), edges)
    with pytest.raises(ParameterError, match=r"shape \(3,\): expected one number or one per "
                                             r"connector \(2,\)"):
        viscoelastic_params(2).validate((np.zeros(3), 0.1))
    # a range of one strain (a connector held there) is a range: the same rule as the
    # stability limit's (lo <= hi)
    viscoelastic_params(2).validate((0.1, 0.1))


def test_validate_takes_per_connector_strain_ranges():
    """K(eps) = 10 (1 + 4 eps) is <= 0 at eps <= -0.25: refused where a connector's own range
    reaches it, accepted where only another connector's range would."""
    p = viscoelastic_params(3, K0=10.0, a=40.0)
    edges = np.array([[0, 1], [1, 2], [2, 5]])
    with pytest.raises(ParameterError, match=r"connector 2 \(particles 2-5\): spring stiffness "
                       r".* reaches -2 N/m <= 0 in the strain range \[-0\.3, 0\.1\]"):
        p.validate((np.array([-0.2, -0.2, -0.3]), np.array([0.1, 0.1, 0.1])), edges)
    p.validate((np.array([-0.2, -0.2, -0.2]), 0.5), edges)


def test_arm_recursion_coefficients():
    p = ConnectorParams.uniform(1, K0=1.0, k1=2.0, b1=1.0, k2=4.0, b2=40.0)
    dt = 0.1
    r, c = p.arm_recursion(dt)
    tau = np.array([0.5, 10.0])
    k = np.array([2.0, 4.0])
    # the paper's coefficients: k b/(k dt + b) multiplies (ddx + F/k)
    np.testing.assert_allclose(c[0], k * k * tau / (k * dt + k * tau), rtol=1e-15)
    np.testing.assert_allclose(r[0], c[0] / k, rtol=1e-15)
    r, c = p.arm_recursion(dt, exact=True)
    np.testing.assert_allclose(r[0], np.exp(-dt / tau), rtol=1e-15)
    np.testing.assert_allclose(c[0], k * tau * (1 - np.exp(-dt / tau)) / dt, rtol=1e-14)
    with pytest.raises(ParameterError, match="time step"):
        p.arm_recursion(0.0)


def test_build_model_from_a_mesh():
    mesh = box_mesh((2, 2, 1), (0.02, 0.02, 0.01))
    params = viscoelastic_params(len(mesh.edges))
    model = build_model(mesh, 1000.0, params, fixed=[0, 1, 2])
    assert model.n_particles == mesh.n_vertices and model.n_connectors == len(mesh.edges)
    np.testing.assert_array_equal(model.edges, mesh.edges)  # same order: connector e = edge e
    np.testing.assert_allclose(model.rest_lengths, mesh.edge_lengths, rtol=1e-15)
    # lumped masses add up to density x volume
    assert model.masses.sum() == pytest.approx(1000.0 * 0.02 * 0.02 * 0.01, rel=1e-12)
    assert model.fixed[[0, 1, 2]].all() and model.fixed.sum() == 3
    np.testing.assert_array_equal(model.free_nodes, np.arange(3, mesh.n_vertices))
    # CSR incidence: every connector appears at both ends
    for n in (0, 5):
        touching = model.incidence_edge[model.incidence_ptr[n]:model.incidence_ptr[n + 1]]
        expected = np.nonzero((mesh.edges == n).any(axis=1))[0]
        np.testing.assert_array_equal(np.sort(touching), expected)
    other = dataclasses.replace(params, K0=params.K0 * 2)
    m2 = model.with_params(other)
    assert m2.params is other and m2.edges is model.edges and m2.masses is model.masses
    with pytest.raises(ParameterError, match="3 entries but the model has"):
        model.with_params(viscoelastic_params(3))
    restored = pickle.loads(pickle.dumps(model))
    np.testing.assert_array_equal(restored.incidence_edge, model.incidence_edge)


def test_build_model_from_a_problem_uses_its_fixed_nodes(liver_problem):
    model = build_model(liver_problem, 1060.0, viscoelastic_params(len(liver_problem.mesh.edges)))
    np.testing.assert_array_equal(np.nonzero(model.fixed)[0], np.sort(liver_problem.fixed))
    assert model.n_connectors == 1400


def test_state_starts_at_rest():
    mesh = box_mesh((1, 1, 1))
    model = build_model(mesh, 1.0, viscoelastic_params(len(mesh.edges)))
    s = model.state()
    np.testing.assert_array_equal(s.x, model.rest_positions)
    np.testing.assert_array_equal(s.x_prev, s.x)
    assert s.x is not model.rest_positions and s.dt is None and s.t == 0.0
    assert not s.arm_force.any() and not s.dx_prev.any()
    c = s.copy()
    c.x[0, 0] = 5.0
    assert s.x[0, 0] == 0.0


def test_builder_refusals():
    b = ModelBuilder()
    b.add_particle((0, 0, 0), 1.0)
    b.add_particle((1, 0, 0), 1.0)
    with pytest.raises(MeshError, match="unknown particle"):
        b.add_connector(0, 2)
    with pytest.raises(MeshError, match="to itself"):
        b.add_connector(1, 1)
    with pytest.raises(ParameterError, match="mass"):
        b.add_particle((2, 0, 0), 0.0)
    with pytest.raises(MeshError, match="needs particles and connectors"):
        b.finalize(viscoelastic_params(0))
    b.add_connector(0, 1)
    b.add_connector(1, 0)
    with pytest.raises(MeshError, match="joined by 2 connectors"):
        b.finalize(viscoelastic_params(2))
    z = ModelBuilder()
    z.add_particles(np.zeros((2, 3)), [1.0, 1.0])
    z.add_connector(0, 1)
    with pytest.raises(MeshError, match="zero rest length"):
        z.finalize(viscoelastic_params(1))


def test_unknown_and_fixed_nodes_are_refused():
    mesh = box_mesh((1, 1, 1))
    model = build_model(mesh, 1.0, viscoelastic_params(len(mesh.edges)), fixed=[0])
    with pytest.raises(MeshError, match=r"unknown particle\(s\) \[8\]"):
        model.check_nodes([8], "test points")
    with pytest.raises(MeshError, match=r"particle\(s\) \[0\] are fixed"):
        model.check_nodes([0], "test points")
    with pytest.raises(MeshError, match="not vertices"):
        build_model(mesh, 1.0, viscoelastic_params(len(mesh.edges)), fixed=[99])


def test_a_renumbered_model_is_the_same_model_and_moves_the_same():
    """Particles renumbered along the longest axis: the same particles, connectors (re-sorted,
    with their parameters) and, stepped, the same motion up to the force summation order."""
    model = box_model((4, 2, 2), a=-20.0, b=300.0)
    model = model.with_params(dataclasses.replace(  # every connector different
        model.params, K0=model.params.K0 * np.linspace(1.0, 2.0, model.n_connectors)))
    order = spatial_order(model)
    assert np.all(np.diff(model.rest_positions[order, 0]) >= 0)  # x: the first longest axis
    new, connectors = model.renumbered(order)
    np.testing.assert_array_equal(new.rest_positions, model.rest_positions[order])
    np.testing.assert_array_equal(new.fixed, model.fixed[order])
    assert np.all(new.edges[:, 0] < new.edges[:, 1])
    assert np.all(np.diff(new.edges[:, 0]) >= 0)
    np.testing.assert_array_equal(np.sort(order[new.edges], axis=1),
                                  np.sort(model.edges[connectors], axis=1))
    np.testing.assert_array_equal(new.params.K0, model.params.K0[connectors])
    np.testing.assert_array_equal(new.rest_lengths, model.rest_lengths[connectors])
    gravity = np.array([0.0, 0.0, -9.81])
    dt = 0.5 * critical_time_step(model)
    states = [model.state(), new.state()]
    for m, state in zip((model, new), states):
        VerletIntegrator().simulate(m, state, dt, 500, gravity=gravity)
    u = states[0].x - model.rest_positions
    np.testing.assert_allclose(states[1].x - new.rest_positions, u[order], rtol=0,
                               atol=1e-12 * np.abs(u).max())
    np.testing.assert_allclose(states[1].arm_force, states[0].arm_force[connectors], rtol=0,
                               atol=1e-12 * np.abs(states[0].arm_force).max())
    for bad in (order[:-1], np.zeros_like(order), order + 0.5):
        with pytest.raises(ParameterError, match="must be a permutation of 0"):
            model.renumbered(bad)


@pytest.mark.parametrize("make, error, message", [
    (lambda v, t: (v, np.where(t == t.max(), 10 ** 6, t)), MeshError,
     r"tet vertex ids must lie in \[0, \d+\], got range \[0, 1000000\] \(e\.g\. tet \d+: "),
    (lambda v, t: (v, t - 1), MeshError, r"tet vertex ids must lie in \[0, \d+\], got range \[-1,"),
    (lambda v, t: (v[:, :2], t), MeshError, r"vertices must be an \(N, 3\) array, got shape"),
    (lambda v, t: (v, t[:, :3]), MeshError, r"tets must be a \(T, 4\) array of vertex ids"),
    (lambda v, t: (v, t + 0.4), MeshError, r"tets: vertex ids must be integers, got 0\.4 at "
                                           r"index \(0, 0\)"),
    (lambda v, t: (np.where(np.arange(len(v))[:, None] == 5, np.nan, v), t), MeshError,
     r"non-finite coordinates at vertices \[5\]"),
])
def test_a_bare_mesh_is_checked_before_the_model_is_built(make, error, message):
    """build_model on a TetMesh: the shapes, dtypes and id ranges are checked beside the
    finite-coordinate check (inverted or degenerate tets: the Model's own check), instead of
    failing inside numpy or silently truncating float ids."""
    mesh = box_mesh((1, 1, 1))
    params = viscoelastic_params(len(mesh.edges))
    v, t = np.array(mesh.vertices), np.array(mesh.tets)
    with pytest.raises(error, match=message):
        build_model(TetMesh(*make(v, t)), 1000.0, params)


def test_inverted_tets_of_a_bare_mesh_are_still_refused_by_the_model():
    mesh = box_mesh((1, 1, 1))
    t = np.array(mesh.tets)
    t[2] = t[2][[1, 0, 2, 3]]
    with pytest.raises(MeshError, match=r"tet 2 \(particles .*\): rest volume .* must be > 0 "
                       r"\(inverted or degenerate tet\)"):
        build_model(TetMesh(mesh.vertices, t), 1000.0, viscoelastic_params(len(mesh.edges)))


def test_bad_fixed_ids_density_and_connector_counts_are_refused():
    mesh = box_mesh((1, 1, 1))
    params = viscoelastic_params(len(mesh.edges))
    with pytest.raises(MeshError, match=r"fixed vertices: vertex ids must be integers, got 0\.5 "
                       r"at index 0 \(2 non-integer value\(s\)\)"):
        build_model(mesh, 1000.0, params, fixed=[0.5, 1.7])
    model = build_model(mesh, 1000.0, params, fixed=np.array([0.0, 1.0]))  # integral: taken
    np.testing.assert_array_equal(np.nonzero(model.fixed)[0], [0, 1])
    for density in (np.array([1060.0, 1.0]), 0.0, -5.0, np.nan, "dense", None):
        with pytest.raises(ParameterError, match=r"density = .* kg/m\^3 must be one finite "
                                                 r"number > 0"):
            build_model(mesh, density, params)
    assert build_model(mesh, np.float32(1000.0), params).masses.sum() == pytest.approx(1000.0)
    with pytest.raises(MeshError, match="build_model needs a Problem or a TetMesh, got list"):
        build_model([mesh], 1000.0, params)
    for n in (-3, 2.5, "7"):
        with pytest.raises(ParameterError, match=rf"n_connectors = {n!r} must be an integer >= 0"):
            ConnectorParams.uniform(n, K0=40.0, k1=35.0, b1=19.0, k2=30.0, b2=270.0)
    assert ConnectorParams.uniform(np.int64(4), K0=40.0, k1=35.0, b1=19.0, k2=30.0,
                                   b2=270.0).n_connectors == 4


def test_finalize_refuses_tets_that_are_not_four_particle_ids():
    mesh = box_mesh((1, 1, 1))
    for tets, message in ((mesh.tets[:, :3], r"tets must be a \(T, 4\) array of particle ids, "
                                             r"got shape \(\d+, 3\)"),
                          (mesh.tets + 0.5, r"tets: vertex ids must be integers")):
        b = ModelBuilder()
        b.add_particles(mesh.vertices, np.ones(mesh.n_vertices))
        b.add_connectors(mesh.edges)
        with pytest.raises(MeshError, match=message):
            b.finalize(viscoelastic_params(len(mesh.edges)), tets=tets)
