"""The flat punch: its footprint rule, its refusals and the particle punch against closed forms."""
import numpy as np
import pytest

from calibration.network import linear_indentation
from forcecal.errors import SceneError
from forcecal.indenter import (footprint_edges, indenter_footprints, punch_candidates,
                               punch_footprint)
from forcecal.mesh import TetMesh, box_mesh, check_mesh
from forcecal.problem import build_problem
from forcecal.scene import load_scene, replace
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.model import build_model
from particle.params import ConnectorParams

UP = np.array([0.0, 0.0, 1.0])
DOWN = -UP


def _vertex_at(mesh: TetMesh, point) -> int:
    return int(np.argmin(np.linalg.norm(mesh.vertices - np.asarray(point), axis=1)))


def test_footprint_is_the_disc_on_the_tangent_plane():
    mesh = box_mesh((4, 4, 2), (1.0, 1.0, 0.5))  # top-face grid spacing 0.25
    centre = _vertex_at(mesh, (0.5, 0.5, 0.5))
    top = lambda ids: np.all(np.isclose(mesh.vertices[ids, 2], 0.5))  # noqa: E731
    # the 4 neighbours lie exactly on the rim (0.25): inside
    five = punch_footprint(mesh, centre, DOWN, 0.25)
    assert len(five) == 5 and top(five) and centre in five
    assert np.array_equal(punch_footprint(mesh, centre, DOWN, 0.3), five)  # diagonals at 0.354
    assert len(punch_footprint(mesh, centre, DOWN, 0.36)) == 9
    # a radius wider than the block: the whole top face (side nodes face sideways: n.n = 0)
    whole = punch_footprint(mesh, centre, DOWN, 10.0)
    assert len(whole) == 25 and top(whole)
    # P2 mid-edge nodes on the punch face: the surface edges between two footprint nodes
    edges = footprint_edges(mesh, five)
    assert len(edges) == 6 and np.all(np.isin(edges, five))  # 4 spokes + 2 face diagonals


def test_footprint_follows_the_surface_not_the_projection():
    # a step two cells high: the lower terrace faces up and projects inside the radius, but
    # the step face between them faces sideways, so the terrace is not connected to the punch
    box = box_mesh((4, 4, 4), (1.0, 1.0, 1.0))
    centroid = box.vertices[box.tets].mean(axis=1)
    keep = box.tets[~((centroid[:, 0] > 0.5) & (centroid[:, 2] > 0.5))]
    used = np.unique(keep)
    mesh = check_mesh(TetMesh(box.vertices[used], np.searchsorted(used, keep)))
    vertex = _vertex_at(mesh, (0.25, 0.5, 1.0))
    held = punch_footprint(mesh, vertex, DOWN, 0.6)
    x = mesh.vertices[held]
    assert np.all(x[:, 2] > 0.99)  # the upper terrace only
    assert np.any(np.isclose(x[:, 0], 0.5))  # up to its edge
    lower = np.nonzero(np.isclose(mesh.vertices[:, 2], 0.5) & (mesh.vertices[:, 0] > 0.7)
                       & (np.abs(mesh.vertices[:, 1] - 0.5) < 0.3))[0]
    assert len(lower) and not np.intersect1d(lower, held).size


def test_punch_refusals_name_the_radius_key():
    mesh = box_mesh((4, 4, 2), (1.0, 1.0, 0.5))
    centre = _vertex_at(mesh, (0.5, 0.5, 0.5))
    for bad in (0.0, -0.1):
        with pytest.raises(SceneError, match=r"indentation\.radius = .* must be > 0"):
            punch_footprint(mesh, centre, DOWN, bad)
    with pytest.raises(SceneError, match=rf"indentation\.radius = 0\.1 m: the punch footprint "
                                         rf"of test point {centre} holds 1 particle.*"
                                         rf"at least 0\.25 m"):
        punch_footprint(mesh, centre, DOWN, 0.1)
    # a punch on a side face that reaches the clamped base
    tall = box_mesh((4, 4, 4), (1.0, 1.0, 1.0))
    fixed = np.nonzero(np.isclose(tall.vertices[:, 2], 0.0))[0]
    side, inward = _vertex_at(tall, (0.0, 0.5, 0.5)), np.array([1.0, 0.0, 0.0])
    with pytest.raises(SceneError, match=rf"indentation\.radius = 0\.55 m: the punch footprint "
                                         rf"of test point {side} reaches clamped vertices.*"
                                         rf"below 0\.5 m"):
        punch_footprint(tall, side, inward, 0.55, fixed=fixed)
    assert len(punch_footprint(tall, side, inward, 0.3, fixed=fixed)) == 5


