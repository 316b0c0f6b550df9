"""The nodal (one-ring averaged) volume term (particle/nodal_volume.py): its identities with
the per-tet term, gradients, tangent, the model's volume element, refusals, and the locking
it removes on a slender cantilever."""
import dataclasses
import pickle
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from forcecal.errors import MeshError, ParameterError, SceneError
from forcecal.mesh import box_mesh
from forcecal.scene import replace
from particle.model import ModelBuilder, build_model
from particle.nodal_volume import (mean_tet_pressures, nodal_arm_recursion, nodal_params,
                                   nodal_volume_energy, nodal_volume_forces_numpy,
                                   nodal_volume_tangent_numpy, node_volume_strains)
from particle.params import ConnectorParams, viscoelastic_params
from particle.reference_numpy import step_numpy
from particle.volume import (network_bulk_modulus, signed_volumes, volume_arm_pressures_numpy,
                             volume_energy, volume_forces_numpy, volume_gradients_numpy,
                             volume_hessian_numpy, volume_strains)
from tests.particle_models import box_model, compiled_and_numpy_steps
from tests.test_particle_volume import central_gradient, tangent_and_differences

TET = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.003, 0.018, 0.0], [0.004, 0.006, 0.017]])
ARMS = (1500.0, 1000.0)  # kv1, kv2 [Pa]
TAU = (0.05, 0.5)  # [s]


def with_volume(model, kv, arms=None, element="nodal"):
    """``model`` with the volume term ``kv`` [Pa] ((T,) or one value), its arms ``arms`` (kv1,
    kv2) [Pa] with the relaxation times ``TAU`` (None: elastic), on ``element``."""
    t = model.n_tets
    volume = {"kv": np.broadcast_to(np.asarray(kv, dtype=np.float64), (t,))}
    if arms is not None:
        volume.update(kv1=np.full(t, arms[0]), bv1=np.full(t, arms[0] * TAU[0]),
                      kv2=np.full(t, arms[1]), bv2=np.full(t, arms[1] * TAU[1]))
    return model.with_params(dataclasses.replace(model.params, **volume)).with_volume_element(
        element)


def single_tet(element, kv=2500.0, arms=None, K0=1e-9, fixed=(False,) * 4, **springs):
    builder = ModelBuilder()
    builder.add_particles(TET, np.full(4, 1e-3), np.array(fixed))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    model = builder.finalize(viscoelastic_params(6, K0, **springs),
                             tets=np.array([[0, 1, 2, 3]]))
    return with_volume(model, kv, arms, element)


def deformed(model, amplitude, seed):
    rng = np.random.default_rng(seed)
    return model.rest_positions + amplitude * rng.standard_normal(model.rest_positions.shape)


def random_kv_box(seed=3, arms=None):
    """A free (2, 2, 2) Kuhn box (48 tets) with kv 1-10 kPa drawn per tet, nodal."""
    model = box_model((2, 2, 2), fixed_bottom=False)
    kv = np.random.default_rng(seed).uniform(1e3, 1e4, model.n_tets)
    return with_volume(model, kv, arms)


def nodal_terms(model):
    """(tets, node volumes, nodal kv) of a nodal model, the twin's arguments."""
    return model.tets, model.node_volumes, nodal_params(model).kv


def arm_pressure_at(model, x, dt=1e-3):
    """(the nodal arms' summed pressures (N,) [Pa] after one step to ``x`` from a loaded arm
    state, their step coefficients c_1 + c_2 (N,) [Pa])."""
    rng = np.random.default_rng(11)
    n = model.n_particles
    prev, strain_prev = 50.0 * rng.standard_normal((n, 2)), 1e-3 * rng.standard_normal(n)
    r, c = nodal_arm_recursion(nodal_params(model), dt)
    strain = node_volume_strains(x, model.tets, model.node_volumes)
    return volume_arm_pressures_numpy(strain, r, c, prev, strain_prev).sum(axis=1), c.sum(1)


def per_tet_tangent(x, model):
    """(3N, 3N) the per-tet term's tangent [N/m] from volume_hessian_numpy."""
    n = 3 * model.n_particles
    out = np.zeros((n, n))
    for t, tet in enumerate(model.tets):
        dofs = (3 * tet[:, None] + np.arange(3)).ravel()
        out[np.ix_(dofs, dofs)] += volume_hessian_numpy(x, tet, model.rest_volumes[t],
                                                        model.params.kv[t])
    return out


