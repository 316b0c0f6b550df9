"""Bad input end to end: each case through a user-facing entry point, exit code 2, one clear line.

The unit-level refusals live next to their code (tests/test_mesh.py,
test_scene.py, test_h5io.py, test_calibration_inputs.py, test_particle_*.py,
test_fe_*.py); here the same situations go through ``python -m pipelines``
(and ``python -m calibration``), as a user meets them: exit code 2, an
``error: <message>`` line naming the problem, no traceback, nothing written.
Interrupted runs are covered where the checkpoints live
(test_calibration_fit.py::test_interrupted_calibration_resumes_to_the_same_result,
test_fe_reference.py::test_reference_file_contents_and_checkpoint_reuse and
::test_failed_item_names_itself_and_keeps_the_checkpoints).
"""
import re
import subprocess
import sys

import meshio
import numpy as np
import pytest

from calibration.cli import main as calibration_main
from forcecal.errors import StabilityError
from forcecal.mesh import box_mesh
from forcecal.problem import Problem
from forcecal.scene import load_scene, replace
from pipelines.cli import main as pipelines_main
from calibration.gravity_check import gravity_outcome
from particle.params import viscoelastic_params
from tests.conftest import ROOT, SCENES

BOX = box_mesh((2, 2, 2), (0.03, 0.03, 0.03))


def _write_mesh(path, vertices, cells):
    meshio.write(path, meshio.Mesh(vertices, cells))
    return path.name


def _inverted(path):
    tets = BOX.tets.copy()
    tets[3] = tets[3][[1, 0, 2, 3]]
    return _write_mesh(path, BOX.vertices, [("tetra", tets)])


def _duplicated(path):
    vertices = np.vstack([BOX.vertices, BOX.vertices[:1]])  # vertex 27 sits on vertex 0
    tets = BOX.tets.copy()
    tets[tets == 0] = len(vertices) - 1
    tets[0, tets[0] == len(vertices) - 1] = 0  # vertex 0 still used by tet 0
    return _write_mesh(path, vertices, [("tetra", tets)])


def _two_parts(path):
    vertices = np.vstack([BOX.vertices, BOX.vertices + [0.1, 0.0, 0.0]])
    return _write_mesh(path, vertices, [("tetra", np.vstack([BOX.tets, BOX.tets + 27]))])


MESHES = {
    "triangles only": (lambda p: _write_mesh(p, BOX.vertices, [("triangle", BOX.surface_faces)]),
                       r"no tetra cells \(found \['triangle'\]\)"),
    "empty file": (lambda p: (p.write_text(""), p.name)[1], r"meshio could not read it"),
    "inverted tet": (_inverted, r"1 inverted tets \(negative volume\), e.g. \[3\]"),
    "duplicate vertices": (_duplicated, r"duplicate vertices 0 and 27"),
    "disconnected parts": (_two_parts, r"2 disconnected parts \(vertex counts \[27, 27\]\)"),
}


