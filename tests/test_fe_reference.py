"""End to end: the tiny scene's FE reference, serial vs mpirun -n 2, checkpoints, failures."""

import dataclasses
import io
import json
import os
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from forcecal.errors import ConvergenceError, DataFileError, SceneError  # noqa: E402
from forcecal.h5io import check_reference_settings, read_reference  # noqa: E402
from forcecal.problem import build_problem  # noqa: E402
from forcecal.scene import load_scene, replace  # noqa: E402
from reference_fe.run import (WorkItem, _Parts, _Progress, compute_item,  # noqa: E402
                              compute_reference, progress_stream, run_keys, work_items)

from tests.conftest import ROOT, SCENES  # noqa: E402

pytestmark = pytest.mark.fe

FAKE = 123.0  # planted checkpoint value: proves a finished item is reused, not recomputed


@pytest.fixture(scope="module")
def tiny_scene():
    return load_scene(SCENES / "tiny.toml")


@pytest.fixture(scope="module")
def serial(tiny_scene, tmp_path_factory):
    """Serial reference of the tiny scene, started from a half-filled checkpoint folder."""
    out = tmp_path_factory.mktemp("serial") / "reference.h5"
    parts = out.with_name("reference.h5.parts")
    parts.mkdir()
    key = run_keys(tiny_scene, build_problem(tiny_scene))["indentation"]
    steps = tiny_scene.indentation.steps
    np.savez(parts / "indentation-0000.npz", run_key=key, force=np.full((steps, 3), FAKE),
             seconds=0.0)
    np.savez(parts / "indentation-0001.npz", run_key="another scene",
             force=np.full((steps, 3), FAKE), seconds=0.0)
    (parts / "relaxation-0002.claim").touch()  # left by an interrupted run ...
    finished = subprocess.Popen(["true"])
    finished.wait()
    (parts / "OWNER").write_text(f"{socket.gethostname()} {finished.pid}")  # ... now gone
    ref = compute_reference(tiny_scene, out_path=out, progress=False)
    return out, ref


def test_reference_file_contents_and_checkpoint_reuse(serial, tiny_scene):
    out, ref = serial
    assert not out.with_name("reference.h5.parts").exists()  # removed once the file is written
    back = read_reference(out)
    assert back.fe == tiny_scene.fe and back.fe.element == "P2" and back.fe.quadrature_degree == 4
    assert back.gravity.settings.acceleration == tiny_scene.gravity.acceleration
    assert back.gravity.settings.fe_dt == tiny_scene.gravity.fe_dt
    check_reference_settings(back, tiny_scene, out)  # the settings it was computed with
    assert back.meta["n_ranks"] == 1 and back.meta["dolfinx_version"] == "0.5.2"
    assert back.meta["mesh_fingerprint"] == ref.problem.mesh.fingerprint()
    timings = json.loads(back.meta["timings_s"])
    assert set(timings) == {"mesh", "indentation", "relaxation", "gravity_static",
                            "gravity_dynamic", "body", "second_support", "floor", "total"}
    # not asked for: not computed
    assert timings["body"] == timings["second_support"] == timings["floor"] == 0.0
    assert back.body is None and back.second_support is None and back.floor is None
    np.testing.assert_array_equal(back.indentation.force, ref.indentation.force)
    # the matching part was reused, the stale one (other run key) and the stale claim were not
    assert np.all(ref.indentation.force[0] == FAKE)
    assert not np.any(ref.indentation.force[1:] == FAKE)
    n_points = len(ref.problem.test_points)
    assert ref.relaxation.force.shape == (n_points, 12, 3)
    g = ref.gravity
    assert g.displacement.shape == (61, ref.problem.mesh.n_vertices, 3)
    np.testing.assert_array_equal(g.displacement[0], 0.0)  # released from rest, undeformed
    np.testing.assert_allclose(g.time[-1], tiny_scene.gravity.duration)
    assert np.all(g.static_displacement[ref.problem.fixed] == 0.0)


def test_curves_are_physically_consistent(serial, tiny_scene):
    """Indentation pushes in and stiffens; relaxation peaks at the end of the ramp and, after a
    hold of 5 tau_max, ends within 1 % of the long-term (indentation) force at the same depth
    (remaining overstress ~ sum g_i exp(-5 tau_max/tau_i) / g_inf ~ 0.4 %)."""
    _, ref = serial
    f_ind = ref.indentation.force_normal[1:]  # point 0 holds the planted checkpoint
    assert np.all(f_ind > 0) and np.all(np.diff(f_ind, axis=1) > 0)
    f_rel = ref.relaxation.force_normal[1:]
    ramp = tiny_scene.relaxation.ramp_steps
    assert np.all(np.argmax(f_rel, axis=1) == ramp - 1)
    np.testing.assert_allclose(f_rel[:, -1], f_ind[:, -1], rtol=0.01)
    assert np.all(f_rel[:, -1] > f_ind[:, -1])  # approaches from above
    # the organ sags: every free vertex moves down, on average
    assert np.mean(ref.gravity.static_displacement[ref.problem.free, 2]) < 0