def test_scene_punch_keys(tmp_path):
    scene = load_scene("scenes/tiny.toml")
    punch = replace(scene, indentation={"indenter": "punch", "radius": 0.05})
    assert punch.indentation.radius == 0.05
    with pytest.raises(SceneError, match=r"indentation\.radius = 0\.0 m must be > 0"):
        replace(scene, indentation={"indenter": "punch"})
    with pytest.raises(SceneError, match=r"indentation\.radius"):
        replace(scene, indentation={"radius": 0.02})  # a radius on the vertex indenter
    with pytest.raises(SceneError, match=r"indentation\.radius"):
        replace(scene, indentation={"indenter": "punch", "radius": -1.0})
    assert [len(f) for f in indenter_footprints(box_mesh(), np.zeros(0, int), np.array([0]),
                                                np.array([[1.0, 0, 0]]), "vertex", 0.0)] == [1]


def _held_block():
    """A 2x2x1-cell block (Kuhn split, one connector per edge), base clamped, punch over the
    whole top face: every particle is clamped or held, so the force has a closed form."""
    mesh = box_mesh((2, 2, 1), (0.02, 0.02, 0.01))
    fixed = np.nonzero(np.isclose(mesh.vertices[:, 2], 0.0))[0]
    centre = _vertex_at(mesh, (0.01, 0.01, 0.01))
    held = punch_footprint(mesh, centre, DOWN, 0.05, fixed=fixed)
    assert len(held) == 9
    return mesh, fixed, centre, held


def _elongations(mesh, held, depth):
    """(E,) connector elongations [m] with ``held`` moved by ``depth`` down, and unit vectors."""
    x = mesh.vertices.copy()
    x[held] += depth * DOWN
    d = x[mesh.edges[:, 1]] - x[mesh.edges[:, 0]]
    length = np.linalg.norm(d, axis=1)
    return length - mesh.edge_lengths, d / length[:, None]


def _punch_force(mesh, held, tension, unit):
    """(3,) force the punch applies: minus the connectors' pull on the held particles."""
    f = np.zeros_like(mesh.vertices)
    np.add.at(f, mesh.edges[:, 0], tension[:, None] * unit)
    np.add.at(f, mesh.edges[:, 1], -tension[:, None] * unit)
    return -f[held].sum(axis=0)


def test_particle_punch_static_matches_closed_form():
    mesh, fixed, centre, held = _held_block()
    K0, a, b = 40.0, -30.0, 400.0
    params = ConnectorParams.uniform(len(mesh.edges), K0=K0, a=a, b=b, k1=10.0, b1=5.0,
                                     k2=5.0, b2=25.0)
    model = build_model(mesh, 1000.0, params, fixed=fixed)
    depths = np.linspace(2e-4, 2e-3, 10)
    ev = IndentationEvaluator(model, [centre], [DOWN], depths, footprints=[held])
    got = ev.force_vectors(params)[0]
    want = []
    for d in depths:
        dx, unit = _elongations(mesh, held, d)
        eps = dx / mesh.edge_lengths
        want.append(_punch_force(mesh, held, (K0 + a * eps + b * eps ** 2) * dx, unit))
    np.testing.assert_allclose(got, np.array(want), rtol=1e-9, atol=1e-12)
    # the sum over the footprint is a punch: twice the vertex-only force, at least
    vertex_only = IndentationEvaluator(model, [centre], [DOWN], depths)(params)[0]
    assert np.all(got @ DOWN > 2 * vertex_only)