def run_cli(capsys, tmp_path, scene_text: str, stage: str = "reference") -> str:
    """Run ``python -m pipelines <stage>`` in-process on a scene; return its stderr."""
    scene = tmp_path / "bad.toml"
    scene.write_text(scene_text)
    out = tmp_path / "out"
    code = pipelines_main([stage, "--scene", str(scene), "--out", str(out), "--ranks", "1",
                           "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err
    assert not any(out.glob("*.h5"))  # nothing half-done is left as a result
    return err


@pytest.mark.parametrize("case", MESHES)
def test_unusable_mesh_files_are_refused_by_the_pipeline(case, tmp_path, capsys):
    make, message = MESHES[case]
    name = make(tmp_path / ("mesh.msh" if case == "empty file" else "mesh.vtu"))
    err = run_cli(capsys, tmp_path, f'[mesh]\nsource = "{name}"\n')
    assert err.startswith("error: ") and name in err
    assert re.search(message, err), err


@pytest.mark.parametrize("text, message", [
    ('[mesh]\nsorce = "generate"\n', r"unknown key\(s\) \['sorce'\] in \[mesh\]; known keys"),
    ('[gravity]\nduration = "3 s"\n', r"gravity.duration = '3 s': expected number in s"),
    ('[material]\nkappa = 0.0\n', r"material.kappa = 0.0: must be > 0"),
    ('[mesh]\ncharacteristic_length = 0.04\n[test_points]\ncalibration = [0, 1]\n',
     r"calibration test point\(s\) \[0\] are fixed nodes"),
    ('[mesh]\ncharacteristic_length = 0.04\n[test_points]\ncalibration = "cover"\nn_calibration = 2\n',
     r"covering the 58 free surface vertices needs at least 9"),
])
def test_bad_scenes_are_refused_by_the_pipeline(text, message, tmp_path, capsys):
    err = run_cli(capsys, tmp_path, text)
    assert re.search(message, err), err


def test_interior_test_point_is_refused(tmp_path, capsys):
    """A vertex inside the organ has no surface normal to indent along."""
    from forcecal.liver_mesh import generate_liver
    mesh = generate_liver(0.04)
    inside = int(np.setdiff1d(np.arange(mesh.n_vertices), mesh.surface_vertices)[0])
    err = run_cli(capsys, tmp_path, f"[mesh]\ncharacteristic_length = 0.04\n[test_points]\n"
                  f"calibration = {[inside]}\nheld_out = []\n")
    assert f"[{inside}]" in err and "not on the surface" in err


def test_unwritable_output_folder_is_refused(tmp_path, capsys):
    (tmp_path / "a_file").write_text("")
    scene = tmp_path / "tiny.toml"
    scene.write_text((SCENES / "tiny.toml").read_text())
    code = pipelines_main(["reference", "--scene", str(scene), "--out",
                           str(tmp_path / "a_file" / "out"), "--ranks", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "error: cannot create" in err and "Not a directory" in err


def test_truncated_reference_is_refused_by_the_calibration_cli(tmp_path, capsys):
    reference = tmp_path / "reference.h5"
    reference.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))  # an HDF5 signature, then nothing
    code = calibration_main(["--scene", str(SCENES / "tiny.toml"), "--reference",
                             str(reference), "--out", str(tmp_path / "params.h5"),
                             "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and f"error: {reference} is not a readable HDF5 file" in err
    assert not (tmp_path / "params.h5").exists()


def test_corrupt_report_is_refused_by_results_table(tmp_path, capsys):
    report = tmp_path / "report.json"
    report.write_text('{"errors": ')
    assert pipelines_main(["results-table", str(report)]) == 2
    assert f"error: {report} is not a readable report.json" in capsys.readouterr().err


def test_time_step_above_the_limit_is_refused_by_the_gravity_stage():
    """``particle.dt`` above the model's stability limit: refused before a step, with the limit."""
    scene = replace(load_scene(SCENES / "tiny.toml"), particle={"dt": 1.0})
    fixed = np.nonzero(np.isclose(BOX.vertices[:, 2], 0.0))[0]
    problem = Problem(BOX, fixed, np.zeros(0, np.int64), np.zeros(0, np.int64), 26)
    params = viscoelastic_params(len(BOX.edges), 50.0)
    with pytest.raises(StabilityError, match=r"dt = 1 s is above the stability limit .* \(use "
                       r"particle.dt = 'auto'"):
        gravity_outcome(scene, problem, params, np.array([0.0, 0.01]), (-0.5, 0.5),
                        "calibrated")


def test_real_entry_point_prints_one_error_line_without_traceback(tmp_path):
    """The same through a real ``python -m pipelines`` process (what make and users run)."""
    name = _two_parts(tmp_path / "mesh.vtu")
    scene = tmp_path / "bad.toml"
    scene.write_text(f'[mesh]\nsource = "{name}"\n')
    r = subprocess.run([sys.executable, "-m", "pipelines", "demo", "--scene", str(scene),
                        "--out", str(tmp_path / "out")], capture_output=True, text=True,
                       cwd=ROOT)
    assert r.returncode == 2
    lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "2 disconnected parts" in lines[0]
    assert "Traceback" not in r.stderr
