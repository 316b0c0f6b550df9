"""The FE side of the second held-out body test (experiment ``second_support``): the gravity
test's own code with the other clamp, and a failure recorded rather than ending the reference.

The body: an 80 x 20 x 20 mm beam (4 x 1 x 1 cells, P2), stiff enough (mu_inf = 240 kPa) to
sag about a millimetre as a cantilever. Clamped at x = 0 ([fixed]) with its second support at
x = 80 mm, and the same scene with the two supports swapped: the second support's static sag
and release of the one are the gravity test's of the other, to round-off (they clamp the same
vertices of the same mesh, on the particle mesh and on a refined FE mesh).
"""

import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from forcecal.errors import ConvergenceError, DataFileError  # noqa: E402
from forcecal.h5io import read_reference  # noqa: E402
from forcecal.mesh import box_mesh  # noqa: E402
from forcecal.point_selection import fixed_nodes  # noqa: E402
from forcecal.problem import Problem, second_support, tracked_node_by_rule  # noqa: E402
from forcecal.scene import scene_from_dict  # noqa: E402
from pipelines.runners.common import Context  # noqa: E402
from pipelines.runners.reference import scene_after_reference  # noqa: E402
from reference_fe import experiments as ex  # noqa: E402
from reference_fe.model import FEModel  # noqa: E402
from reference_fe.refine import fe_problem  # noqa: E402
from reference_fe.run import WorkItem, compute_item, compute_reference, run_keys  # noqa: E402

pytestmark = pytest.mark.fe

MESH = box_mesh((4, 1, 1), (0.08, 0.02, 0.02))
END = {"axis": "x", "side": "max", "tolerance": 1e-4}
ROOT = {"axis": "x", "side": "min", "tolerance": 1e-4}
SECTIONS = {"material": {"C10": 2e5, "C01": 1e5, "kappa": 3e7},
            "gravity": {"duration": 0.015, "fe_dt": 0.005, "record_interval": 0.005},
            "indentation": {"depth": 0.001}}


def _scene(fixed: dict, second: dict, **fe):
    return scene_from_dict({**SECTIONS, "fixed": fixed, "second_support": second, "fe": fe,
                            "experiments": ["indentation", "relaxation", "gravity_static",
                                            "gravity_dynamic", "second_support"]})


def _problem(scene) -> Problem:
    """The beam clamped by ``scene``'s [fixed], one calibration and eight held-out points on its
    free top face and side (what the indentation items need; the gravity items do not)."""
    f = scene.fixed
    fixed = fixed_nodes(MESH, f.axis, f.side, f.tolerance)
    free = np.setdiff1d(np.arange(MESH.n_vertices), fixed)
    return Problem(mesh=MESH, fixed=fixed, calibration=free[:1], held_out=free[1:9],
                   tracked_node=tracked_node_by_rule(MESH, fixed, "farthest_from_support"))


@pytest.mark.parametrize("refine", [0, 1])
def test_the_second_support_is_the_gravity_test_with_the_supports_swapped(refine):
    a, b = _scene(ROOT, END, refine=refine), _scene(END, ROOT, refine=refine)
    pa, pb = _problem(a), _problem(b)
    fe_a, fe_b = fe_problem(pa, a.fe), fe_problem(pb, b.fe)
    model = FEModel(fe_a.problem.mesh, a.material, a.fe)
    second = compute_item(model, a, pa, WorkItem("second_support", -1, 0.0), fe_a)
    static = compute_item(model, b, pb, WorkItem("gravity_static", -1, 0.0), fe_b)
    release = compute_item(model, b, pb, WorkItem("gravity_dynamic", -1, 0.0), fe_b)
    scale = np.abs(static["displacement"]).max()
    np.testing.assert_allclose(second["static_displacement"], static["displacement"],
                               rtol=0, atol=1e-9 * scale)
    np.testing.assert_array_equal(second["time"], release["time"])
    np.testing.assert_allclose(second["displacement"], release["displacement"], rtol=0,
                               atol=1e-9 * scale)
    # the second support holds its own end, the beam hangs from it: the free end at x = 0
    held = second_support(a, pa)
    assert np.array_equal(held.fixed, pb.fixed) and held.tracked_node == pb.tracked_node
    assert np.all(second["static_displacement"][held.fixed] == 0.0)
    tip = second["static_displacement"][held.tracked_node]
    assert MESH.vertices[held.tracked_node, 0] == 0.0 and -3e-3 < tip[2] < -3e-4
    largest = np.argmax(np.linalg.norm(second["static_displacement"], axis=1))
    assert MESH.vertices[largest, 0] == 0.0  # the largest sag is at the free end


