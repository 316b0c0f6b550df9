"""The shape-response study (studies/shape_response.py): its network tangents against the
whole-body module's and against the material part written out per connector and tet."""
import numpy as np

from particle.body import RestOperators, incremental_tangent
from particle.statics import weight_equilibrium
from studies.shape_response import inverted_tets, mac, network_tangent, shift, volume_ratio
from tests.test_body import _box_model


def test_the_full_network_tangent_is_the_whole_body_modules():
    """About the box's equilibrium under its weight along x (springs with a shape, per-tet kv
    with arms): the study's tangent with its initial stress is
    :func:`particle.body.incremental_tangent`'s, to round-off."""
    model = _box_model(arms=True)
    pattern = RestOperators.of(model).pattern
    x = weight_equilibrium(model, np.array([9.81, 0.0, 0.0]), 2)
    assert np.abs(x - model.rest_positions).max() > 1e-3  # a load that moves it
    ours = network_tangent(model, pattern, x).toarray()
    np.testing.assert_allclose(ours, incremental_tangent(model, pattern, x).toarray(),
                               rtol=0, atol=1e-12 * np.abs(ours).max())


def test_without_initial_stress_the_tangent_is_the_material_part_alone():
    """At a deformed state (every free particle moved by up to 2 mm), the tangent without its
    initial stress has the energy ``sum_e s_e (e_e . (d_j - d_i))^2 + sum_t (kv + kv1 + kv2)
    / V0 (g_t . d)^2`` for any motion ``d``: ``s_e = K0 + 2 a eps + 3 b eps^2 + k1 + k2``
    along the connector's current direction ``e_e``, ``g_t = dV/dx`` at the deformed
    positions (written out here, not the kernels')."""
    model = _box_model(arms=True)
    p = model.params
    pattern = RestOperators.of(model).pattern
    rng = np.random.default_rng(3)
    x = model.rest_positions.copy()
    free = model.free_nodes
    x[free] += rng.uniform(-0.002, 0.002, (len(free), 3))
    stiffness = network_tangent(model, pattern, x, initial_stress=False)
    i, j = model.edges.T
    d = x[j] - x[i]
    length = np.linalg.norm(d, axis=1)
    unit = d / length[:, None]
    eps = length / model.rest_lengths - 1.0
    axial = p.K0 + 2 * p.a * eps + 3 * p.b * eps ** 2 + p.k1 + p.k2
    a, b, c, e = (x[model.tets[:, k]] for k in range(4))
    grads = [None, np.cross(c - a, e - a) / 6, np.cross(e - a, b - a) / 6,
             np.cross(b - a, c - a) / 6]
    grads[0] = -(grads[1] + grads[2] + grads[3])
    bulk = (p.kv + p.kv1 + p.kv2) / model.rest_volumes
    for _ in range(3):
        motion = np.zeros_like(x)
        motion[free] = rng.standard_normal((len(free), 3))
        stretch = np.einsum("ij,ij->i", unit, motion[j] - motion[i])
        change = sum(np.einsum("ij,ij->i", g, motion[model.tets[:, k]])
                     for k, g in enumerate(grads))
        exact = axial @ stretch ** 2 + bulk @ change ** 2
        v = motion[free].ravel()
        np.testing.assert_allclose(v @ (stiffness @ v), exact, rtol=1e-11)


def test_inverted_tets_and_the_lowest_modes_shift():
    model = _box_model(arms=False)
    x = model.rest_positions
    assert inverted_tets(x, model.tets) is None
    flipped = x * np.array([1.0, 1.0, -1.0])  # a mirror image: every tet inverted
    assert inverted_tets(flipped, model.tets) == f"{len(model.tets)} tet(s) inverted at the " \
        "loaded vertices"
    np.testing.assert_allclose(shift([10.5, 3.0], [10.0, 1.0]), 0.05, rtol=1e-12)
    np.testing.assert_allclose(volume_ratio(model, x), 1.0, rtol=1e-12)
    np.testing.assert_allclose(volume_ratio(model, 0.9 * x), 0.9 ** 3, rtol=1e-12)
    assert volume_ratio(model, flipped) == -1.0
    shape = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    assert mac(shape, -3.0 * shape) == 1.0  # a shape's scale and sign do not count
    assert mac(shape, [[0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]) == 0.0
    np.testing.assert_allclose(mac(shape, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), 1.0 / 5.0)
