"""The FE reference when some of its runs fail (provoked by tests/fe_fail_hook.py): a failed
test point is replaced under a rule and dropped from an explicit list, more than a quarter
failing stops the run with what they share, a failed gravity test leaves the gravity out and
keeps the force curves, a recorded failure is resumed, and mpirun -n 2 decides the same."""

import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from forcecal.errors import ConvergenceError  # noqa: E402
from forcecal.fe_failures import apply_fe_failures  # noqa: E402
from forcecal.h5io import read_reference  # noqa: E402
from forcecal.problem import build_problem, replacement_point  # noqa: E402
from forcecal.scene import load_scene, replace  # noqa: E402
from reference_fe.run import WorkItem, _Parts, compute_reference, run_keys  # noqa: E402

from tests import fe_fail_hook  # noqa: E402
from tests.conftest import ROOT, SCENES  # noqa: E402

pytestmark = pytest.mark.fe

FORCES = ("indentation", "relaxation")


@pytest.fixture(scope="module")
def tiny():
    """The tiny scene without its gravity runs (the force curves are what is tested)."""
    scene = dataclasses.replace(load_scene(SCENES / "tiny.toml"), experiments=FORCES)
    return scene, build_problem(scene)


@pytest.fixture(scope="module")
def plain(tiny, tmp_path_factory):
    """The force curves with nothing failing."""
    scene, _ = tiny
    return compute_reference(scene, out_path=tmp_path_factory.mktemp("plain") / "r.h5",
                             progress=False)


def _run(scene, out, spec, monkeypatch):
    monkeypatch.setattr("reference_fe.run.compute_item", fe_fail_hook.failing(spec))
    return compute_reference(scene, out_path=out, progress=False)


def test_a_failed_auto_point_is_replaced_by_the_next_candidate(tiny, plain, tmp_path,
                                                               monkeypatch):
    scene, problem = tiny
    slot = len(problem.calibration) + 2  # a held-out point ("auto")
    vertex = int(problem.test_points[slot])
    ref = _run(scene, tmp_path / "r.h5", f"relaxation:{vertex}", monkeypatch)
    back = read_reference(tmp_path / "r.h5")
    by = replacement_point(scene, problem, slot, {vertex})
    replaced = back.fe_failures.replaced
    assert [(r["point"], r["by"], r["slot"], r["experiment"], r["role"]) for r in replaced] \
        == [(vertex, by, slot, "relaxation", "held_out")]
    assert "test hook: the relaxation of vertex" in replaced[0]["reason"]
    assert replaced[0]["reached"] == {"time_s": 0.5}
    assert not back.fe_failures.dropped and back.fe_failures.gravity is None
    points = back.problem.test_points
    assert points[slot] == by and np.array_equal(np.delete(points, slot),
                                                 np.delete(problem.test_points, slot))
    # the other points' curves are those of a run where nothing failed; the replacement's
    # are its own FE curves (a point load that pushes back and stiffens)
    keep = np.arange(len(points)) != slot
    for e in FORCES:
        np.testing.assert_allclose(getattr(ref, e).force[keep], getattr(plain, e).force[keep],
                                   rtol=1e-7, atol=1e-9)
    f = ref.indentation.force_normal[slot]
    assert np.all(f > 0) and np.all(np.diff(f) > 0)
    assert np.argmax(ref.relaxation.force_normal[slot]) == scene.relaxation.ramp_steps - 1
    # the calibration stage accepts it: the scene's points with the recorded replacement
    np.testing.assert_array_equal(apply_fe_failures(problem, back.fe_failures).test_points,
                                  points)
    # relaxation items run first (the larger): the failed point's indentation was never run
    assert json.loads(back.meta["items_computed"]) == {"indentation": 17, "relaxation": 17}


def test_a_failed_point_of_an_explicit_list_is_dropped(tiny, plain, tmp_path, monkeypatch):
    scene, problem = tiny
    listed = replace(scene, test_points={"calibration": problem.calibration.tolist(),
                                         "held_out": problem.held_out.tolist()})
    vertex = int(problem.calibration[4])
    _run(listed, tmp_path / "r.h5", f"indentation:{vertex}", monkeypatch)
    back = read_reference(tmp_path / "r.h5")
    dropped = back.fe_failures.dropped
    assert [(d["point"], d["slot"], d["experiment"], d["role"]) for d in dropped] \
        == [(vertex, 4, "indentation", "calibration")]
    assert not back.fe_failures.replaced
    np.testing.assert_array_equal(back.problem.calibration, np.delete(problem.calibration, 4))
    for e in FORCES:
        np.testing.assert_allclose(getattr(back, e).force, np.delete(getattr(plain, e).force, 4,
                                                                     axis=0),
                                   rtol=1e-7, atol=1e-9)