@pytest.mark.parametrize("prony_g, peak", [((0.01, 0.01), (1.9, 2.1)), ((0.35, 0.25), (0.7, 1.0))],
                         ids=["nearly elastic", "the default Prony terms"])
def test_a_release_on_a_sound_support_swings_within_twice_its_static_sag(prony_g, peak):
    """The premise of :data:`reference_fe.experiments.RELEASE_RUNAWAY_LIMIT`: released from
    rest under its weight, the cantilever beam's largest displacement peaks (first swing,
    about 22 ms) at twice its static sag when it is nearly elastic (a step load on a linear
    oscillator); with the default Prony terms the static sag is the long-term one, 1 / 0.4 x
    the instantaneous, and the swing stays below it. Either way below the limit of 3."""
    scene = scene_from_dict({**SECTIONS, "fixed": ROOT, "second_support": END,
                             "material": {**SECTIONS["material"], "prony_g": list(prony_g)},
                             "gravity": {"duration": 0.05, "fe_dt": 0.002,
                                         "record_interval": 0.002},
                             "experiments": ["indentation", "relaxation", "gravity_static",
                                             "gravity_dynamic"]})
    problem = _problem(scene)
    fe = fe_problem(problem, scene.fe)
    model = FEModel(fe.problem.mesh, scene.material, scene.fe)
    g = scene.gravity
    static = ex.gravity_static(model, problem.fixed, g.acceleration, g.static_load_steps)
    sag = np.linalg.norm(static, axis=1).max()
    times, disp = ex.gravity_dynamic(model, problem.fixed, g.acceleration, g.duration, g.fe_dt,
                                     g.record_interval, static_sag=sag)
    swing = np.linalg.norm(disp, axis=2).max(axis=1) / sag
    assert peak[0] < swing.max() < peak[1] < ex.RELEASE_RUNAWAY_LIMIT
    assert 0.015 < times[np.argmax(swing)] < 0.03


def test_a_release_says_how_far_the_body_moved_when_it_fails_or_runs_away(monkeypatch):
    """The beam's release on its second support, 3 steps of 5 ms: against a static sag it
    passes a tenth of, it stops at its first record as a support that does not hold the body
    in motion; a step that does not converge says what the last completed step shows."""
    from forcecal.errors import StabilityError
    from reference_fe.model import StepFailed
    scene = _scene(ROOT, END)
    problem = _problem(scene)
    fe = fe_problem(problem, scene.fe)
    model = FEModel(fe.problem.mesh, scene.material, scene.fe)
    held = second_support(scene, problem).fixed
    g = scene.gravity

    def release(static_sag):
        return ex.gravity_dynamic(model, held, g.acceleration, g.duration, g.fe_dt,
                                  g.record_interval, "second_support", static_sag=static_sag)
    times, disp = release(None)
    moved = np.linalg.norm(disp, axis=2).max(axis=1)  # (S,) the body's largest displacement
    assert len(times) == 4 and moved[0] == 0.0 and 0 < moved[1] < moved[2] < moved[3]
    with pytest.raises(StabilityError, match=(
            r"^second support dynamic: the release has moved the body by .* mm at 0.005 s, "
            r"10.00 x its static sag of .*: it falls over or buckles: the \d+ fixed vertices of "
            r"the \[second_support\] section do not hold the body in motion")) as info:
        release(moved[1] / 10.0)
    assert info.value.reached == pytest.approx(0.005)
    solve = ex.solve_step

    def diverging(model_, state, load, progress, **kwargs):
        if progress > 0.01 + 1e-9:
            raise StepFailed("diverging Newton iterate")
        return solve(model_, state, load, progress, **kwargs)
    monkeypatch.setattr(ex, "solve_step", diverging)
    with pytest.raises(ConvergenceError, match=(
            r"second support dynamic: step 3/3 \(to 0.015 s\) did not converge from 0.01 s "
            r"even after 6 halvings .*; at 0.01 s, the last completed time step: the body has "
            r"moved by ([0-9.]+) mm \(0.5 x its static sag\)$")) as info:
        release(2.0 * moved[2])
    assert float(info.value.args[0].split("moved by ")[1].split(" mm")[0]) == pytest.approx(
        moved[2] * 1e3, rel=1e-2)
    assert info.value.reached == 0.01


