"""The discretisation floor: the ANP element against a closed form, its locking against plain
P1, the floor's runs on a small scene, its reference.h5 group and its report block."""
import dataclasses

import h5py
import numpy as np
import pytest

from forcecal.errors import ConvergenceError
from forcecal.h5io import FloorResult, GravityResult, read_reference, write_reference
from forcecal.mesh import TetMesh
from forcecal.scene import FESection, GravitySection, MaterialSection, load_scene, replace
from forcecal.schedules import record_times

from tests.conftest import SCENES

pytest.importorskip("dolfinx")

# the Kuhn split of a cube into six positively oriented tets sharing the diagonal 0-7 (corner
# bits: 4 di + 2 dj + dk)
KUHN = ((0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7))


def quarter_annulus(a: float, b: float, height: float, n_r: int, n_theta: int) -> TetMesh:
    """A quarter of a thick-walled tube (radii a < b, axis z) of one layer of n_r x n_theta
    polar hexahedra, each split into six tets."""
    r, t = np.linspace(a, b, n_r + 1), np.linspace(0.0, np.pi / 2, n_theta + 1)
    R, T, Z = np.meshgrid(r, t, [0.0, height], indexing="ij")
    vertices = np.c_[(R * np.cos(T)).ravel(), (R * np.sin(T)).ravel(), Z.ravel()]
    index = np.arange(len(vertices)).reshape(n_r + 1, n_theta + 1, 2)
    tets = []
    for i in range(n_r):
        for j in range(n_theta):
            corners = [index[i + di, j + dj, dk] for di in (0, 1) for dj in (0, 1)
                       for dk in (0, 1)]
            for tet in KUHN:
                ids = [corners[c] for c in tet]
                x = vertices[ids]
                if np.linalg.det(np.c_[x[1] - x[0], x[2] - x[0], x[3] - x[0]]) < 0:
                    ids[0], ids[1] = ids[1], ids[0]
                tets.append(ids)
    return TetMesh(vertices, np.array(tets))


def lame_work(a: float, b: float, height: float, mu: float, kappa: float,
              delta: float) -> float:
    """Work [J] of the pressure on the inner face of a quarter tube in plane strain whose inner
    radius is moved out by ``delta``, outer face free (linear elasticity, Lame):
    u(r) = A r + B / r, sigma_rr(b) = 0, u(a) = delta."""
    lam = kappa - 2.0 * mu / 3.0
    B = delta / (mu / ((lam + mu) * b ** 2) * a + 1.0 / a)
    A = mu * B / ((lam + mu) * b ** 2)
    pressure = 2.0 * mu * B / a ** 2 - 2.0 * (lam + mu) * A
    return pressure * delta * np.pi / 2.0 * a * height


def tube_work(element: str, kappa_over_mu: float, n_r: int, n_theta: int) -> tuple[float, float]:
    """(FE work of the inner face's reactions, closed form) of the Lame tube: plane strain (every
    z dof held), symmetry planes x = 0 and y = 0, inner vertices moved radially by 5e-6 a
    (the linear regime), long-term material without Prony terms."""
    from reference_fe.model import Constraint, FEModel, Load, initial_state, solve_step

    a, b, height, delta = 0.02, 0.05, 0.005, 1e-7
    C10, C01 = 2000.0, 1000.0
    mu = 2.0 * (C10 + C01)
    material = MaterialSection(C10=C10, C01=C01, kappa=kappa_over_mu * mu, density=1000.0,
                               prony_g=(), prony_tau=())
    mesh = quarter_annulus(a, b, height, n_r, n_theta)
    x = mesh.vertices
    model = FEModel(mesh, material, FESection(element=element, quadrature_degree=2))
    dofs = model.vertex_dofs
    inner = np.flatnonzero(np.isclose(np.hypot(x[:, 0], x[:, 1]), a))
    constraints = [Constraint(2, dofs[:, 2], 0.0),
                   Constraint(0, dofs[np.isclose(x[:, 0], 0.0, atol=1e-12), 0], 0.0),
                   Constraint(1, dofs[np.isclose(x[:, 1], 0.0, atol=1e-12), 1], 0.0)]
    for v in inner:
        for k in (0, 1):
            if abs(x[v, k]) > 1e-12:
                constraints.append(Constraint(k, dofs[[v], k], delta * x[v, k] / a))
    state = solve_step(model, initial_state(model), Load(tuple(constraints)), 1.0, dt=None)
    work = float((state.force[dofs[inner, :2]] * state.u[dofs[inner, :2]]).sum())
    return work, lame_work(a, b, height, mu, kappa_over_mu * mu, delta)


