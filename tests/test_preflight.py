"""Mesh preflight: tet quality, face-connected parts, the small-strain stiffness, the support
check (rigid modes, linear sag) and the preflight numbers, against closed forms."""

import math

import numpy as np
import pytest

from forcecal.errors import StabilityError
from forcecal.mesh import TetMesh, box_mesh
from forcecal.preflight import (POOR_QUALITY, check_support, face_connected_parts,
                                mesh_preflight, particle_step_estimate, run_preflight,
                                small_strain_stiffness, tet_quality)
from forcecal.scene import MaterialSection, load_scene, replace

from tests.conftest import SCENES

REGULAR = TetMesh(np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0],
                            [-1.0, -1.0, 1.0]]), np.array([[0, 1, 2, 3]]))


def _positive(mesh: TetMesh) -> TetMesh:
    tets = mesh.tets.copy()
    flip = mesh.signed_volumes < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return TetMesh(mesh.vertices, tets)


def test_quality_is_one_for_the_regular_tet_and_the_closed_form_for_a_kuhn_tet():
    np.testing.assert_allclose(tet_quality(_positive(REGULAR)), 1.0, rtol=1e-12)
    # the Kuhn tet (0,0,0) (1,0,0) (1,1,0) (1,1,1) of a unit cube: faces 1/2, 1/2, sqrt(2)/2
    # twice -> r_in = 3 V / A = 0.5 / (1 + sqrt 2); circumsphere = the cube's, R = sqrt(3)/2
    box = box_mesh((1, 1, 1))
    np.testing.assert_allclose(tet_quality(box), math.sqrt(3) / (1 + math.sqrt(2)), rtol=1e-12)
    # a sliver: four well-spread vertices nearly in one plane, no short edge
    sliver = _positive(TetMesh(np.array([[0, 0, 0], [1, 1, 0], [1, 0, 1e-3], [0, 1, 1e-3]],
                                        float), np.array([[0, 1, 2, 3]])))
    assert tet_quality(sliver)[0] < 0.01 and sliver.edge_lengths.min() >= 1.0


def test_face_connected_parts_split_at_a_shared_edge_not_at_a_shared_face():
    assert face_connected_parts(box_mesh((2, 1, 1)))[0] == 1
    hinged = _two_boxes(shift=(1.0, 0.0, 1.0))  # the second box touches the first along an edge
    n, labels = face_connected_parts(hinged)
    assert n == 2 and np.bincount(labels).tolist() == [6, 6]


def _two_boxes(shift=(3.0, 0.0, 0.0)) -> TetMesh:
    """Two unit cubes (6 Kuhn tets each), the second moved by ``shift``; vertices at the
    same place are merged (a shared edge or face)."""
    a = box_mesh((1, 1, 1))
    b = box_mesh((1, 1, 1), origin=shift)
    vertices = np.concatenate([a.vertices, b.vertices])
    tets = np.concatenate([a.tets, b.tets + a.n_vertices])
    _, first, inverse = np.unique(np.round(vertices, 9), axis=0, return_index=True,
                                  return_inverse=True)
    return TetMesh(vertices[first], inverse.ravel()[tets])


def test_small_strain_stiffness_stores_the_energy_of_a_uniform_strain_exactly():
    """Linear tets represent a linear field exactly: 1/2 u.K u = V (mu A:A + lambda/2 tr(A)^2)
    for u = A x with A symmetric; rigid motions cost nothing."""
    mesh = box_mesh((2, 2, 1), size=(0.1, 0.05, 0.02))
    mu, kappa = 2400.0, 3e5
    k = small_strain_stiffness(mesh, mu, kappa)
    a = np.array([[1.0, 0.3, -0.2], [0.3, -0.5, 0.1], [-0.2, 0.1, 0.4]]) * 1e-3
    u = (mesh.vertices @ a.T).ravel()
    lame = kappa - 2 * mu / 3
    volume = 0.1 * 0.05 * 0.02
    np.testing.assert_allclose(0.5 * u @ (k @ u), volume * (mu * np.sum(a * a)
                                                            + lame / 2 * np.trace(a) ** 2),
                               rtol=1e-12)
    w = np.array([[0.0, -1.0, 2.0], [1.0, 0.0, -0.5], [-2.0, 0.5, 0.0]])  # a rotation
    rigid = (mesh.vertices @ w.T + [1.0, 2.0, 3.0]).ravel()
    assert np.abs(k @ rigid).max() < 1e-9 * np.abs(k).max()