def test_particle_punch_relaxation_matches_hereditary_integral():
    mesh, fixed, centre, held = _held_block()
    k, tau = np.array([10.0, 5.0]), np.array([0.5, 5.0])
    params = ConnectorParams.uniform(len(mesh.edges), K0=40.0, k1=k[0], b1=k[0] * tau[0],
                                     k2=k[1], b2=k[1] * tau[1])
    model = build_model(mesh, 1000.0, params, fixed=fixed)
    ramp, depth = 0.5, 2e-3
    times = np.r_[np.linspace(0.05, ramp, 10), ramp + np.geomspace(0.1, 20.0, 12)]
    depths = depth * np.minimum(times / ramp, 1.0)
    got = RelaxationEvaluator(model, [centre], [DOWN], times, depths,
                              footprints=[held]).force_vectors(params)[0]
    # independent: F_arm(t) = int_0^min(t, ramp) k exp(-(t-s)/tau) d(dx)/ds ds (the depth is
    # constant after the ramp) on a fine grid, with the elongation dx(s) of the exact geometry
    # (not linear in the depth)
    s = np.linspace(0.0, ramp, 20001)
    dx_s = np.array([_elongations(mesh, held, depth * si / ramp)[0] for si in s[::10]])
    rate = np.gradient(dx_s, s[::10], axis=0)  # (S', E)
    rate = np.array([np.interp(s, s[::10], rate[:, e]) for e in range(rate.shape[1])]).T
    want = []
    for t in times:
        inside = s <= t
        arm = sum(np.trapz(ki * np.exp(-(t - s[inside]) / ti)[:, None] * rate[inside], s[inside],
                           axis=0) for ki, ti in zip(k, tau))
        dx, unit = _elongations(mesh, held, np.interp(t, times, depths))
        want.append(_punch_force(mesh, held, 40.0 * dx + arm, unit))
    np.testing.assert_allclose(got @ DOWN, np.array(want) @ DOWN, rtol=2e-4)


def test_particle_punch_slope_is_the_linear_network_punch():
    # free particles under and around the punch: the evaluator's initial slope is the linear
    # network's punch slope, which calibration's initial guess uses
    mesh = box_mesh((4, 4, 2), (0.04, 0.04, 0.02))
    fixed = np.nonzero(np.isclose(mesh.vertices[:, 2], 0.0))[0]
    centre = _vertex_at(mesh, (0.02, 0.02, 0.02))
    held = punch_footprint(mesh, centre, DOWN, 0.011, fixed=fixed)
    assert len(held) == 5
    params = ConnectorParams.uniform(len(mesh.edges), K0=25.0, k1=1.0, b1=1.0, k2=1.0, b2=1.0)
    model = build_model(mesh, 1000.0, params, fixed=fixed)
    depth = 1e-7
    got = IndentationEvaluator(model, [centre], [DOWN], [depth], footprints=[held])(params)[0, 0]
    linear = linear_indentation(mesh, fixed, [centre], [DOWN], 25.0 * np.ones(len(mesh.edges)),
                                footprints=[held])
    assert got / depth == pytest.approx(linear.slope[0], rel=1e-5)


def test_convergence_changes_are_against_the_finest_level():
    from pipelines.bench.fe_convergence import summarise

    rows = [{"level": 0, "punch_force": [1.10, 2.0], "max_sag": 0.030},
            {"level": 1, "punch_force": [1.02, 2.02], "max_sag": 0.0345},
            {"level": 2, "punch_force": [1.00, 2.00], "max_sag": 0.035}]
    out = summarise(rows, default_level=1)
    assert out["finest_level"] == 2 and out["levels"] is rows
    assert out["punch_force_change"] == pytest.approx(0.02)  # the largest over the points
    assert out["sag_change"] == pytest.approx(5.0 / 35)  # the gravity runs' level 0
    assert out["punch_force_change_two_finest"] == out["punch_force_change"]
    assert out["sag_change_two_finest"] == pytest.approx(0.5 / 35)
    assert summarise(rows, default_level=0)["punch_force_change"] == pytest.approx(0.10)
    # each quantity against the finest level that has it: the sag stops at level 1 here
    rows.append({"level": 3, "punch_force": [0.99, 1.98], "max_sag": None})
    out = summarise(rows, default_level=2, default_sag_level=1)
    assert out["finest_level"] == 3 and out["finest_sag_level"] == 2
    assert out["punch_force_change"] == pytest.approx(1 / 99)
    assert out["sag_change"] == pytest.approx(0.5 / 35)