@pytest.mark.parametrize("kappa_over_mu", [50.0, 1000.0])
def test_anp_matches_the_lame_tube_and_plain_p1_locks(kappa_over_mu):
    # the work of the inner pressure (twice the strain energy) on a 8 x 16 polar mesh: ANP
    # within 2.5 % of the closed form at the liver's kappa/mu (50) and at 1000 (measured
    # +1.0 % and +2.0 %), and converging at second order (measured 4 x 8 -> 8 x 16: 5.0 ->
    # 1.0 % and 15 -> 2.0 %); plain P1 locks: +25 % and +400 % on the same mesh, growing with
    # kappa/mu
    work, exact = tube_work("ANP", kappa_over_mu, 8, 16)
    coarse, _ = tube_work("ANP", kappa_over_mu, 4, 8)
    locked, _ = tube_work("P1", kappa_over_mu, 8, 16)
    assert abs(work / exact - 1.0) < 0.025
    assert abs(work / exact - 1.0) < abs(coarse / exact - 1.0) / 4.0
    assert locked / exact - 1.0 > (0.2 if kappa_over_mu < 100 else 3.0)


@pytest.fixture(scope="module")
def tiny_floor():
    from forcecal.problem import build_problem
    from reference_fe.floor import floor_arrays, result_of

    scene = replace(load_scene(SCENES / "tiny.toml"), gravity={"duration": 0.05})
    problem = build_problem(scene)
    settings = dataclasses.replace(scene.gravity, tracked_node=problem.tracked_node)
    return scene, problem, result_of(floor_arrays(scene, problem), settings)


def test_floor_runs_both_elements_and_plain_p1_is_stiffer(tiny_floor):
    # on the tiny liver (78 vertices) the P2 reference sags 17.0 mm, ANP 10.1 mm, plain P1
    # 7.3 mm: locking-free is at least 25 % softer than P1 under the organ's weight
    scene, problem, floor = tiny_floor
    assert floor.elements == ("ANP", "P1") and not floor.failed
    sag = {e: np.linalg.norm(r.static_displacement, axis=1).max() for e, r in floor.runs.items()}
    assert sag["ANP"] > 1.25 * sag["P1"]
    np.testing.assert_allclose(sag["ANP"], 10.06e-3, rtol=0.02)
    for run in floor.runs.values():
        assert run.displacement.shape == (len(run.time), problem.mesh.n_vertices, 3)
        np.testing.assert_array_equal(run.displacement[:, problem.fixed], 0.0)
        assert np.isfinite(run.displacement).all() and run.displacement[-1].any()
    # the held-out points' curves (the scene does not run the second support): pushing in
    # takes force along the inward normal, less with ANP than with the locking P1 at the
    # full depth
    assert not floor.has_second_support
    normals = problem.normals[len(problem.calibration):]
    push = {e: np.einsum("psk,pk->ps", c.indentation, normals) for e, c in floor.held_out.items()}
    for e, curves in floor.held_out.items():
        np.testing.assert_array_equal(curves.vertices, problem.held_out)
        assert not curves.failed and curves.indentation.shape == (8, scene.indentation.steps, 3)
        assert curves.relaxation.shape == (8, scene.relaxation.ramp_steps
                                           + scene.relaxation.hold_steps, 3)
        assert np.all(push[e][:, -1] > 0.0)
    assert np.all(push["ANP"][:, -1] < push["P1"][:, -1])


def _reference_with_floor(problem, material, scale: float):
    """A reference whose gravity test is a uniform translation of the free vertices (static
    sag s, release s (1 - cos(2 pi t / 0.5 s))) and whose ANP floor is ``scale`` times it and
    P1's run failed."""
    settings = dataclasses.replace(GravitySection(duration=1.0, record_interval=0.01),
                                   tracked_node=problem.tracked_node)
    times = record_times(settings.duration, settings.record_interval)
    sag = np.array([0.0, 0.0, -0.01])
    static = np.where(problem.free[:, None], sag, 0.0)
    history = (1.0 - np.cos(2.0 * np.pi * times / 0.5))[:, None, None] * static[None]
    gravity = GravityResult(static, times, history, settings)
    floor = FloorResult({"ANP": GravityResult(scale * static, times, scale * history, settings)},
                        {"P1": "ConvergenceError: no convergence"}, {"ANP": 1.5, "P1": 0.5}, 2)
    return gravity, floor


