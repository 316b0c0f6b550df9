"""reference.h5: round trip, atomic write, clear errors on corrupt or mismatched files."""
import dataclasses

import h5py
import numpy as np
import pytest

from forcecal.errors import DataFileError
from forcecal.h5io import (GravityResult, IndentationCurves, Reference, RelaxationCurves,
                           check_reference_settings, read_reference, write_reference)
from forcecal.scene import FESection, GravitySection, replace
from forcecal.schedules import record_times


def _fake_reference(problem, material, gravity: GravitySection | None = None):
    gravity = gravity or GravitySection(record_interval=0.5)  # 7 samples over 3 s
    times = record_times(gravity.duration, gravity.record_interval)
    n_p, n_v = len(problem.test_points), problem.mesh.n_vertices
    d = np.linspace(0.0005, 0.005, 10)
    t = np.linspace(0.05, 50.0, 12)
    rng = np.random.default_rng(0)
    return Reference(
        problem=problem, material=material,
        indentation=IndentationCurves(d, rng.normal(size=(n_p, 10, 3)), rng.normal(size=(n_p, 10))),
        relaxation=RelaxationCurves(t, np.minimum(t, 0.5) * 0.01, rng.normal(size=(n_p, 12, 3)),
                                    rng.normal(size=(n_p, 12))),
        gravity=GravityResult(rng.normal(size=(n_v, 3)), times,
                              rng.normal(size=(len(times), n_v, 3)),
                              dataclasses.replace(gravity, tracked_node=problem.tracked_node)),
        meta={"scene_fingerprint": "abc"}, fe=FESection())


def test_round_trip(tmp_path, liver_problem, liver_scene):
    ref = _fake_reference(liver_problem, liver_scene.material)
    path = tmp_path / "reference.h5"
    write_reference(path, ref)
    back = read_reference(path, expect_mesh=liver_problem.mesh.fingerprint())
    np.testing.assert_array_equal(back.problem.calibration, liver_problem.calibration)
    np.testing.assert_array_equal(back.problem.held_out, liver_problem.held_out)
    np.testing.assert_array_equal(back.indentation.force, ref.indentation.force)
    np.testing.assert_array_equal(back.gravity.displacement, ref.gravity.displacement)
    assert back.material == liver_scene.material
    assert back.fe == FESection() and back.indentation.indenter == "vertex"
    assert back.gravity.settings == ref.gravity.settings
    assert back.gravity.tracked_node == liver_problem.tracked_node
    assert back.meta["scene_fingerprint"] == "abc"
    assert not list(tmp_path.glob("*.tmp-*"))


def test_corrupt_truncated_and_mismatched_files(tmp_path, liver_problem, liver_scene):
    path = tmp_path / "reference.h5"
    write_reference(path, _fake_reference(liver_problem, liver_scene.material))
    with pytest.raises(DataFileError, match="different mesh"):
        read_reference(path, expect_mesh="0" * 64)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(DataFileError, match="not a readable HDF5 file"):
        read_reference(truncated)
    with h5py.File(path, "a") as fh:
        fh["relaxation/force_normal"][0, 0] = np.nan
    with pytest.raises(DataFileError, match="NaN"):
        read_reference(path)
    with h5py.File(path, "a") as fh:
        fh.attrs["kind"] = "something.else"
    with pytest.raises(DataFileError, match="is not a forcecal.reference file"):
        read_reference(path)
    with pytest.raises(DataFileError, match="does not exist"):
        read_reference(tmp_path / "missing.h5")


def test_refuses_to_write_nan_curves(tmp_path, liver_problem, liver_scene):
    ref = _fake_reference(liver_problem, liver_scene.material)
    ref.indentation.force[0, 0, 0] = np.nan
    with pytest.raises(DataFileError, match="NaN"):
        write_reference(tmp_path / "r.h5", ref)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("where, name", [
    ("material", "C10"), ("material", "prony_tau"), ("gravity", "tracked_node"),
    ("gravity", "acceleration"), ("gravity", "fe_dt"), ("fe", "element"),
    ("fe", "quadrature_degree"), ("indentation", "indenter"), ("mesh", "fingerprint"),
    ("test_points", "tracked_node")])