def test_convergence_levels_are_assembled_from_items_finished_in_any_order():
    """The study's forces and sags are independent items (run side by side by the bench): a
    level's row holds its points' forces in the order of the points, whatever order they
    finished in, and appears only once all its items have."""
    from pipelines.bench.fe_convergence import Item, level_rows

    points = np.array([7, 3])
    results = {Item(1, 3): {"force": 0.13, "dofs": 130, "wall_s": 2.0},
               Item(0): {"max_sag": 0.030, "dofs": 50, "wall_s": 4.0},
               Item(1): {"max_sag": 0.034, "dofs": 150, "wall_s": 8.0},
               Item(0, 3): {"force": 0.03, "dofs": 30, "wall_s": 1.0},
               Item(0, 7): {"force": 0.07, "dofs": 70, "wall_s": 3.0}}
    rows = level_rows(results, points, levels=(0, 1), sag_levels=(0, 1), element="TH")
    assert [r["level"] for r in rows] == [0]  # level 1 still waits for point 7
    assert rows[0]["punch_force"] == [0.07, 0.03] and rows[0]["dofs"] == [70, 30]
    assert rows[0]["max_sag"] == 0.030 and rows[0]["sag_dofs"] == 50
    assert rows[0]["wall_s"] == 8.0 and rows[0]["wall_s_punch_per_point"] == 2.0
    results[Item(1, 7)] = {"force": 0.17, "dofs": 170, "wall_s": 6.0}
    rows = level_rows(results, points, levels=(0, 1), sag_levels=(0, 1), element="TH")
    assert rows[1]["punch_force"] == [0.17, 0.13] and rows[1]["wall_s_sag"] == 8.0
    # a sag-only level has no forces; longest items are scheduled first
    assert level_rows(results, points, levels=(0,), sag_levels=(1,), element="TH")[1][
        "punch_force"] is None
    items = sorted([Item(0, 3), Item(2), Item(4, 3), Item(3, 3)], key=lambda i: -i.cost())
    assert items == [Item(2), Item(4, 3), Item(3, 3), Item(0, 3)]


def test_punch_candidates_keep_the_footprint_off_the_clamp():
    # the 4 x 4 x 4 block of the refusal test: spacing 0.25, base clamped
    tall = box_mesh((4, 4, 4), (1.0, 1.0, 1.0))
    fixed = np.nonzero(np.isclose(tall.vertices[:, 2], 0.0))[0]
    got = punch_candidates(tall, fixed, 0.3)
    low_side = _vertex_at(tall, (0.0, 0.5, 0.25))  # one cell above the clamp: its disc reaches it
    assert _vertex_at(tall, (0.5, 0.5, 1.0)) in got and low_side not in got
    inward = -tall.vertex_normals[got]
    for vertex, normal in zip(got, inward):  # every candidate is accepted ...
        punch_footprint(tall, vertex, normal, 0.3, fixed=fixed)
    for vertex in np.setdiff1d(np.setdiff1d(tall.surface_vertices, fixed), got):
        with pytest.raises(SceneError):  # ... and every other free surface vertex refused
            punch_footprint(tall, vertex, -tall.vertex_normals[vertex], 0.3, fixed=fixed)
    with pytest.raises(SceneError, match=r"indentation\.radius = 0\.1 m: no free surface vertex "
                                         r"has a punch footprint of at least 3 particles"):
        punch_candidates(tall, fixed, 0.1)  # narrower than the spacing: one particle each


def test_auto_test_points_of_a_punch_scene_can_all_be_indented():
    """With a punch, the "auto" rules pick among the vertices it can indent: on the coarse
    liver a 45 mm punch reaches the clamped base from some of the vertex rules' points."""
    scene = replace(load_scene("scenes/tiny.toml"), test_points={"calibration": "auto"})
    punch = replace(scene, indentation={"indenter": "punch", "radius": 0.045})
    vertex_points = build_problem(scene).test_points
    problem = build_problem(punch)
    held = indenter_footprints(problem.mesh, problem.fixed, problem.test_points,
                               problem.normals, "punch", 0.045)  # raises if one reaches
    assert len(held) == len(vertex_points) == 17 and min(len(h) for h in held) >= 3
    refused = 0
    for vertex, normal in zip(vertex_points, problem.mesh.inward_normals(vertex_points)):
        try:
            punch_footprint(problem.mesh, vertex, normal, 0.045, fixed=problem.fixed)
        except SceneError:
            refused += 1
    assert refused > 0  # without the candidates the punch scene would be refused


