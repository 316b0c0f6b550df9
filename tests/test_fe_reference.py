"""End to end: the tiny scene's FE reference, serial vs mpirun -n 2, checkpoints, failures."""

import json
import os
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from forcecal.errors import ConvergenceError, DataFileError  # noqa: E402
from forcecal.h5io import check_reference_settings, read_reference  # noqa: E402
from forcecal.problem import build_problem  # noqa: E402
from forcecal.scene import load_scene, replace  # noqa: E402
from reference_fe.run import compute_reference, run_key  # noqa: E402

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
    key = run_key(tiny_scene, build_problem(tiny_scene))
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
                            "gravity_dynamic", "total"}
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
def test_mpirun_two_ranks_equals_serial(serial, tmp_path):
    mpirun = shutil.which("mpirun")
    if mpirun is None:
        pytest.skip("mpirun not installed")
    out = tmp_path / "reference.h5"
    env = dict(os.environ)
    for k in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM",
              "OMPI_MCA_rmaps_base_oversubscribe"):
        env.setdefault(k, "1")
    cmd = [mpirun, "-n", "2", sys.executable, "-m", "reference_fe", "--scene",
           str(SCENES / "tiny.toml"), "--out", str(out), "--no-progress"]
    run = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=600,
                         stdin=subprocess.DEVNULL)
    assert run.returncode == 0, run.stderr[-3000:]
    par, (_, ser) = read_reference(out), serial
    assert par.meta["n_ranks"] == 2
    # each item runs the same serial code on MPI.COMM_SELF whichever rank takes it, so the
    # results agree to round-off; the bound is the Newton tolerance (1e-10 N + 1e-8 |f|)
    close = dict(rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(par.indentation.force[1:], ser.indentation.force[1:], **close)
    np.testing.assert_allclose(par.relaxation.force, ser.relaxation.force, **close)
    np.testing.assert_allclose(par.gravity.static_displacement, ser.gravity.static_displacement,
                               **close)
    np.testing.assert_allclose(par.gravity.displacement, ser.gravity.displacement, **close)


def test_failed_item_names_itself_and_keeps_the_checkpoints(tiny_scene, tmp_path):
    scene = replace(tiny_scene, fe={"newton_max_it": 1, "max_step_cuts": 0})
    out = tmp_path / "reference.h5"
    with pytest.raises(ConvergenceError, match=r"gravity_dynamic: gravity dynamic: step 1/60"):
        compute_reference(scene, out_path=out, progress=False)
    assert not out.exists()
    assert (tmp_path / "reference.h5.parts" / "FAILED").is_file()


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