def test_more_than_a_quarter_failing_stops_the_run_saying_what_they_share(tiny, tmp_path,
                                                                          monkeypatch):
    scene, problem = tiny
    spec = ",".join(f"relaxation:{v}" for v in problem.test_points[:5])  # 5 of 17
    with pytest.raises(ConvergenceError, match=r"FE reference failed: 5 FE test point runs "
                       r"failed, more than a quarter of the 17 test points: the FE set-up does "
                       r"not suit this scene; what the failures share: 5 in relaxation"):
        _run(scene, tmp_path / "r.h5", spec, monkeypatch)
    assert not (tmp_path / "r.h5").exists()
    assert (tmp_path / "r.h5.parts" / "FAILED").is_file()


def _slab_at_its_edge(directory):
    """A 80 x 80 x 40 mm slab (5 x 20 x 20 mm cells, base clamped) indented by a 16 mm punch
    at 9 vertices along its top edge y = 0 and 8 on its top face: at the edge the punch's
    face leans 45 degrees, the footprint reaches the nodes 20 mm across the edge (on the top
    and down the side, 14.1 mm off the face), beyond the 2 mm depth; radii from 5 to 14.1 mm
    keep only the edge's nodes (tests/test_punch.py). Returns the scene and the edge points."""
    from calibration.synthetic import box_scene
    from forcecal.mesh import box_mesh
    x = box_mesh((16, 4, 2), (0.08, 0.08, 0.04)).vertices

    def at(px, py):
        return int(np.argmin(np.linalg.norm(x - [px, py, 0.04], axis=1)))
    edge = [at(0.005 * k, 0.0) for k in range(3, 12)]
    face = [at(0.005 * k, 0.04) for k in range(3, 11)]
    scene = dataclasses.replace(box_scene(
        directory, cells=(16, 4, 2), size=(0.08, 0.08, 0.04),
        test_points={"calibration": edge, "held_out": face},
        indentation={"indenter": "punch", "radius": 0.016, "depth": 0.002},
        relaxation={"depth": 0.002}), experiments=FORCES)
    return scene, edge


def test_more_than_a_quarter_failing_names_the_punch_footprints_beyond_its_reach(
        tmp_path, monkeypatch):
    """Five of the slab's edge points failing stop the run with what their footprints hold
    beyond the punch's reach and a radius that keeps only the edge's nodes, 10 mm
    (:func:`forcecal.fe_failures.punch_reach`)."""
    scene, edge = _slab_at_its_edge(tmp_path)
    spec = ",".join(f"relaxation:{v}" for v in edge[:5])
    with pytest.raises(ConvergenceError, match=(
            r"what the failures share: 5 in relaxation; .*the punch footprints of 5 of the 5 "
            r"failed points hold particles beyond the punch's reach, up to 14.1 mm from its "
            r"face against the 2 mm depth \(a flat punch never touches them, its footprint "
            r"holds them as if glued\): indentation.radius = 0.01 m keeps them within reach; "
            r"first failure: ")):
        _run(scene, tmp_path / "r.h5", spec, monkeypatch)


def test_footprints_beyond_the_punch_reach_at_most_points_are_warned_of_before_the_fe(
        tmp_path, caplog):
    """9 of the slab's 17 footprints hold particles beyond the punch's reach: fewer than 3/4,
    no warning; with the 8 held-out points on the opposite top edge (y = 80 mm) instead of
    its face, every one: warned of, with the radius, before any FE work."""
    import logging

    from reference_fe.run import check_indenter
    scene, edge = _slab_at_its_edge(tmp_path)
    problem = build_problem(scene)
    x = problem.mesh.vertices
    opposite = tuple(int(np.argmin(np.linalg.norm(x - [0.005 * k, 0.08, 0.04], axis=1)))
                     for k in range(3, 11))
    with caplog.at_level(logging.WARNING, logger="reference_fe.run"):
        check_indenter(scene, problem)
        assert not caplog.records
        along = dataclasses.replace(scene, test_points=dataclasses.replace(
            scene.test_points, held_out=opposite))
        check_indenter(along, build_problem(along))
    assert [r.getMessage() for r in caplog.records] == [
        "the punch footprints of 17 of the 17 test points hold particles beyond the punch's "
        "reach, up to 14.1 mm from its face against the 2 mm depth (a flat punch never "
        "touches them, its footprint holds them as if glued): indentation.radius = 0.01 m "
        "keeps them within reach; the FE punch runs there may not converge (docs/punch.md)"]


def test_a_failed_gravity_test_the_preflight_expected_says_so(tmp_path, monkeypatch):
    """The preflight saying the support does not hold the body (its linear sag beyond a
    quarter of the body): the gravity failure's reason carries it, and a rerun that takes the
    failure over does not add it twice."""
    import reference_fe.run as run
    preflight = run.run_preflight

    def soft(scene, mesh, fixed):
        pf = preflight(scene, mesh, fixed)
        return {**pf, "support": {**pf["support"], "holds": False,
                                  "linear_sag_m": 0.5 * pf["support"]["body_size_m"]}}
    monkeypatch.setattr(run, "run_preflight", soft)
    scene = load_scene(SCENES / "tiny.toml")
    out = tmp_path / "reference.h5"
    _run(scene, out, "gravity_static:", monkeypatch)
    expected = (r"test hook: the gravity_static of vertex -1 diverges; expected by the mesh "
                r"preflight: the support does not hold the body under its weight \(linear sag "
                r"under full gravity [0-9.]+ mm, 0.5 x the body's size [0-9.]+ mm\)")
    assert re.fullmatch(expected, read_reference(out).fe_failures.gravity["reason"])
    _run(scene, out, "", monkeypatch)
    assert re.fullmatch(expected, read_reference(out).fe_failures.gravity["reason"])