def test_floor_group_round_trip_and_report_block(tmp_path, liver_problem, liver_scene):
    from pipelines.report import FLOOR_HELD_OUT_METRICS, FLOOR_SUPPORT_METRICS, floor_block
    from tests.test_h5io import _fake_reference

    gravity, floor = _reference_with_floor(liver_problem, liver_scene.material, 0.9)
    ref = dataclasses.replace(_fake_reference(liver_problem, liver_scene.material,
                                              gravity.settings), gravity=gravity, floor=floor)
    assert ref.experiments[-1] == "floor"
    write_reference(tmp_path / "reference.h5", ref)
    back = read_reference(tmp_path / "reference.h5").floor
    assert back.failed == floor.failed and back.seconds == floor.seconds
    assert back.quadrature_degree == 2 and back.elements == ("ANP", "P1")
    np.testing.assert_array_equal(back.runs["ANP"].displacement, floor.runs["ANP"].displacement)
    assert back.runs["ANP"].settings == gravity.settings

    errors = {"gravity_static": 0.05, "gravity_dynamic": 0.2}
    block = floor_block(liver_problem, gravity, back, errors, errors,
                        {"calibrated": {"period_error": 0.01, "first_peak_error": 0.02}})
    anp = block["elements"]["ANP"]
    # 0.9 x the reference: every free vertex 10 % short of its sag, the release's history and
    # peak 10 % short at the same period
    assert anp["static_sag"] == pytest.approx(0.1, rel=1e-12)
    expected_rms = 0.1 * np.sqrt(np.mean(np.sum(gravity.displacement[:, liver_problem.tracked_node]
                                                ** 2, axis=1))) / 0.02
    assert anp["release_rms"] == pytest.approx(expected_rms, rel=1e-12)
    assert anp["first_peak_error"] == pytest.approx(-0.1, abs=1e-9)
    assert anp["period_error"] == pytest.approx(0.0, abs=1e-9)
    assert anp["max_static_sag_m"] == pytest.approx(0.009) and anp["fe_seconds"] == 1.5
    assert block["elements"]["P1"]["static_sag"] is None
    assert block["elements"]["P1"]["failed"].startswith("ConvergenceError")
    assert block["floor_element"] == "ANP"
    assert block["calibrated"] == {"static_sag": 0.05, "release_rms": 0.2, "period_error": 0.01,
                                   "first_peak_error": 0.02, **dict.fromkeys(
                                       FLOOR_SUPPORT_METRICS + FLOOR_HELD_OUT_METRICS)}
    assert block["baseline"]["period_error"] is None
    # no second support and no held-out curves in this floor: their metrics are null
    assert all(anp[k] is None for k in FLOOR_SUPPORT_METRICS + FLOOR_HELD_OUT_METRICS)


def test_a_floor_whose_own_gravity_tests_failed_keeps_its_second_support(tmp_path,
                                                                         liver_problem,
                                                                         liver_scene):
    """Both elements' gravity tests failed (a support that does not hold the body), their
    second-support runs did not: the file keeps the second support's runs with their tracked
    node, and the ``gravity`` settings the reference's (the corpus armadillo with the recipe,
    standing on its feet, hung from its head)."""
    from tests.test_h5io import _fake_reference

    gravity, _ = _reference_with_floor(liver_problem, liver_scene.material, 0.9)
    held = int(np.flatnonzero(liver_problem.free)[0])
    held_settings = dataclasses.replace(gravity.settings, tracked_node=held)
    runs = GravityResult(0.5 * gravity.static_displacement, gravity.time,
                         0.5 * gravity.displacement, held_settings)
    failed = {"ANP": "ConvergenceError: no equilibrium", "P1": "ConvergenceError: diverged"}
    floor = FloorResult({}, failed, {"ANP": 1.5, "P1": 0.5}, 2, second_support={
        "ANP": runs, "P1": runs})
    ref = dataclasses.replace(_fake_reference(liver_problem, liver_scene.material,
                                              gravity.settings), gravity=None, floor=floor)
    write_reference(tmp_path / "reference.h5", ref)
    back = read_reference(tmp_path / "reference.h5").floor
    assert back.failed == failed and not back.runs
    for element in ("ANP", "P1"):
        np.testing.assert_array_equal(back.second_support[element].displacement,
                                      runs.displacement)
        assert back.second_support[element].settings == held_settings
    with h5py.File(tmp_path / "reference.h5") as fh:
        assert int(fh["floor/gravity"].attrs["tracked_node"]) == liver_problem.tracked_node