def _edge_of_a_slab():
    """A 80 x 80 x 40 mm slab of 5 x 20 x 20 mm cells and the vertex at the middle of its top
    face's edge y = 0: its inward normal leans 45 degrees (equal top and side areas), so the
    surface nodes along the edge (5 mm apart) lie in the plane of a punch's face there, and
    those across the edge (20 mm into the top or down the side) 20 mm x cos 45 = 14.1 mm
    off it, at 14.1 mm from the punch's axis. Two cells deep, so no node of the footprint has
    a normal at right angles to the vertex's (the bottom edge's, of a one-cell slab, whose
    dot product is zero up to round-off, in or out of the footprint by its sign)."""
    mesh = box_mesh((16, 4, 2), (0.08, 0.08, 0.04))
    vertex = int(np.argmin(np.linalg.norm(mesh.vertices - [0.04, 0.0, 0.04], axis=1)))
    return mesh, vertex, mesh.inward_normals(np.array([vertex]))[0]


def test_a_node_at_right_angles_is_out_of_the_footprint_on_every_machine():
    """On a one-cell slab the bottom edge's normal (0, -1, -1)/sqrt 2 is at right angles to
    the top edge's (0, -1, 1)/sqrt 2: their dot product is zero up to round-off, whose sign
    differs between machines (BLAS kernels, summation order: in on one, out on another).
    Nudged to either side by 1e-13 it stays out."""
    mesh = box_mesh((16, 4, 1), (0.08, 0.08, 0.02))
    x = mesh.vertices
    vertex = int(np.argmin(np.linalg.norm(x - [0.04, 0.0, 0.02], axis=1)))
    below = int(np.argmin(np.linalg.norm(x - [0.04, 0.0, 0.0], axis=1)))
    m = mesh.vertex_normals.copy()
    assert abs(m[below] @ m[vertex]) < 1e-15
    for nudge in (1e-13, -1e-13):
        nudged = m.copy()
        nudged[below] += nudge * m[vertex]
        mesh.__dict__["vertex_normals"] = nudged
        held = punch_footprint(mesh, vertex, -m[vertex], 0.021)
        assert below not in held and len(held) == 16


def test_the_radii_within_reach_drop_what_the_punch_face_never_touches():
    from forcecal.indenter import face_gaps, radii_within_reach
    mesh, vertex, normal = _edge_of_a_slab()
    np.testing.assert_allclose(normal, [0.0, np.sqrt(0.5), -np.sqrt(0.5)], atol=1e-15)
    held = punch_footprint(mesh, vertex, normal, 0.021)
    gaps = face_gaps(mesh, vertex, normal, held)
    # the 9 nodes along the edge within 21 mm of the axis, and 7 across it on each side
    # (5 mm apart along x, within sqrt(21^2 - 14.1^2) = 15.5 mm)
    assert len(held) == 23 and np.sum(gaps > 0.002) == 14
    np.testing.assert_allclose(gaps.max(), 0.02 * np.sqrt(0.5), rtol=1e-12)
    # within 2 mm of the face: the edge's nodes only, from 3 of them at 5 mm from the axis to 5
    # at 10 mm, until the nodes across the edge join at 14.1 mm
    smallest, beyond = radii_within_reach(mesh, vertex, normal, 0.021, 0.002)
    assert smallest == pytest.approx(0.005, rel=1e-12)
    assert beyond == pytest.approx(0.02 * np.sqrt(0.5), rel=1e-12)
    for r, n in ((smallest, 3), (0.0141, 5)):
        kept = punch_footprint(mesh, vertex, normal, r)
        assert len(kept) == n and face_gaps(mesh, vertex, normal, kept).max() < 1e-15
    assert face_gaps(mesh, vertex, normal, punch_footprint(mesh, vertex, normal, beyond)
                     ).max() > 0.002
    # a depth past the nodes across the edge: every radius up to the scene's; six nodes
    # within 2 mm: none
    assert radii_within_reach(mesh, vertex, normal, 0.021, 0.015) == (
        pytest.approx(0.005, rel=1e-12), np.nextafter(0.021, 1.0))
    assert radii_within_reach(mesh, vertex, normal, 0.021, 0.002, min_nodes=6) is None