def test_a_recorded_failure_is_resumed_not_recomputed(tiny, tmp_path, monkeypatch):
    """A run interrupted after an item failed: the rerun takes the failure from the
    checkpoint folder and replaces the point (the hook fails nothing this time)."""
    scene, problem = tiny
    out = tmp_path / "r.h5"
    parts = _Parts(out, run_keys(scene, problem))
    parts.folder.mkdir()
    vertex = int(problem.test_points[3])
    parts.save_failure(WorkItem("indentation", 3, 1.0), ConvergenceError("diverged"), 1.0,
                       vertex)
    _run(scene, out, "", monkeypatch)
    back = read_reference(out)
    assert [(r["point"], r["slot"]) for r in back.fe_failures.replaced] == [(vertex, 3)]
    assert back.fe_failures.replaced[0]["by"] == replacement_point(scene, problem, 3, {vertex})


def test_a_failed_gravity_test_leaves_the_gravity_out_and_keeps_the_force_curves(tmp_path,
                                                                                 monkeypatch):
    """The static sag runs first; when it fails the release is not run, neither gravity
    experiment is stored, and the reason is recorded; the stages after the reference then
    run the scene as one without gravity."""
    from pipelines.runners.common import Context
    from pipelines.runners.reference import adopt_reference, scene_after_reference

    scene = load_scene(SCENES / "tiny.toml")
    out = tmp_path / "reference.h5"
    ref = _run(scene, out, "gravity_static:", monkeypatch)
    back = read_reference(out)
    assert back.experiments == FORCES and ref.gravity is None
    assert back.fe_failures.gravity == {"experiment": "gravity_static",
                                        "reason": "test hook: the gravity_static of vertex -1 "
                                                  "diverges",
                                        "reached": {"load_factor": 0.5}}
    assert "gravity_dynamic" not in json.loads(back.meta["items_computed"])  # never started
    assert json.loads(back.meta["mesh_preflight"])["support"]["holds"]  # not expected to fail
    assert back.indentation.force.shape[0] == 17 and back.relaxation is not None
    ctx = Context(scene, tmp_path, False, 1)
    assert scene_after_reference(ctx).experiments == FORCES
    assert adopt_reference(ctx, back.problem.mesh.fingerprint())  # the failure has its key
    # a rerun takes the failure over instead of computing the sag again
    monkeypatch.setattr("reference_fe.run.compute_item", fe_fail_hook.failing("gravity_static:"))
    out.rename(tmp_path / "kept.h5")
    shutil.copy(tmp_path / "kept.h5", out)
    again = compute_reference(replace(scene, relaxation={"hold_steps": 6}), out_path=out,
                              progress=False)
    meta = read_reference(out).meta
    assert json.loads(meta["items_computed"]) == {"relaxation": 17}
    assert again.gravity is None and read_reference(out).fe_failures.gravity is not None


@pytest.mark.mpi
def test_mpirun_two_ranks_replace_the_same_point(tiny, tmp_path):
    """Under mpirun -n 2 (the pipeline's default) the ranks agree on the replacement."""
    mpirun = shutil.which("mpirun")
    if mpirun is None:
        pytest.skip("mpirun not installed")
    scene, problem = tiny
    toml = tmp_path / "tiny.toml"
    toml.write_text('experiments = ["indentation", "relaxation"]\n'
                    + (SCENES / "tiny.toml").read_text())
    slot = 5
    vertex = int(problem.test_points[slot])
    env = dict(os.environ, FORCECAL_TEST_FAIL=f"indentation:{vertex}")
    for k in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM",
              "OMPI_MCA_rmaps_base_oversubscribe"):
        env.setdefault(k, "1")
    cmd = [mpirun, "-n", "2", sys.executable, str(ROOT / "tests" / "fe_fail_hook.py"),
           "--scene", str(toml), "--out", str(tmp_path / "r.h5"), "--no-progress"]
    run = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=600,
                         stdin=subprocess.DEVNULL)
    assert run.returncode == 0, run.stderr[-3000:]
    back = read_reference(tmp_path / "r.h5")
    assert back.meta["n_ranks"] == 2
    assert [(r["point"], r["by"]) for r in back.fe_failures.replaced] == [
        (vertex, replacement_point(scene, problem, slot, {vertex}))]
    assert "replaced by vertex" in run.stderr and run.stderr.count("replaced by vertex") == 1