@pytest.mark.mpi
@pytest.mark.parametrize("ranks", [2, 4])
def test_mpirun_ranks_give_the_serial_curves_bit_for_bit(serial, tmp_path, ranks):
    """2 ranks, and 4 (oversubscribed on a 2-core machine), against the serial run (1 rank, in
    process): every item runs the same serial code on MPI.COMM_SELF from a fresh tangent
    (FEModel.forget_tangent), whichever rank takes it and whatever it computed before, so
    the curves are identical, not merely equal to the Newton tolerance."""
    mpirun = shutil.which("mpirun")
    if mpirun is None:
        pytest.skip("mpirun not installed")
    out = tmp_path / "reference.h5"
    env = dict(os.environ)
    for k in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM",
              "OMPI_MCA_rmaps_base_oversubscribe"):
        env.setdefault(k, "1")
    cmd = [mpirun, "-n", str(ranks), sys.executable, "-m", "reference_fe", "--scene",
           str(SCENES / "tiny.toml"), "--out", str(out), "--no-progress"]
    run = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=600,
                         stdin=subprocess.DEVNULL)
    assert run.returncode == 0, run.stderr[-3000:]
    par, (_, ser) = read_reference(out), serial
    assert par.meta["n_ranks"] == ranks
    assert len(json.loads(par.meta["items_computed"])) == 4  # every kind computed here
    np.testing.assert_array_equal(par.indentation.force[1:], ser.indentation.force[1:])
    np.testing.assert_array_equal(par.relaxation.force, ser.relaxation.force)
    np.testing.assert_array_equal(par.gravity.static_displacement,
                                  ser.gravity.static_displacement)
    np.testing.assert_array_equal(par.gravity.displacement, ser.gravity.displacement)


def test_failing_everywhere_names_the_first_failure_and_keeps_the_checkpoints(tiny_scene,
                                                                               tmp_path):
    """Every step fails: the static sag (run first) is recorded, the release never starts,
    and the run stops once more than a quarter of the points failed (5 of 17)."""
    scene = replace(tiny_scene, fe={"newton_max_it": 1, "max_step_cuts": 0})
    out = tmp_path / "reference.h5"
    with pytest.raises(ConvergenceError, match=r"FE reference failed: 5 FE test point runs "
                       r"failed, more than a quarter of the 17 test points: .* first failure: "
                       r"vertex \d+ \(relaxation\): .* step 1/12 .* did not converge"):
        compute_reference(scene, out_path=out, progress=False)
    assert not out.exists()
    parts = tmp_path / "reference.h5.parts"
    assert (parts / "FAILED").is_file() and (parts / "gravity_static.failed").is_file()
    assert not (parts / "gravity_dynamic.failed").exists()


def test_refuses_a_folder_another_live_process_is_filling(tiny_scene, tmp_path):
    parts = tmp_path / "reference.h5.parts"
    parts.mkdir()
    (parts / "OWNER").write_text(f"{socket.gethostname()} {os.getppid()}")  # alive
    with pytest.raises(DataFileError, match=rf"in use by process {os.getppid()}"):
        compute_reference(tiny_scene, out_path=tmp_path / "reference.h5", progress=False)


def test_cli_reports_bad_input_without_a_traceback(tmp_path, capsys):
    from reference_fe.__main__ import main

    assert main(["--scene", str(tmp_path / "missing.toml"), "--out",
                 str(tmp_path / "r.h5"), "--no-progress"]) == 2
    assert "error: scene file" in capsys.readouterr().err


def test_an_indenter_without_an_fe_experiment_is_refused_where_items_are_computed(tiny_scene,
                                                                                  tmp_path):
    """The scene only accepts 'vertex'; a scene built around that check (or a future
    indenter without FE code) is refused by the work-item code before any solve."""
    scene = dataclasses.replace(tiny_scene, indentation=dataclasses.replace(
        tiny_scene.indentation, indenter="sphere"))
    problem = build_problem(tiny_scene)
    for kind in ("indentation", "relaxation"):
        with pytest.raises(SceneError, match="indentation.indenter = 'sphere': the FE "
                           "reference has no experiment for it"):
            compute_item(None, scene, problem, WorkItem(kind, 0, 1.0))
    with pytest.raises(SceneError, match="'sphere'"):
        compute_reference(scene, problem, out_path=tmp_path / "reference.h5", progress=False)
    assert not (tmp_path / "reference.h5.parts").exists()


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


@pytest.mark.parametrize("stderr_tty, stdout_tty, forced, expected", [
    (True, True, None, "stderr"), (False, True, None, "stdout"),  # mpirun: stdout is a pty
    (False, False, None, None), (False, False, "1", "stderr"), (False, False, "0", None)])
def test_progress_bar_goes_to_a_terminal_or_where_forced(monkeypatch, stderr_tty, stdout_tty,
                                                         forced, expected):
    streams = {"stderr": _Stream(stderr_tty), "stdout": _Stream(stdout_tty)}
    monkeypatch.setattr(sys, "stderr", streams["stderr"])
    monkeypatch.setattr(sys, "stdout", streams["stdout"])
    if forced is None:
        monkeypatch.delenv("FORCECAL_PROGRESS", raising=False)
    else:
        monkeypatch.setenv("FORCECAL_PROGRESS", forced)
    assert progress_stream(True, 0) is (streams[expected] if expected else None)
    assert progress_stream(False, 0) is None  # --no-progress
    assert progress_stream(True, 1) is None  # rank 0 only


def test_progress_bar_ticks_once_per_finished_item_with_its_name(tiny_scene, tmp_path):
    """Items finished by any rank (parts appearing in the folder) tick the bar; a part left
    from another run (other run key) counts only once it is recomputed."""
    items = work_items(tiny_scene, 2)  # 6 items
    parts = _Parts(tmp_path / "reference.h5", "key")
    parts.folder.mkdir()
    parts.save(items[0], {"force": np.zeros(1)})  # finished before: initial count
    _Parts(tmp_path / "reference.h5", "another run").save(items[1], {"force": np.zeros(1)})
    out = _Stream(True)
    bar = _Progress(parts, items, out)
    parts.save(items[2], {"force": np.zeros(1)})
    bar.poll()
    parts.save(items[1], {"force": np.zeros(1)})
    bar.close()
    text = out.getvalue()
    assert "1/6" in text and "3/6" in text and "4/6" not in text
    assert items[2].name in text and items[1].name in text
    assert items[3].name not in text