# --- the floor runs the reference's own experiments: a cantilever beam, every test -----------


@pytest.fixture(scope="module")
def beam_reference(tmp_path_factory):
    """The beam of tests/test_fe_second_support.py (20 vertices, P2, 1 calibration + 8 held-out
    points) with every experiment but the whole-body data, the floor included, through
    :func:`reference_fe.run.compute_reference`."""
    from reference_fe.run import compute_reference
    from tests.test_fe_second_support import END, ROOT, _problem, _scene

    scene = dataclasses.replace(_scene(ROOT, END), experiments=(
        "indentation", "relaxation", "gravity_static", "gravity_dynamic", "second_support",
        "floor"))
    problem = _problem(scene)
    out = tmp_path_factory.mktemp("beam") / "reference.h5"
    compute_reference(scene, problem, out_path=out, progress=False)
    return scene, problem, read_reference(out)


def _block(problem, reference, floor):
    from pipelines.report import floor_block, held_out_curves

    errors = {"gravity_static": 0.05, "gravity_dynamic": 0.2, "indentation_held_out": 0.03,
              "relaxation_held_out": 0.04}
    support = {"errors": {"static_sag": 0.06, "release_rms": 0.3},
               "baseline_errors": {"static_sag": 0.07, "release_rms": 0.35},
               "dynamic_metrics": {"calibrated": {"period_error": 0.01, "first_peak_error": 0.02}}}
    return floor_block(problem, reference.gravity, floor, errors, errors, None,
                       held_out=held_out_curves(reference),
                       second_support=reference.second_support, support_block=support)


def test_the_floor_with_the_references_element_is_the_reference(beam_reference):
    # the floor's runs with the reference's own [fe] (P2, degree 4) are the reference's
    # gravity test, second-support test and held-out curves bit for bit, so the floor runs
    # the same experiments; measured by the report's floor block, every error is zero
    from pipelines.report import FLOOR_HELD_OUT_METRICS, FLOOR_METRICS, FLOOR_SUPPORT_METRICS
    from reference_fe.floor import element_arrays, result_of

    scene, problem, reference = beam_reference
    first = len(problem.calibration)
    own = element_arrays(scene, problem, scene.fe)
    np.testing.assert_array_equal(own["held_out_vertices"], problem.held_out)
    np.testing.assert_array_equal(own["held_out_indentation_force"],
                                  reference.indentation.force[first:])
    np.testing.assert_array_equal(own["held_out_relaxation_force"],
                                  reference.relaxation.force[first:])
    np.testing.assert_array_equal(own["second_support_displacement"],
                                  reference.second_support.runs.displacement)
    np.testing.assert_array_equal(own["static_displacement"],
                                  reference.gravity.static_displacement)
    arrays = {f"ANP_{k}": v for k, v in own.items()}
    arrays["second_support_tracked_node"] = np.asarray(reference.second_support.runs.tracked_node)
    floor = result_of(arrays, reference.gravity.settings)
    row = _block(problem, reference, floor)["elements"]["ANP"]
    for key in ("static_sag", "release_rms") + FLOOR_SUPPORT_METRICS[:2] + FLOOR_HELD_OUT_METRICS:
        assert row[key] == 0.0, key
    for key in FLOOR_METRICS[2:] + FLOOR_SUPPORT_METRICS[2:]:  # a release's own period, peak
        assert row[key] == pytest.approx(0.0, abs=1e-12), key
    assert row["held_out_points"] == 8 and set(row["part_seconds"]) == {
        "build", "gravity", "second_support", "held_out"}