def test_a_clamped_column_sags_by_the_closed_form():
    """A column clamped at its base, nu = 0 (lambda = 0: no lateral coupling), under its
    weight: u_z(H) = -rho g H^2 / (2 E) with E = 2 mu, which 1-D linear elements give exactly
    at the nodes: the top's mean u_z to 1e-4 (the Kuhn tets lump the weight unevenly over a
    cross-section, which tilts the column a little: the largest sag is a bit larger)."""
    height, rho, g, mu = 0.16, 1000.0, 9.81, 10000.0
    mesh = box_mesh((2, 2, 16), size=(0.01, 0.01, height))
    fixed = np.nonzero(mesh.vertices[:, 2] == 0.0)[0]
    material = MaterialSection(C10=mu / 2, C01=0.0, kappa=2 * mu / 3, density=rho,
                               prony_g=(), prony_tau=())
    check = check_support(mesh, fixed, material, np.array([0.0, 0.0, -g]))
    assert check.rigid_modes == 0 and check.holds
    exact = rho * g * height ** 2 / (2 * 2 * mu)
    top = mesh.vertices[:, 2] == height
    np.testing.assert_allclose(-check.displacement[top, 2].mean(), exact, rtol=1e-4)
    assert mesh.vertices[check.sag_vertex, 2] == height and exact < check.sag_m < 1.1 * exact


def test_a_body_the_clamp_does_not_reach_has_six_rigid_modes_and_is_refused():
    mesh = _two_boxes()
    fixed = np.nonzero(mesh.vertices[:, 0] == 0.0)[0]  # a face of the first box only
    scene = load_scene(SCENES / "tiny.toml")
    check = check_support(mesh, fixed, scene.material, np.array([0.0, 0.0, -9.81]))
    assert check.rigid_modes == 6 and not check.holds
    np.testing.assert_array_equal(check.free_vertices, np.arange(8, 16))  # the second box
    with pytest.raises(StabilityError, match=r"does not hold the body: .* 6 motion\(s\) cost "
                       r"no energy .* move 8 vertices .* face-connected part\(s\) \[1\] of 2, "
                       r"none of them clamped"):
        run_preflight(scene, mesh, fixed)


def test_a_part_hinged_on_an_edge_has_one_free_rotation():
    mesh = _two_boxes(shift=(1.0, 0.0, 1.0))
    fixed = np.nonzero(mesh.vertices[:, 2] == 0.0)[0]  # the bottom of the first box
    scene = load_scene(SCENES / "tiny.toml")
    check = check_support(mesh, fixed, scene.material, np.array([0.0, 0.0, -9.81]))
    assert check.rigid_modes == 1
    with pytest.raises(StabilityError, match=r"2 shared vertices"):
        run_preflight(scene, mesh, fixed)


def test_particle_step_of_one_regular_tet_is_the_closed_form():
    """One tet of edge a: k = E0 V / a^2 on every edge, m = rho V / 4 at every vertex, so
    dt = 2 / sqrt(2 k / m) = 2 / sqrt(8 E0 / (rho a^2))."""
    mesh = _positive(REGULAR)
    material = MaterialSection(C10=2000.0, C01=1000.0, kappa=3e5, density=1060.0,
                               prony_g=(0.35, 0.25), prony_tau=(0.5, 10.0))
    mu = 6000.0
    young = 9 * 3e5 * mu / (3 * 3e5 + mu)
    a = math.sqrt(8.0)
    dt, edge = particle_step_estimate(mesh, material)
    np.testing.assert_allclose(dt, 2.0 / math.sqrt(8 * young / (1060.0 * a * a)), rtol=1e-12)
    assert 0 <= edge < 6


def test_preflight_numbers_of_a_box_with_known_edges_and_qualities():
    # hung from its x = 0 face, gravity along the box (a bending cantilever this soft sags
    # more than its size)
    scene = replace(load_scene(SCENES / "tiny.toml"), gravity={"acceleration": [9.81, 0, 0]})
    mesh = box_mesh((2, 1, 1), size=(0.2, 0.1, 0.1))
    fixed = np.nonzero(mesh.vertices[:, 0] == 0.0)[0]
    pf = mesh_preflight(scene, mesh, fixed)
    # 2 cubes: 12 vertices, 12 tets; edges: 20 cube edges, 11 face diagonals, 2 body diagonals
    assert (pf["vertices"], pf["tets"], pf["edges"], pf["fixed_vertices"]) == (12, 12, 33, 4)
    assert pf["edge_min_m"] == pytest.approx(0.1) and pf["edge_max_m"] == pytest.approx(
        0.1 * math.sqrt(3))
    q = math.sqrt(3) / (1 + math.sqrt(2))  # every Kuhn tet
    assert pf["quality_min"] == pytest.approx(q) and pf["quality_median"] == pytest.approx(q)
    assert pf["poor_tets"] == 0 and pf["poor_quality"] == POOR_QUALITY
    assert len(pf["worst_tets"]) == 5 and pf["worst_tets"][0]["quality"] == pytest.approx(q)
    assert pf["parts"] == 1 and pf["support"]["holds"] and pf["support"]["rigid_modes"] == 0
    assert "radius ratio" in pf["quality_measure"]
    assert pf["fe_cost"]["vertex_steps"] > 0 and pf["particle_dt_s"] > 0
    assert any("the support holds the body" in s for s in pf["implications"])
    assert pf["warnings"] == []