def test_each_release_of_a_reference_is_checked_against_its_own_supports_sag(tmp_path,
                                                                            monkeypatch):
    """In a whole reference run, the scene's release gets the static sag of the scene's clamp
    and the second support's release that of the second support, both the largest
    displacement at the particle vertices that ``reference.h5`` stores; the scene's sag also
    when it was taken over from the previous ``reference.h5`` instead of computed."""
    scene = dataclasses.replace(_scene(ROOT, END), experiments=(
        "indentation", "gravity_static", "gravity_dynamic", "second_support"))
    release, seen = ex.gravity_dynamic, {}

    def recording(*args, section="fixed", **kwargs):
        seen[section] = kwargs["static_sag"]
        return release(*args, section=section, **kwargs)
    monkeypatch.setattr(ex, "gravity_dynamic", recording)
    out = tmp_path / "reference.h5"
    first = dataclasses.replace(scene, experiments=("indentation", "gravity_static"))
    compute_reference(first, _problem(scene), out_path=out, progress=False)
    compute_reference(scene, _problem(scene), out_path=out, progress=False)
    back = read_reference(out)
    assert "gravity_static" not in json.loads(back.meta["items_computed"])  # taken over
    assert seen["fixed"] == np.linalg.norm(back.gravity.static_displacement, axis=1).max()
    assert seen["second_support"] == np.linalg.norm(
        back.second_support.runs.static_displacement, axis=1).max()
    assert 0 < seen["fixed"] < 3e-3 and 0 < seen["second_support"] < 3e-3


def test_a_failed_second_support_run_is_recorded_and_the_reference_kept(tmp_path, monkeypatch):
    """Its release failing: the force curves and the scene's gravity test are kept, the second
    support left out and recorded (``fe_failures.second_support``, its key in
    ``failed_experiment_keys``); the later stages run without it, a rerun takes the failure
    over instead of computing it again."""
    scene = dataclasses.replace(_scene(ROOT, END),
                                experiments=("indentation", "gravity_static", "second_support"))
    problem = _problem(scene)
    release = ex.gravity_dynamic

    def diverging(*args, section="fixed", **kwargs):
        if section == "second_support":
            error = ConvergenceError("second support dynamic: step 2 did not converge")
            error.reached = 0.005
            raise error
        return release(*args, section=section, **kwargs)
    monkeypatch.setattr(ex, "gravity_dynamic", diverging)
    out = tmp_path / "reference.h5"
    compute_reference(scene, problem, out_path=out, progress=False)
    back = read_reference(out)
    assert back.experiments == ("indentation", "gravity_static") and back.second_support is None
    assert back.fe_failures.gravity is None
    assert back.fe_failures.second_support == {
        "experiment": "second_support_dynamic", "reached": {"time_s": 0.005},
        "reason": "second support dynamic: step 2 did not converge"}
    key = run_keys(scene, problem)["second_support"]
    assert json.loads(back.meta["failed_experiment_keys"]) == {"second_support": key}
    with pytest.raises(DataFileError, match=r"no second_support results: the FE second-support "
                                            r"test failed \(second_support_dynamic: "):
        back.require("second_support")
    ctx = Context(scene, tmp_path, False, 1)
    assert scene_after_reference(ctx).experiments == ("indentation", "gravity_static")
    monkeypatch.setattr(ex, "gravity_dynamic", release)
    compute_reference(scene, problem, out_path=out, progress=False)
    again = read_reference(out)
    assert json.loads(again.meta["items_computed"]) == {}
    assert again.fe_failures.second_support == back.fe_failures.second_support