def test_a_missing_attribute_is_named(tmp_path, liver_problem, liver_scene, where, name):
    path = tmp_path / "reference.h5"
    write_reference(path, _fake_reference(liver_problem, liver_scene.material))
    with h5py.File(path, "a") as fh:
        del fh[where].attrs[name]
    with pytest.raises(DataFileError, match=rf"{path}:/{where} attribute '{name}' is missing"):
        read_reference(path)


def test_missing_groups_and_bad_settings_are_named(tmp_path, liver_problem, liver_scene):
    path = tmp_path / "reference.h5"
    write_reference(path, _fake_reference(liver_problem, liver_scene.material))
    with h5py.File(path, "a") as fh:
        fh["fe"].attrs["element"] = "Q9"
    with pytest.raises(DataFileError, match=rf"{path}:/fe: fe.element = 'Q9': must be one of"):
        read_reference(path)
    with h5py.File(path, "a") as fh:
        fh["fe"].attrs["element"] = "P2"
        fh["gravity"].attrs["record_interval"] = 0.25
    with pytest.raises(DataFileError, match=r"/gravity/time does not match its duration "
                       r"\(3.0 s\) and record_interval \(0.25 s\)"):
        read_reference(path)
    with h5py.File(path, "a") as fh:
        fh["gravity"].attrs["record_interval"] = 0.5
        fh["gravity"].attrs["tracked_node"] = liver_problem.tracked_node + 1
    with pytest.raises(DataFileError, match="/gravity tracked_node .* differs from /test_points"):
        read_reference(path)
    with h5py.File(path, "a") as fh:
        del fh["material"]
    with pytest.raises(DataFileError, match=rf"{path}:/material is missing"):
        read_reference(path)


@pytest.mark.parametrize("changes, message", [
    ({"gravity": {"acceleration": [0.0, 0.0, -1.62]}},
     r"gravity.acceleration = \(0.0, 0.0, -9.81\) \(scene: \(0.0, 0.0, -1.62\)\)"),
    ({"gravity": {"fe_dt": 0.001}}, r"gravity.fe_dt = 0.005 \(scene: 0.001\)"),
    ({"gravity": {"duration": 2.0}}, r"gravity.duration = 3.0 \(scene: 2.0\)"),
    ({"gravity": {"record_interval": 0.25}}, r"gravity.record_interval = 0.5 \(scene: 0.25\)"),
    ({"gravity": {"static_load_steps": 8}}, r"gravity.static_load_steps = 4 \(scene: 8\)"),
    ({"gravity": {"tracked_node": "max_x"}}, r"gravity.tracked_node = \d+ \(scene: \d+\)"),
    ({"fe": {"element": "TH"}}, r"fe.element = 'P2' \(scene: 'TH'\)"),
    ({"fe": {"quadrature_degree": 2, "newton_rtol": 1e-6}},
     r"fe.quadrature_degree = 4 \(scene: 2\); fe.newton_rtol = 1e-08 \(scene: 1e-06\); "
     "recompute the reference"),
])
def test_reference_settings_must_match_the_scene(liver_problem, liver_scene, changes, message):
    # the fake reference's [fe] is the default's (the liver scene loosens the Newton tolerance)
    scene = replace(liver_scene, gravity={"record_interval": 0.5},
                    fe={"newton_rtol": FESection().newton_rtol})
    ref = _fake_reference(liver_problem, liver_scene.material)
    check_reference_settings(ref, scene, "reference.h5")  # the scene it was computed for
    with pytest.raises(DataFileError, match="reference.h5 was computed with other settings "
                       "than the scene's: " + message):
        check_reference_settings(ref, replace(scene, **changes), "reference.h5")


def test_reference_indenter_and_missing_sections(liver_problem, liver_scene):
    ref = _fake_reference(liver_problem, liver_scene.material)
    other = dataclasses.replace(ref, indentation=dataclasses.replace(ref.indentation,
                                                                     indenter="sphere"))
    with pytest.raises(DataFileError, match=r"indentation.indenter = 'sphere' \(scene: "
                       r"'vertex'\)"):
        check_reference_settings(other, liver_scene, "reference.h5")
    # a reference not computed by the FE (synthetic: no [fe], no gravity) has nothing to compare
    check_reference_settings(dataclasses.replace(ref, fe=None, gravity=None), liver_scene, "r.h5")