@pytest.mark.parametrize("arms", [None, ARMS], ids=["elastic", "viscoelastic"])
def test_on_one_tet_the_nodal_term_is_the_per_tet_term(arms):
    """One tet: V0_n = V0/4, j_n = j, kv_n = kv (a volume-weighted mean of one value) and the
    pairwise mean of four equal pressures is exact, so forces, energy, arm step and tangent
    are the per-tet term's to round-off (1e-14 relative: kv_n = kv V0/4 / (V0/4) is one
    rounding off kv)."""
    tet, nodal = single_tet("tet", arms=arms), single_tet("nodal", arms=arms)
    x = deformed(tet, 1e-3, 0)
    assert nodal.node_volumes == pytest.approx(np.full(4, tet.rest_volumes[0] / 4), rel=1e-15)
    _, v0, kv = nodal_terms(nodal)
    np.testing.assert_allclose(kv, np.full(4, 2500.0), rtol=1e-15)
    j = volume_strains(x, tet.tets, tet.rest_volumes)
    np.testing.assert_allclose(node_volume_strains(x, tet.tets, v0), np.full(4, j[0]),
                               rtol=1e-14)
    per_tet_arm = nodal_arm = None
    if arms is not None:
        r, c = tet.params.volume_arm_recursion(1e-3)
        rn, cn = nodal_arm_recursion(nodal_params(nodal), 1e-3)
        np.testing.assert_allclose(rn, np.repeat(r, 4, axis=0), rtol=1e-15)
        np.testing.assert_allclose(cn, np.repeat(c, 4, axis=0), rtol=1e-14)
        per_tet_arm = volume_arm_pressures_numpy(j, r, c, np.array([[30.0, -20.0]]),
                                                 np.array([1e-3])).sum(axis=1)
        nodal_arm = volume_arm_pressures_numpy(np.full(4, j[0]), rn, cn,
                                               np.tile([30.0, -20.0], (4, 1)),
                                               np.full(4, 1e-3)).sum(axis=1)
    f_tet = volume_forces_numpy(x, tet.tets, tet.rest_volumes, tet.params.kv, per_tet_arm)
    f_nodal = nodal_volume_forces_numpy(x, nodal.tets, v0, kv, nodal_arm)
    np.testing.assert_allclose(f_nodal, f_tet, rtol=0, atol=1e-14 * np.abs(f_tet).max())
    assert nodal_volume_energy(x, nodal.tets, v0, kv) == pytest.approx(
        volume_energy(x, tet.tets, tet.rest_volumes, tet.params.kv), rel=1e-14)
    stiffness = None if arms is None else float(tet.params.volume_arm_recursion(1e-3)[1].sum())
    extra = () if arms is None else (stiffness, float(per_tet_arm[0]))
    k_tet = volume_hessian_numpy(x, tet.tets[0], tet.rest_volumes[0], 2500.0, *extra)
    nodal_arms = None if arms is None else (np.full(4, stiffness), nodal_arm)
    k_nodal = nodal_volume_tangent_numpy(x, nodal.tets, v0, kv, nodal_arms).toarray()
    np.testing.assert_allclose(k_nodal, k_tet, rtol=0, atol=1e-14 * np.abs(k_tet).max())


def test_a_uniform_dilation_adds_exactly_kv_to_the_bulk_modulus():
    """Under x -> c + s (x - c) every j_n is every tet's j, so the nodal energy is the per-tet
    energy for any kv field (sum_n kv_n V0_n = sum_t kv_t V0_t; round-off), and with one kv
    the forces are the per-tet forces too; at small strain E / (9/2 eps^2 V) = kv (O(eps))."""
    model = random_kv_box()
    tet = model.with_volume_element("tet")
    centre = model.rest_positions.mean(axis=0)
    tets, v0, kv = nodal_terms(model)
    for s in (0.95, 1.0 + 1e-6, 1.1):
        x = centre + s * (model.rest_positions - centre)
        assert nodal_volume_energy(x, tets, v0, kv) == pytest.approx(
            volume_energy(x, tets, model.rest_volumes, model.params.kv), rel=1e-12)
    uniform = with_volume(model, 4000.0)
    _, _, kv1 = nodal_terms(uniform)
    x = centre + 1.1 * (model.rest_positions - centre)
    f_tet = volume_forces_numpy(x, tets, model.rest_volumes, uniform.params.kv)
    np.testing.assert_allclose(nodal_volume_forces_numpy(x, tets, v0, kv1), f_tet, rtol=0,
                               atol=1e-13 * np.abs(f_tet).max())
    eps = 1e-6
    x = centre + (1 + eps) * (model.rest_positions - centre)
    volume = float(tet.rest_volumes.sum())
    assert nodal_volume_energy(x, tets, v0, kv1) / (4.5 * eps ** 2 * volume) == pytest.approx(
        4000.0, rel=1e-5)
    assert network_bulk_modulus(uniform, 1.0) == network_bulk_modulus(tet, 1.0)


@pytest.mark.parametrize("arms", [None, ARMS], ids=["elastic", "viscoelastic"])
def test_forces_are_minus_the_energy_gradient_and_balanced(arms):
    """Central differences of the energy (h = 1e-7 m on a 30 mm box: truncation ~(h/L)^2 =
    1e-11, round-off ~1e-16 E/h ~1e-12 of the forces) on a randomly deformed box with kv drawn
    per tet: 1e-7 of the largest force. The arms add a pressure that is no gradient of this
    energy; with them the forces are checked for balance only: the sums of the forces and of
    their torques vanish (translation and rotation invariance) to round-off."""
    model = random_kv_box(arms=arms)
    x = deformed(model, 5e-4, 1)
    tets, v0, kv = nodal_terms(model)
    arm = None if arms is None else arm_pressure_at(model, x)[0]
    f = nodal_volume_forces_numpy(x, tets, v0, kv, arm)
    scale = np.abs(f).max()
    if arms is None:
        fd = -central_gradient(lambda y: nodal_volume_energy(y, tets, v0, kv), x)
        np.testing.assert_allclose(f, fd, rtol=0, atol=1e-7 * scale)
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-14 * scale * len(x))
    size = np.ptp(x, axis=0).max()
    np.testing.assert_allclose(np.cross(x, f).sum(axis=0), 0.0, atol=1e-14 * scale * size * len(x))


@pytest.mark.parametrize("arms", [None, ARMS], ids=["elastic", "viscoelastic"])
def test_the_tangent_is_the_derivative_of_the_forces(arms):
    """nodal_volume_tangent_numpy against central differences of the forces (h = 1e-8 m; with
    arms the forces of one arm step, whose pressures move with j_n by c_1 + c_2): 1e-6 of the
    largest entry; symmetric; it couples particles that share a neighbour (two-ring), which
    the per-tet tangent does not."""
    model = random_kv_box(arms=arms)
    x = deformed(model, 5e-4, 2)
    tets, v0, kv = nodal_terms(model)

    def forces(y):
        arm = None if arms is None else arm_pressure_at(model, y)[0]
        return nodal_volume_forces_numpy(y, tets, v0, kv, arm).ravel()

    tangent_arms = None if arms is None else arm_pressure_at(model, x)[::-1]
    k = nodal_volume_tangent_numpy(x, tets, v0, kv, tangent_arms).toarray()
    h = 1e-8
    fd = np.empty_like(k)
    flat = x.ravel()
    for d in range(len(flat)):
        xp, xm = flat.copy(), flat.copy()
        xp[d] += h
        xm[d] -= h
        fd[:, d] = -(forces(xp.reshape(-1, 3)) - forces(xm.reshape(-1, 3))) / (2 * h)
    np.testing.assert_allclose(k, fd, rtol=0, atol=1e-6 * np.abs(k).max())
    np.testing.assert_allclose(k, k.T, rtol=0, atol=1e-13 * np.abs(k).max())
    coupled = np.abs(k).reshape(len(x), 3, len(x), 3).sum(axis=(1, 3)) > 0
    per_tet = np.abs(per_tet_tangent(x, model.with_volume_element("tet"))).reshape(
        len(x), 3, len(x), 3).sum(axis=(1, 3)) > 0
    assert (per_tet <= coupled).all() and coupled.sum() > per_tet.sum()