def test_the_floor_of_a_reference_has_every_metric(beam_reference):
    # reference.h5 /floor holds both elements' three tests; the block reports each metric,
    # finite, next to the particle models' values of the same metrics
    from pipelines.report import FLOOR_HELD_OUT_METRICS, FLOOR_METRICS, FLOOR_SUPPORT_METRICS

    scene, problem, reference = beam_reference
    floor = reference.floor
    assert floor.elements == ("ANP", "P1") and set(floor.second_support) == {"ANP", "P1"}
    block = _block(problem, reference, floor)
    metrics = FLOOR_METRICS + FLOOR_SUPPORT_METRICS + FLOOR_HELD_OUT_METRICS
    for element, row in block["elements"].items():
        assert all(np.isfinite(row[k]) for k in metrics), (element, row)
        assert row["held_out_points"] == 8 and row["held_out_not_in_reference"] == []
        # a vertex-dof model pushed at one vertex is stiffer than P2: its error is real
        assert row["indentation_held_out"] > 0.05
    assert block["calibrated"]["second_support_static_sag"] == 0.06
    assert block["baseline"]["second_support_release_rms"] == 0.35
    assert block["calibrated"]["second_support_period_error"] == 0.01
    assert block["baseline"]["indentation_held_out"] == 0.03
    assert block["second_support_fe_max_static_sag_m"] > 0.0


def test_a_failed_floor_run_is_recorded_not_raised(tmp_path, beam_reference, monkeypatch):
    # ANP's relaxation fails at the second held-out point and P1's second-support release
    # fails: both recorded (NaN rows and the reason, the reason), stored, and the block
    # measures the other points and leaves the failed test null with its reason
    from reference_fe import experiments as ex
    from reference_fe.floor import arrays_of, floor_arrays, result_of

    scene, problem, reference = beam_reference
    relax, release = ex.held_relaxation_curve, ex.gravity_dynamic
    bad_vertex = int(problem.held_out[1])

    def relaxation(model, fixed, dofs, normal, times, depths, what):
        if model.fe.element == "ANP" and what.endswith(f"vertex {bad_vertex}"):
            raise ConvergenceError("relaxation: step 3 did not converge")
        return relax(model, fixed, dofs, normal, times, depths, what)

    def dynamic(model, *args, section="fixed", **kwargs):
        if model.fe.element == "P1" and section == "second_support":
            raise ConvergenceError("second support dynamic: step 2 did not converge")
        return release(model, *args, section=section, **kwargs)

    monkeypatch.setattr(ex, "held_relaxation_curve", relaxation)
    monkeypatch.setattr(ex, "gravity_dynamic", dynamic)
    floor = result_of(floor_arrays(scene, problem), reference.gravity.settings)
    anp = floor.held_out["ANP"]
    assert set(anp.failed) == {bad_vertex} and "step 3" in anp.failed[bad_vertex]
    assert np.isnan(anp.relaxation[1]).all() and np.isnan(anp.indentation[1]).all()
    assert np.isfinite(np.delete(anp.relaxation, 1, axis=0)).all()
    assert floor.second_support_failed["P1"].startswith("ConvergenceError: second support")
    assert set(floor.second_support) == {"ANP"} and set(floor.runs) == {"ANP", "P1"}

    write_reference(tmp_path / "reference.h5", dataclasses.replace(reference, floor=floor))
    back = read_reference(tmp_path / "reference.h5").floor
    assert back.held_out["ANP"].failed == anp.failed
    np.testing.assert_array_equal(back.held_out["ANP"].relaxation, anp.relaxation)
    assert back.second_support_failed == floor.second_support_failed
    # a reused /floor (reference_fe.run.experiment_arrays) gives the same result back
    again = result_of(arrays_of(back), reference.gravity.settings)
    assert again.second_support_failed == back.second_support_failed
    assert again.held_out["ANP"].failed == anp.failed and again.part_seconds == back.part_seconds
    np.testing.assert_array_equal(again.second_support["ANP"].displacement,
                                  back.second_support["ANP"].displacement)
    assert again.second_support["ANP"].tracked_node == reference.second_support.runs.tracked_node
    block = _block(problem, reference, back)
    assert block["elements"]["ANP"]["held_out_points"] == 7
    assert np.isfinite(block["elements"]["ANP"]["relaxation_held_out"])
    assert block["elements"]["P1"]["second_support_static_sag"] is None
    assert block["elements"]["P1"]["second_support_failed"].startswith("ConvergenceError")
