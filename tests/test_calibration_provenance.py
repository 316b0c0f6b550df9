"""What keys the calibration checkpoint (the fit's inputs, its code) and the provenance
recorded in params.h5."""
import re

import pytest

from calibration.checkpoint import Checkpoint
from calibration.provenance import code_fingerprint, fit_inputs, git_commit, versions
from forcecal.provenance import CodeDependencies
from calibration.synthetic import box_scene
from forcecal.scene import replace
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return box_scene(tmp_path_factory.mktemp("infra"), test_points={"n_calibration": 4,
                                                                    "n_held_out": 8})


@pytest.fixture
def reference(tmp_path):
    path = tmp_path / "reference.h5"
    path.write_bytes(b"stands in for a reference file: only its bytes are fingerprinted")
    return path


def _changed(a: dict, b: dict) -> list[str]:
    return sorted(k for k in a if a[k] != b[k])


def test_fit_inputs_cover_what_the_fit_reads(scene, reference):
    base = fit_inputs(scene, reference)
    assert {"reference", "forcecal", "code", "scene [calibration]", "scene [mesh]",
            "scene [material]"} <= set(base)
    for sections, changed in (
            ({"calibration": {"xatol": 0.01}}, ["scene [calibration]"]),
            ({"material": {"C10": 2500.0}}, ["scene [material]"]),
            ({"relaxation": {"ramp_time": 0.4}}, ["scene [relaxation]"]),
            ({"calibration": {"workers": 1}}, []),   # how fast, not what
            ({"particle": {"dt_safety": 0.5}}, []),  # the fit never reads [particle]
            ({"gravity": {"duration": 1.0}}, [])):
        assert _changed(base, fit_inputs(replace(scene, **sections), reference)) == changed
    reference.write_bytes(b"another reference")
    assert _changed(base, fit_inputs(scene, reference)) == ["reference"]


def test_code_fingerprint_follows_the_code_not_its_comments(tmp_path, monkeypatch):
    package = tmp_path / "fakepkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "mod.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    fake = CodeDependencies(runs=("fakepkg",), reads=("fakepkg",))
    before = code_fingerprint(fake)
    assert code_fingerprint(fake) == before
    # a comment edit keeps a checkpoint, as it keeps a stage cache record
    (package / "sub" / "mod.py").write_text('"""A module."""\n# why X is 1\nX = (1)\n')
    assert code_fingerprint(fake) == before
    (package / "sub" / "mod.py").write_text("X = 2\n")
    assert code_fingerprint(fake) != before
    assert re.fullmatch(r"[0-9a-f]{64}", code_fingerprint())


def test_a_changed_input_discards_the_checkpoint_and_says_what(tmp_path, caplog):
    path = tmp_path / "cp.json"
    inputs = {"reference": "r", "scene [calibration]": "c", "code": "k", "forcecal": "0.1.0"}
    Checkpoint(path, inputs).put("global_static", {"x": [1.0]})
    assert Checkpoint(path, dict(inputs)).get("global_static") == {"x": [1.0]}
    assert not caplog.records
    stale = Checkpoint(path, {**inputs, "code": "k2", "scene [calibration]": "c2"})
    assert stale.get("global_static") is None
    assert [r.getMessage() for r in caplog.records] == [
        f"discarding checkpoint {path}: code, scene [calibration] changed since it was written"]
    caplog.clear()
    path.write_text('{"fingerprint": "abc", "stages": {"global_static": {}}}')  # older format
    assert Checkpoint(path, inputs).get("global_static") is None
    assert "records no inputs" in caplog.text


def test_versions_name_the_libraries_and_the_commit(tmp_path):
    v = versions()
    for name in ("python", "numpy", "scipy", "numba", "h5py", "mpi4py", "forcecal",
                 "git_commit"):
        assert name in v, name
    assert v["h5py"]
    if (ROOT / ".git").exists():
        assert re.fullmatch(r"[0-9a-f]{40}(\+dirty)?", v["git_commit"])
    assert git_commit(tmp_path) is None  # not a checkout