def test_the_model_carries_its_volume_element():
    """build_model/finalize/with_volume_element set it, with_params, renumbered and pickle keep
    it; node volumes are frozen quarters of the tets' volumes; the arm state is per particle;
    a bad element or a particle in no tet is refused."""
    mesh = box_mesh((2, 1, 1), (0.02, 0.01, 0.01))
    params = dataclasses.replace(viscoelastic_params(len(mesh.edges)), kv=np.array([3e3]),
                                 kv1=np.array([1e3]), bv1=np.array([50.0]),
                                 kv2=np.array([1e3]), bv2=np.array([500.0]))
    model = build_model(mesh, 1000.0, params, volume_element="nodal")
    assert model.volume_element == "nodal" and build_model(mesh, 1000.0, params).volume_element \
        == "tet"
    assert model.node_volumes.sum() == pytest.approx(model.rest_volumes.sum(), rel=1e-14)
    assert not model.node_volumes.flags.writeable
    assert model.with_params(params).volume_element == "nodal"
    state = model.state()
    assert state.volume_arm.shape == (model.n_particles, 2)
    assert state.volume_prev.shape == (model.n_particles,)
    order = np.arange(model.n_particles)[::-1]
    renumbered, _ = model.renumbered(order)
    assert renumbered.volume_element == "nodal"
    np.testing.assert_array_equal(renumbered.node_volumes, model.node_volumes[order])
    copy = pickle.loads(pickle.dumps(model))
    assert copy.volume_element == "nodal" and not copy.node_volumes.flags.writeable
    nodal = nodal_params(model)
    np.testing.assert_allclose(nodal.kv, 3e3, rtol=1e-15)
    np.testing.assert_allclose(nodal.arm_tau, np.tile([0.05, 0.5], (model.n_particles, 1)),
                               rtol=1e-15)
    with pytest.raises(ParameterError, match="volume_element = 'hex'"):
        model.with_volume_element("hex")
    builder = ModelBuilder()
    builder.add_particles(np.vstack([TET, [[0.1, 0.1, 0.1]]]), np.full(5, 1e-3))
    builder.add_connectors([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3], [3, 4]])
    with pytest.raises(MeshError, match="particle 4 belongs to no tet"):
        builder.finalize(viscoelastic_params(7), tets=np.array([[0, 1, 2, 3]]),
                         volume_element="nodal")


@pytest.mark.parametrize("arms", [None, ARMS], ids=["elastic", "viscoelastic"])
def test_the_numpy_step_on_one_tet_is_the_per_tet_step(arms):
    """step_numpy (the compiled loop's twin) runs the nodal term; on one tet 20 steps of it
    (arms advanced per particle) stay the per-tet run's to round-off."""
    runs = []
    for element in ("tet", "nodal"):
        model = single_tet(element, kv=5e4, arms=arms)
        state = model.state()
        state.x[:] = deformed(model, 5e-4, 4)
        state.x_prev[:] = state.x
        for _ in range(20):
            step_numpy(model, state, 1e-4)
        runs.append(state)
    np.testing.assert_allclose(runs[1].x, runs[0].x, rtol=0, atol=1e-15)
    if arms is not None:
        np.testing.assert_allclose(runs[1].volume_arm, np.repeat(runs[0].volume_arm, 4, 0),
                                   rtol=1e-11)


def test_paths_without_the_nodal_term_refuse_it(liver_scene):
    """The haptic strain envelope, the whole-body operators (so a scene with the experiment
    'body') and the export refuse a nodal model (never the per-tet term in its place), naming
    themselves; a scene without 'body' is accepted."""
    from particle.body import RestOperators
    from particle.envelope import StrainBands
    model = single_tet("nodal", fixed=(True, True, True, False))
    with pytest.raises(ParameterError, match="strain envelope .* nodal volume element"):
        StrainBands(model, 0.1)
    with pytest.raises(ParameterError, match="whole-body operators .* nodal volume element"):
        RestOperators.of(model)
    with pytest.raises(ParameterError, match="export .* nodal volume element"):
        from pipelines.export import model_document
        model_document(SimpleNamespace(model=model))
    nodal_scene = replace(liver_scene, particle={"volume": True, "volume_element": "nodal"})
    assert nodal_scene.particle.volume_element == "nodal"
    with pytest.raises(SceneError, match="experiment 'body': the whole-body operators"):
        replace(nodal_scene, experiments=["indentation", "body"])
    with pytest.raises(SceneError, match="needs particle.volume"):
        replace(liver_scene, particle={"volume_element": "nodal"})


def spring_tangent(model):
    """(3N, 3N) sparse tangent [N/m] of the linear springs at rest: K0 u u^T per connector."""
    d = model.rest_positions[model.edges[:, 1]] - model.rest_positions[model.edges[:, 0]]
    u = d / np.linalg.norm(d, axis=1)[:, None]
    block = model.params.K0[:, None, None] * u[:, :, None] * u[:, None, :]
    n = 3 * model.n_particles
    parts = []
    for a, b, sign in ((0, 0, 1.0), (1, 1, 1.0), (0, 1, -1.0), (1, 0, -1.0)):
        rows, cols = np.broadcast_arrays(3 * model.edges[:, a, None, None] + np.arange(3)[:, None],
                                         3 * model.edges[:, b, None, None] + np.arange(3))
        parts.append(sp.csr_matrix((sign * block.ravel(), (rows.ravel(), cols.ravel())),
                                   shape=(n, n)))
    return sum(parts)


