"""reference.h5: round trip, atomic write, clear errors on corrupt or mismatched files."""
import h5py
import numpy as np
import pytest

from forcecal.errors import DataFileError
from forcecal.h5io import (GravityResult, IndentationCurves, Reference, RelaxationCurves,
                           read_reference, write_reference)


def _fake_reference(problem, material):
    n_p, n_v = len(problem.test_points), problem.mesh.n_vertices
    d = np.linspace(0.0005, 0.005, 10)
    t = np.linspace(0.05, 50.0, 12)
    rng = np.random.default_rng(0)
    return Reference(
        problem=problem, material=material,
        indentation=IndentationCurves(d, rng.normal(size=(n_p, 10, 3)), rng.normal(size=(n_p, 10))),
        relaxation=RelaxationCurves(t, np.minimum(t, 0.5) * 0.01, rng.normal(size=(n_p, 12, 3)),
                                    rng.normal(size=(n_p, 12))),
        gravity=GravityResult(rng.normal(size=(n_v, 3)), np.linspace(0, 3, 7),
                              rng.normal(size=(7, n_v, 3)), problem.tracked_node),
        meta={"scene_fingerprint": "abc", "element": "P2"})


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
    assert back.meta["element"] == "P2"
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