def per_tet_rest_tangent(model):
    """(3N, 3N) the per-tet term's tangent at rest, ``sum_t kv_t / V0_t g_t g_t^T``."""
    g = volume_gradients_numpy(model.rest_positions, model.tets).reshape(model.n_tets, 12)
    dofs = (3 * model.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
    b = sp.csr_matrix((g.ravel(), (np.repeat(np.arange(model.n_tets), 12), dofs.ravel())),
                      shape=(model.n_tets, 3 * model.n_particles))
    return b.T @ sp.diags(model.params.kv / model.rest_volumes) @ b


def tip_deflection(model, tangent, load=1e-3):
    """Mean downward displacement [m] of the free end's particles under ``load`` [N] shared
    by them, small-deflection (the tangent at rest)."""
    x = model.rest_positions
    free = np.repeat(~model.fixed, 3)
    tip = np.nonzero(np.isclose(x[:, 0], x[:, 0].max()))[0]
    f = np.zeros((model.n_particles, 3))
    f[tip, 2] = -load / len(tip)
    u = np.zeros(3 * model.n_particles)
    u[free] = spla.spsolve(sp.csc_matrix(tangent)[free][:, free], f.ravel()[free])
    return -float(u.reshape(-1, 3)[tip, 2].mean())


#: the cantilever's deflections at kv = 1e3 and 1e5 x the springs' network bulk modulus,
#: relative to the springs alone (measured: per-tet 0.0547, 0.0426; nodal 0.8760, 0.8748)
LOCKING = {"per-tet": (0.0547, 0.0426), "nodal": (0.8760, 0.8748)}


def test_the_nodal_term_does_not_lock_a_slender_cantilever():
    """A 100 x 10 x 10 mm beam of 20 x 3 x 3 Kuhn cells (1080 tets), clamped at x = 0, 1 mN
    shared by its free end's particles, linear springs K0 = 100 N/m (network bulk modulus
    kappa = K0 sum L^2 / (9 V) = 48 kPa), with kv = 1e3 and 1e5 kappa. The springs alone
    deflect 2.76 mm. The per-tet term adds ~3 constraints per particle: its deflection falls
    to 5.5 % and 4.3 % of that (locked); the nodal term, one constraint per particle, keeps
    87.6 % and 87.5 %: the bending that is left is nearly isochoric and not stiffened by kv
    (what remains of the 12 % is the springs' Poisson ratio 1/4 pushed to 1/2 and the coarse
    section's own constraint). The ratios are asserted to 1e-3 (they are the numbers of one
    linear solve; the tolerance covers the solver's round-off and BLAS differences)."""
    mesh = box_mesh((20, 3, 3), (0.1, 0.01, 0.01))
    fixed = np.nonzero(np.isclose(mesh.vertices[:, 0], 0.0))[0]
    springs = ConnectorParams.uniform(len(mesh.edges), K0=100.0, k1=1.0, b1=1.0, k2=1.0, b2=1.0)
    base = build_model(mesh, 1000.0, springs, fixed=fixed)
    kappa = network_bulk_modulus(base, 100.0)
    assert kappa == pytest.approx(48481.48, rel=1e-6)
    k_springs = spring_tangent(base)
    alone = tip_deflection(base, k_springs)
    assert alone == pytest.approx(2.7631e-3, rel=1e-4)
    for k, ratio in enumerate((1e3, 1e5)):
        tet = with_volume(base, ratio * kappa, element="tet")
        nodal = tet.with_volume_element("nodal")
        per_tet = tip_deflection(tet, k_springs + per_tet_rest_tangent(tet)) / alone
        one_ring = tip_deflection(nodal, k_springs + nodal_volume_tangent_numpy(
            nodal.rest_positions, *nodal_terms(nodal))) / alone
        assert per_tet == pytest.approx(LOCKING["per-tet"][k], abs=1e-3)
        assert one_ring == pytest.approx(LOCKING["nodal"][k], abs=1e-3)
    assert LOCKING["nodal"][1] / LOCKING["per-tet"][1] > 20.0


def test_mean_tet_pressures_is_exact_for_equal_pressures():
    """The pairwise mean gives four equal pressures back exactly (a sequential sum need not:
    3 P can round)."""
    p = np.array([0.1 + 0.2, 1.0 / 3.0, 7.0 / 9.0])
    tets = np.array([[0, 0, 0, 0], [1, 1, 1, 1], [2, 2, 2, 2]])
    np.testing.assert_array_equal(mean_tet_pressures(tets, p), p)
    assert signed_volumes(TET, np.array([[0, 1, 2, 3]]))[0] > 0


# ---------------------------------------------------------------------------------------------
# the compiled explicit path. Each new typing of run_verlet costs ~3 s of compilation per test
# process, so the nodal tests share two: the elastic term with a recording (as gravity_dynamic
# calls it) and the relaxing term without (as the haptic session and blows_up call it), both
# on the nonlinear viscoelastic springs of NONLINEAR.

GRAVITY = np.array([0.0, 0.0, -9.81])
NONLINEAR = dict(a=-20.0, b=300.0)


def nodal_box(kv=2000.0, arms=None, n=(3, 3, 2)):
    return with_volume(box_model(n, **NONLINEAR), kv, arms)


def test_the_compiled_elastic_step_matches_the_numpy_step_and_records():
    """Springs + elastic nodal term (kv drawn per tet) + gravity + damping + a prescribed
    particle: the compiled loop against step_numpy, 50 steps, round-off only (1e-12 of the
    displacement); the recording holds the final positions."""
    model = nodal_box(np.random.default_rng(5).uniform(1e3, 4e3, 108))
    compiled, reference, recorded = compiled_and_numpy_steps(
        model, GRAVITY, record_nodes=[0, 40], record_steps=[50])
    scale = np.abs(reference.x - model.rest_positions).max()
    np.testing.assert_allclose(compiled.x, reference.x, rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(recorded[0], compiled.x[[0, 40]])


def test_the_compiled_relaxing_step_matches_the_numpy_step():
    """The same with the nodal arms (per particle, the paper's recursion): positions, arm
    pressures and strains to round-off."""
    model = nodal_box(arms=ARMS)
    compiled, reference, _ = compiled_and_numpy_steps(model, GRAVITY)
    scale = np.abs(reference.x - model.rest_positions).max()
    np.testing.assert_allclose(compiled.x, reference.x, rtol=0, atol=1e-12 * scale)
    pressure = np.abs(reference.volume_arm).max()
    assert pressure > 0 and compiled.volume_arm.shape == (model.n_particles, 2)
    np.testing.assert_allclose(compiled.volume_arm, reference.volume_arm, rtol=0,
                               atol=1e-10 * pressure)
    np.testing.assert_allclose(compiled.volume_prev, reference.volume_prev, rtol=0, atol=1e-13)


def test_the_haptic_force_includes_the_nodal_term():
    """A haptic session on a relaxing nodal model: the force of a step is minus the net
    internal force on the tool particle at the step's end, springs (their arms stepped) plus
    the nodal term (its arms stepped per particle, numpy twin): the probe's two-ring pass
    equals the whole pass to round-off, and Run.force_on gives it bit for bit."""
    from particle.reference_numpy import forces_numpy
    from tests.particle_models import haptic_push
    model = nodal_box(3e4, (1.5e4, 1e4))
    session, node, force = haptic_push(model)
    s = session.state
    x = s.x
    springs = dataclasses.replace(model.params, kv=None, kv1=None, bv1=None, kv2=None, bv2=None)
    f = forces_numpy(model.with_params(springs), s.copy(), session.dt)  # arms stepped
    vr, vc = nodal_arm_recursion(nodal_params(model), session.dt)
    strain = node_volume_strains(x, model.tets, model.node_volumes)
    pressure = volume_arm_pressures_numpy(strain, vr, vc, s.volume_arm,
                                          s.volume_prev).sum(axis=1)
    tets, v0, kv = nodal_terms(model)
    vol = nodal_volume_forces_numpy(x, tets, v0, kv, pressure)
    np.testing.assert_allclose(force, (f + vol)[node], rtol=1e-9,
                               atol=1e-12 * np.abs(f[node]).max())
    assert np.linalg.norm(vol[node]) > 0.05 * np.linalg.norm(force)  # measured 9 %
    elastic = nodal_volume_forces_numpy(x, tets, v0, kv)[node]  # the arms': 4 %
    assert np.linalg.norm(vol[node] - elastic) > 0.01 * np.linalg.norm(force)


def test_a_tet_leaving_its_volume_range_stops_a_nodal_run_naming_it():
    """The nodal run checks the tets' volume ratios (the range its stable step is bounded on)
    as the per-tet run does: one tet's free vertex driven through its opposite face in 100
    steps, V/V0 = 1 - 2 s/100 after step s, stops at step 44 (0.12 < (1 - 0.5)^3 = 0.125)
    with a StabilityError naming the tet and the step, as the per-tet test does."""
    from forcecal.errors import StabilityError
    from particle.integrator import VerletIntegrator
    from particle.model import Prescribed
    from particle.stability import critical_time_step
    model = single_tet("nodal", 1000.0, ARMS, K0=1.0, fixed=(True, True, True, False),
                       **NONLINEAR)
    dt = 0.5 * critical_time_step(model)
    x3 = model.rest_positions[3]
    motion = Prescribed([3], [0.0, 100 * dt], [[x3], [x3 - [0.0, 0.0, 2 * x3[2]]]])
    state = model.state()
    with pytest.raises(StabilityError, match=r"tet 0 \(particles 0-1-2-3\) reached volume "
                       r"ratio V/V0 = 0.12 at step 44 .*outside \[0.125, 3.375\]"):
        VerletIntegrator().simulate(model, state, dt, 200, prescribed=motion)
    assert np.all(np.isfinite(state.x))


def test_the_stability_bound_with_the_nodal_term_is_below_the_bisected_limit():
    """Rigorous for the explicit runs: critical_time_step of a relaxing nodal model is never
    above the limit found by bisection (3000 steps from rest perturbed by 1e-6 m); on a
    narrow strain range (+-1e-3) it is within a factor 2 of it."""
    from pipelines.bench.empirical_limit import bisect, blows_up
    from particle.stability import critical_time_step
    model = nodal_box(2e4, (1.2e4, 8e3))
    estimate = critical_time_step(model)
    empirical = bisect(lambda dt: blows_up(model, dt), estimate)
    narrow = critical_time_step(model, strain_range=(-1e-3, 1e-3))
    assert estimate < narrow <= empirical
    assert narrow / empirical > 0.5


@pytest.mark.parametrize("arms", [None, ARMS], ids=["elastic", "viscoelastic"])
def test_the_nodal_stability_bounds_hold_at_sampled_states(arms):
    """Every bound the stable step and mass scaling take of the nodal term is above the term's
    tangent at states in their range: a (3, 3, 2) box (bottom fixed) with kv drawn per tet
    (1-10 kPa), strains in +-0.1 (volume ratios in [0.9^3, 1.1^3] per tet), at rest and at
    random deformations inside both ranges, the arms (instantaneous coefficients c_i = kv_i,
    their largest) loaded to +- their pressure bound kv_i (J_hi - J_lo) per particle.
    Checked: volume_frequency_bound and the largest eigenvalue of volume_scalar_matrix >=
    lambda_max(M^-1/2 K M^-1/2); diag(D) (x) I - K (node_volume_stiffness_bound) and
    L_w (x) I - K (volume_edge_stiffness_bound, the graph Laplacian of its weights) positive
    semidefinite (to 1e-10 of the largest entry), all on the free particles."""
    from particle.volume_bounds import (node_volume_stiffness_bound, volume_edge_stiffness_bound,
                                        volume_frequency_bound, volume_ratio_range,
                                        volume_scalar_matrix)
    rng = np.random.default_rng(8)
    model = with_volume(box_model((3, 3, 2)), rng.uniform(1e3, 1e4, 108), arms)
    lo, hi = np.full(model.n_connectors, -0.1), np.full(model.n_connectors, 0.1)
    j_lo, j_hi = volume_ratio_range(model, lo, hi)
    omega2 = volume_frequency_bound(model, lo, hi)
    scalar = float(np.linalg.eigvalsh(volume_scalar_matrix(model, lo, hi).toarray()).max())
    node_bound = node_volume_stiffness_bound(model, lo, hi)
    w = volume_edge_stiffness_bound(model, lo, hi)
    n = model.n_particles
    laplacian = sp.csr_matrix((np.r_[w, w, -w, -w], (np.r_[model.edges[:, 0], model.edges[:, 1],
                                                          model.edges[:, 0], model.edges[:, 1]],
                                                    np.r_[model.edges[:, 0], model.edges[:, 1],
                                                          model.edges[:, 1], model.edges[:, 0]])),
                              shape=(n, n)).toarray()
    free = np.repeat(~model.fixed, 3)
    scale = np.repeat(1.0 / np.sqrt(model.masses), 3)[free]
    nodal = nodal_params(model)
    tets, v0, kv = nodal_terms(model)
    samples = 0
    largest = 0.0
    for k in range(12):
        x = deformed(model, 0.0 if k == 0 else 1e-4 * (1 + k % 3), k)
        x[model.fixed] = model.rest_positions[model.fixed]
        strain = (np.linalg.norm(x[model.edges[:, 1]] - x[model.edges[:, 0]], axis=1)
                  / model.rest_lengths - 1.0)
        ratio = signed_volumes(x, tets) / model.rest_volumes
        if not (np.all((lo <= strain) & (strain <= hi)) and np.all((j_lo < ratio) &
                                                                   (ratio <= j_hi))):
            continue
        samples += 1
        extra = None
        if arms is not None:
            span = np.full(n, -np.inf)
            np.maximum.at(span, tets.ravel(), np.repeat(j_hi - j_lo, 4))
            sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
            extra = (nodal.arm_stiffness.sum(1), sign * nodal.arm_stiffness.sum(1) * span)
        k_full = nodal_volume_tangent_numpy(x, tets, v0, kv, extra).toarray()
        k_free = k_full[free][:, free]
        mass_scaled = scale[:, None] * k_free * scale[None, :]
        top = float(np.linalg.eigvalsh(mass_scaled).max())
        largest = max(largest, top)
        tol = 1e-10 * np.abs(k_free).max()
        assert top <= omega2 and top <= scalar * (1 + 1e-12)
        assert np.linalg.eigvalsh(np.diag(np.repeat(node_bound, 3)[free]) - k_free).min() >= -tol
        assert np.linalg.eigvalsh(np.kron(laplacian, np.eye(3))[free][:, free] - k_free).min() \
            >= -tol
    assert samples >= 8 and largest > 0.0


def test_the_gravity_release_runs_the_nodal_term():
    """gravity_dynamic (release from rest under gravity, every particle recorded) on an elastic
    nodal model: its displacements are step_numpy's to round-off (it shares the elastic
    recorded typing of the compiled loop)."""
    from particle.experiments import gravity_dynamic
    from particle.stability import critical_time_step
    model = nodal_box(np.random.default_rng(6).uniform(1e3, 4e3, 108))
    dt = 0.5 * critical_time_step(model)
    shown = gravity_dynamic(model, GRAVITY, 40 * dt, dt, np.array([0.0, 20 * dt, 40 * dt]))
    state = model.state()
    for _ in range(40):
        step_numpy(model, state, dt, gravity=GRAVITY)
    sag = state.x - model.rest_positions
    assert np.abs(sag).max() > 0
    np.testing.assert_allclose(shown[-1], sag, rtol=0, atol=1e-12 * np.abs(sag).max())


def test_every_argument_a_nodal_run_passes_fits_numbas_fingerprint():
    """The nodal term adds one group to the compiled loop's arguments (the particles' volume
    and pressure scratch), which fits numba 0.56's type fingerprint with the others
    (particle.dispatch), arms and probe included."""
    from particle import dispatch, step_kernels
    from particle.integrator import VerletIntegrator, recording
    from particle.stability import critical_time_step
    from tests.particle_models import top_centre
    model = nodal_box(3000.0, ARMS)
    node = top_centre(model)
    run = VerletIntegrator().prepare(model, 0.5 * critical_time_step(model),
                                     prescribed_nodes=[node])
    state = model.state()
    probe = (node, *run._incident(node)[:1], np.empty(3), run._incident(node)[1])
    args = run.arguments(state, 1, (np.zeros(2), np.zeros((2, 1, 3))), 1.0,
                         recording(model, [node], [0, 1], 1), probe)
    assert len(args) == step_kernels.run_verlet.py_func.__code__.co_argcount
    assert [k for k, a in enumerate(args) if not dispatch.fits(a)] == []
    assert args[-1] is not None and len(args[-1]) == 2


# ---------------------------------------------------------------------------------------------
# statics: the compiled Newton loop with the nodal term (its tangent on the two-ring pattern)

def arm_step_of(model, seed=2, dt=0.01):
    """A quasi-static arm step (exact recursion over ``dt`` [s]) from a random loaded arm state
    of ``model`` (connectors and, with volume arms, the particles' volume arms)."""
    from particle.nodal_volume import element_arm_recursion
    from particle.statics import ArmStep, VolumeArmStep
    rng = np.random.default_rng(seed)
    p, n = model.params, model.n_volume_elements
    volume = None
    if p.has_volume_arms:
        volume = VolumeArmStep(*element_arm_recursion(model, dt, exact=True),
                               10.0 * rng.standard_normal((n, 2)), 1e-4 * rng.standard_normal(n))
    return ArmStep(*p.arm_recursion(dt, exact=True), 1e-3 * rng.standard_normal(
        (model.n_connectors, 2)), 1e-5 * rng.standard_normal(model.n_connectors), volume)


@pytest.mark.parametrize("arms", [None, ARMS], ids=["elastic", "viscoelastic"])
def test_the_static_tangent_is_the_derivative_of_the_forces_and_its_twins(arms):
    """The statics' assembled tangent of a nodal model (compiled, on the pattern extended by
    every particle's star pairs) against central differences of the statics' forces (h = 1e-8
    m: 1e-7 of the largest entry, measured 2e-10), with a quasi-static arm step when the term
    has arms; its volume part against the numpy twin nodal_volume_tangent_numpy (round-off,
    1e-12); the pattern holds the two-ring pairs the per-tet pattern lacks."""
    from particle.statics import TangentPattern, tangent_data
    model = nodal_box(np.random.default_rng(1).uniform(1e3, 1e4, 108), arms)
    x = deformed(model, 2e-4, 3)
    x[model.fixed] = model.rest_positions[model.fixed]
    step = None if arms is None else arm_step_of(model)
    tangent, fd = tangent_and_differences(model, x, step)
    np.testing.assert_allclose(tangent, fd, rtol=0, atol=1e-7 * np.abs(tangent).max())
    pat = TangentPattern.of(model)
    assert len(pat.indices) > len(TangentPattern.of(model.with_volume_element("tet")).indices)
    springs = dataclasses.replace(model.params, kv=None, kv1=None, bv1=None, kv2=None, bv2=None)
    forces_step = None if step is None else dataclasses.replace(step, volume=None)
    solver_tension = _tension(model, x, step)
    only_springs = sp.csc_matrix((tangent_data(model.with_params(springs), pat, x,
                                               solver_tension, springs, True, forces_step),
                                  pat.indices, pat.indptr)).toarray()
    twin_arms = None
    if step is not None:
        strain = node_volume_strains(x, model.tets, model.node_volumes)
        pressure = volume_arm_pressures_numpy(strain, step.volume.r, step.volume.c,
                                              step.volume.pressure_prev,
                                              step.volume.strain_prev).sum(axis=1)
        twin_arms = (step.volume.stiffness, pressure)
    twin = nodal_volume_tangent_numpy(x, *nodal_terms(model), twin_arms).toarray()
    free = np.repeat(~model.fixed, 3)
    volume_part = tangent - only_springs
    np.testing.assert_allclose(volume_part, twin[free][:, free], rtol=0,
                               atol=1e-12 * np.abs(twin).max())


def _tension(model, x, step):
    """(E,) connector tensions [N] at ``x`` with the arm step ``step`` (the statics' forces)."""
    from particle.statics import EquilibriumSolver, TangentPattern
    solver = EquilibriumSolver(model, np.zeros(0, np.int64), TangentPattern.of(model))
    return solver._evaluate(x, model.params, True, step, None).tension


def test_a_nodal_static_sag_balances_the_numpy_forces_and_unlocks_the_cantilever():
    """gravity_static (the compiled Newton loop) of the locking test's cantilever under a weak
    gravity (0.01 m/s^2: the springs alone sag 0.108 mm, 1 % of the section: nearly linear),
    kv = 100 kappa. The numpy twin's net force vanishes at the free particles (to the
    solver's tolerance: 1e-8 of the force scale, 4e-4 N, so 4e-8 of the 1e-4 N weight;
    1e-8 because the stiff volume term's round-off, ~1e-12 N, is above the default 1e-10
    for the per-tet term and the nodal one alike), and the sags are the small-deflection
    solves' within 2 %: the per-tet term keeps 15.5 % of the springs' sag (locked), the
    nodal term 87 %."""
    from particle.reference_numpy import forces_numpy
    from particle.statics import gravity_static
    mesh = box_mesh((20, 3, 3), (0.1, 0.01, 0.01))
    fixed = np.nonzero(np.isclose(mesh.vertices[:, 0], 0.0))[0]
    springs = ConnectorParams.uniform(len(mesh.edges), K0=100.0, k1=1.0, b1=1.0, k2=1.0, b2=1.0)
    base = build_model(mesh, 1000.0, springs, fixed=fixed)
    tet = with_volume(base, 100.0 * network_bulk_modulus(base, 100.0), element="tet")
    nodal = tet.with_volume_element("nodal")
    gravity = np.array([0.0, 0.0, -0.01])
    k_springs = spring_tangent(base)
    load = base.masses[:, None] * gravity
    sags, linear = {}, {}
    for name, model, k in (("springs", base, k_springs),
                           ("per-tet", tet, k_springs + per_tet_rest_tangent(tet)),
                           ("nodal", nodal, k_springs + nodal_volume_tangent_numpy(
                               nodal.rest_positions, *nodal_terms(nodal)))):
        sag = gravity_static(model, gravity, rtol=1e-8)
        sags[name] = -sag[:, 2].min()
        free = np.repeat(~model.fixed, 3)
        u = np.zeros(3 * model.n_particles)
        u[free] = spla.spsolve(sp.csc_matrix(k)[free][:, free], load.ravel()[free])
        linear[name] = -u.reshape(-1, 3)[:, 2].min()
        assert sags[name] == pytest.approx(linear[name], rel=0.02)
        if name == "nodal":
            state = nodal.state()
            state.x[:] = nodal.rest_positions + sag
            f = forces_numpy(nodal, state, 1.0, gravity=gravity, arms=False)
            assert np.abs(f[nodal.free_nodes]).max() < 1e-7 * nodal.masses.sum() * 0.01
    assert sags["springs"] == pytest.approx(1.076e-4, rel=1e-3)
    assert sags["per-tet"] < 0.2 * sags["springs"] and sags["nodal"] > 0.8 * sags["springs"]


def test_nodal_relaxation_curves_relax_to_the_static_force():
    """The evaluators on a relaxing nodal model (the particles' arms stepped exactly over each
    sample): a ramp-and-hold ends at the long-term static indentation force (the arms relaxed;
    within 2e-5, the per-tet test's tolerance: the particles still creep late in the hold),
    holds more force early in the hold, and the nodal term adds force to the springs'."""
    from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
    from tests.particle_models import top_centre
    model = nodal_box(4000.0, (3000.0, 2000.0))
    node = top_centre(model)
    normal = np.array([0.0, 0.0, -1.0])
    depth = 1e-3
    static = IndentationEvaluator(model, [node], normal[None], [depth])
    relax = RelaxationEvaluator(model, [node], normal[None], [0.05, 1.0, 5.0, 10.0],
                                [depth] * 4)
    f_static = static(model.params)[0, 0]
    f_relax = relax(model.params)[0]
    assert f_relax[-1] == pytest.approx(f_static, rel=2e-5)
    assert f_relax[0] > f_relax[-1]
    springs = dataclasses.replace(model.params, kv=None, kv1=None, bv1=None, kv2=None, bv2=None)
    assert f_static > static(springs)[0, 0]


# ---------------------------------------------------------------------------------------------
# the adjoint sensitivities through the nodal averaging (particle/sensitivity.py)

def nodal_sensitivities():
    """(params, {kind: evaluator}) on a relaxing nodal box (bottom fixed, nonlinear springs,
    kv 1-4 kPa and arms drawn per tet, per-tet relaxation times around TAU), its top-centre
    particle indented 0.5 and 1 mm, and held at 1 mm for 0.05-2 s; Newton converged to 1e-11
    of the force scale so that differences resolve 1e-8."""
    from particle.sensitivity import IndentationSensitivity, RelaxationSensitivity
    from tests.particle_models import top_centre
    rng = np.random.default_rng(12)
    base = box_model((3, 3, 2), **NONLINEAR)
    t = base.n_tets
    kv, k1, k2 = (rng.uniform(1e3, 4e3, t) for _ in range(3))
    params = dataclasses.replace(base.params, kv=kv, kv1=k1, bv1=k1 * TAU[0] * rng.uniform(
        0.7, 1.4, t), kv2=k2, bv2=k2 * TAU[1] * rng.uniform(0.7, 1.4, t))
    model = base.with_params(params).with_volume_element("nodal")
    node = [top_centre(model)]
    normal = np.array([[0.0, 0.0, -1.0]])
    kw = dict(strain_range=(-0.3, 0.3), rtol=1e-11)
    return params, {"indentation": IndentationSensitivity(model, node, normal, [5e-4, 1e-3],
                                                          **kw),
                    "relaxation": RelaxationSensitivity(model, node, normal,
                                                        [0.05, 0.2, 0.5, 2.0], [1e-3] * 4,
                                                        **kw)}


def test_nodal_sensitivities_match_finite_differences_and_the_numpy_twin():
    """The adjoint derivatives of a nodal model's curves with respect to every connector's
    parameters and every tet's kv, kv1, bv1, kv2, bv2 (through the particles' volume-weighted
    means, linear in them), along a random direction of each (every element scaled by its own
    factor in [0.5, 1.5]), against 4th-order central differences of the curves, to 1e-6 as
    the per-tet test: h = 3e-3 relative, the truncation ~h^4 ~1e-10 and the Newton tolerance's
    noise (1e-11 of the 0.23 N force over 12 h) ~1e-7 of the smallest derivative (measured
    <= 1.6e-7; 6e-7 at h = 1e-3); the compiled pass against its numpy twin to round-off
    (1e-12); the springs' arms and the volume arms act on the relaxation curves only."""
    from particle.params import PARAM_NAMES, VOLUME_ARM_NAMES
    params, evaluators = nodal_sensitivities()
    rng = np.random.default_rng(0)
    for kind, ev in evaluators.items():
        sens = ev.jacobian(params)
        np.testing.assert_array_equal(sens.forces, ev(params))
        ev.numpy_twin = True
        twin = ev.jacobian(params)
        ev.numpy_twin = False
        for name in PARAM_NAMES + ("kv",) + VOLUME_ARM_NAMES:
            value = getattr(params, name)
            if name == "kv":
                jac, want = sens.kv, twin.kv
            elif name in VOLUME_ARM_NAMES:
                k = VOLUME_ARM_NAMES.index(name)
                jac, want = sens.volume_arms[:, :, k], twin.volume_arms[:, :, k]
            else:
                k = PARAM_NAMES.index(name)
                jac, want = sens.connectors[:, :, k], twin.connectors[:, :, k]
            assert jac.shape[-1] == len(value)
            if kind == "indentation" and name not in ("K0", "a", "b", "kv"):
                assert not jac.any() and not want.any()
                continue
            assert np.abs(jac - want).max() <= 1e-12 * np.abs(want).max(), (kind, name)
            direction = rng.uniform(0.5, 1.5, len(value)) * value
            h = 3e-3

            def at(t):
                return ev(dataclasses.replace(params, **{name: value + t * direction}))

            fd = (8 * (at(h) - at(-h)) - (at(2 * h) - at(-2 * h))) / (12 * h)
            exact = np.einsum("pse,e->ps", jac, direction)
            assert np.abs(exact).max() > 0, (kind, name)
            assert np.abs(fd - exact).max() <= 1e-6 * np.abs(exact).max(), (kind, name)
