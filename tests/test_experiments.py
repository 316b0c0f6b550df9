"""The scene's ``experiments`` list: validated at load, honoured by every stage and its cache.

End to end on the tiny scene (FE in-process, small calibration budgets): an
indentation-only scene computes no relaxation or gravity; adding
``gravity_static`` computes that one FE item and reruns no calibration;
removing it again recomputes nothing upstream.
"""
import dataclasses
import json

import h5py
import numpy as np
import pytest

from calibration import read_params
from calibration.core import ARMS_NOT_CALIBRATED
from forcecal.errors import DataFileError, SceneError
from forcecal.h5io import read_reference, reference_digest, write_reference
from forcecal.problem import build_problem
from forcecal.scene import DEFAULT_EXPERIMENTS, EXPERIMENTS, load_scene, replace, scene_from_dict
from pipelines.report import ERROR_KEYS, read_report
from pipelines.stages import run_pipeline
from tests.conftest import SCENES
from tests.test_pipeline_e2e import ran, write_scene


def test_default_is_every_experiment_but_the_opt_in_ones_and_the_order_does_not_matter():
    assert scene_from_dict({}).experiments == DEFAULT_EXPERIMENTS
    # asked for explicitly (the second support: one more FE sag and release; the floor: the
    # gravity test with two more elements)
    assert set(EXPERIMENTS) - set(DEFAULT_EXPERIMENTS) == {"body", "second_support", "floor"}
    scene = scene_from_dict({"experiments": ["gravity_static", "indentation"]})
    assert scene.experiments == ("indentation", "gravity_static")
    assert replace(scene, experiments=["indentation"]).experiments == ("indentation",)


@pytest.mark.parametrize("value, message", [
    ([], "experiments is empty"),
    (["indentation", "creep"], r"unknown name\(s\) \['creep'\]"),
    (["indentation", "indentation"], r"lists \['indentation'\] more than once"),
    ("indentation", "expected a list of strings"),
    (["relaxation"], "'relaxation' needs 'indentation'"),
    (["gravity_static"], "'gravity_static' needs 'indentation'"),
    (["indentation", "gravity_dynamic"],
     r"'gravity_dynamic' needs 'relaxation' \(the release is damped only by the Maxwell arms"),
    (["body"], "'body' needs 'indentation'"),
    (["indentation", "relaxation", "gravity_static", "second_support"],
     r"'second_support' needs 'gravity_dynamic' \(it is the gravity test with another support"),
])
def test_impossible_lists_are_refused_at_load_with_the_reason(value, message):
    with pytest.raises(SceneError, match=message):
        scene_from_dict({"experiments": value})


def test_a_partial_reference_round_trips_and_keys_each_experiment_on_its_own_content(
        tmp_path, liver_problem, liver_scene):
    from tests.test_h5io import _fake_reference
    full = _fake_reference(liver_problem, liver_scene.material)
    write_reference(tmp_path / "full.h5", full)
    static_only = dataclasses.replace(full.gravity, time=None, displacement=None)
    part = dataclasses.replace(full, relaxation=None, gravity=static_only)
    write_reference(tmp_path / "part.h5", part)
    back = read_reference(tmp_path / "part.h5")
    assert back.experiments == ("indentation", "gravity_static") and back.relaxation is None
    assert back.gravity.time is None
    np.testing.assert_array_equal(back.gravity.static_displacement,
                                  full.gravity.static_displacement)
    with pytest.raises(DataFileError, match="has no relaxation results"):
        back.require("relaxation", "part.h5")
    assert read_reference(tmp_path / "full.h5").experiments == DEFAULT_EXPERIMENTS
    # a stage reading some experiments keys on their content, not on the file's bytes
    for experiments in (("indentation",), ("indentation", "gravity_static"), ("gravity_static",)):
        assert (reference_digest(tmp_path / "part.h5", experiments)
                == reference_digest(tmp_path / "full.h5", experiments))
    assert (reference_digest(tmp_path / "full.h5", ("indentation", "relaxation"))
            != reference_digest(tmp_path / "full.h5", ("indentation",)))
    with pytest.raises(DataFileError, match=r"has no \['relaxation'\] results"):
        reference_digest(tmp_path / "part.h5", ("indentation", "relaxation"))
    bent = dataclasses.replace(part, indentation=dataclasses.replace(
        part.indentation, force_normal=part.indentation.force_normal * (1 + 1e-12)))
    write_reference(tmp_path / "bent.h5", bent)
    assert (reference_digest(tmp_path / "bent.h5", ("gravity_static",))
            == reference_digest(tmp_path / "part.h5", ("gravity_static",)))
    assert (reference_digest(tmp_path / "bent.h5", ("indentation",))
            != reference_digest(tmp_path / "part.h5", ("indentation",)))


def test_fe_keys_follow_each_experiments_own_sections(liver_scene):
    from reference_fe.keys import experiment_keys
    base = experiment_keys(liver_scene, "mesh")
    assert experiment_keys(replace(liver_scene, experiments=["indentation"]), "mesh") == base

    def changed(**sections):
        keys = experiment_keys(replace(liver_scene, **sections), "mesh")
        return sorted(e for e in EXPERIMENTS if keys[e] != base[e])
    assert changed(gravity={"duration": 1.0}) == ["body", "floor", "gravity_dynamic",
                                                  "gravity_static", "second_support"]
    assert changed(body={"modes": 4}) == ["body"]
    # the floor runs the held-out points' curves and, when asked for, the second support's test
    assert changed(second_support={"tolerance": 0.02}) == ["floor", "second_support"]
    assert changed(relaxation={"hold_steps": 20}) == ["floor", "relaxation"]
    assert changed(indentation={"steps": 12}) == ["floor", "indentation", "relaxation"]
    assert changed(experiments=list(liver_scene.experiments) + ["second_support"]) == ["floor"]
    assert changed(material={"C10": 2100.0}) == list(sorted(EXPERIMENTS))
    assert sorted(e for e, k in experiment_keys(liver_scene, "other mesh").items()
                  if k != base[e]) == sorted(EXPERIMENTS)


def _groups(path) -> set[str]:
    with h5py.File(path, "r") as fh:
        out = set()
        fh.visit(out.add)
        return out


@pytest.mark.slow
@pytest.mark.fe
def test_an_indentation_only_scene_computes_only_what_it_needs(tmp_path):
    scene_path, out = tmp_path / "tiny.toml", tmp_path / "out"
    write_scene(scene_path, {})
    scene_path.write_text('experiments = ["indentation"]\n' + scene_path.read_text())
    scene = load_scene(scene_path)
    n_points = len(build_problem(scene).test_points)

    # 1. indentation only: no relaxation or gravity item, no gravity stage, nulls with reasons
    outcomes = run_pipeline(scene, out, progress=False, ranks=1)
    assert ran(outcomes) == ["reference", "calibrate", "report"]
    ref = read_reference(out / "reference.h5")
    assert ref.experiments == ("indentation",)
    assert json.loads(ref.meta["items_computed"]) == {"indentation": n_points}
    assert json.loads(ref.meta["timings_s"])["relaxation"] == 0.0
    assert not {"relaxation", "gravity"} & _groups(out / "reference.h5")
    params = read_params(out / "params.h5")
    assert params.experiments == ("indentation",) and set(params.global_fits) == {"static"}
    assert ARMS_NOT_CALIBRATED in params.warnings
    assert not (out / "gravity.h5").exists()
    report = read_report(out / "report.json")
    assert report["experiments"] == ["indentation"]
    assert set(report["not_run"]) == {"relaxation", "gravity_static", "gravity_dynamic", "body",
                                      "second_support", "floor"}
    assert all("not in the scene's experiments" in why for why in report["not_run"].values())
    for key in ERROR_KEYS:
        assert (report["errors"][key] is None) == (not key.startswith("indentation")), key
    assert 0.0 < report["errors"]["indentation_calibrated"] < 0.2
    assert report["timings_s"]["gravity_fe"] is None and report["gravity"] is None
    assert ARMS_NOT_CALIBRATED in report["warnings"]
    figures = {p.name for p in (out / "figures").iterdir()}
    assert figures == {"calibration.png", "held_out.png", "errors.png"}
    assert not list(out.glob("gravity_*"))
    forces = ref.indentation.force

    # 2. + gravity_static: that one FE item, the reused curves; the calibration reruns, as a
    # fresh run of this scene would: its springs are now kept stiff on the FE sag's release
    # strains and its fit must carry gravity (the gravity check)
    scene_path.write_text(scene_path.read_text().replace(
        'experiments = ["indentation"]', 'experiments = ["indentation", "gravity_static"]'))
    scene = load_scene(scene_path)
    outcomes = run_pipeline(scene, out, progress=False, ranks=1)
    assert ran(outcomes) == ["reference", "calibrate", "gravity", "report"]
    assert "scene [experiments] changed" in outcomes[1].reasons
    ref = read_reference(out / "reference.h5")
    assert ref.experiments == ("indentation", "gravity_static")
    assert json.loads(ref.meta["items_computed"]) == {"gravity_static": 1}
    assert json.loads(ref.meta["reused"]) == ["indentation"]
    np.testing.assert_array_equal(ref.indentation.force, forces)  # taken over, not recomputed
    assert np.all(ref.gravity.static_displacement[ref.problem.fixed] == 0.0)
    assert np.linalg.norm(ref.gravity.static_displacement, axis=1).max() > 1e-4  # it sags
    report = read_report(out / "report.json")
    assert report["experiments"] == ["indentation", "gravity_static"]
    assert set(report["not_run"]) == {"relaxation", "gravity_dynamic", "body", "second_support",
                                      "floor"}
    assert 0.0 < report["errors"]["gravity_static"] < 1.0
    assert report["errors"]["gravity_dynamic"] is None
    assert report["errors"]["relaxation_calibrated"] is None
    assert "particle_dynamic_s" not in report["gravity"]
    assert (out / "figures" / "gravity_static.png").is_file()
    assert not (out / "figures" / "gravity_dynamic.png").exists()

    # 3. removing it again recomputes nothing upstream; the reference stays a superset, and
    # the calibration, rerun, is the indentation-only scene's of step 1 (it reads the FE sag
    # only for a scene that runs gravity)
    scene_path.write_text(scene_path.read_text().replace(', "gravity_static"]', "]"))
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, ranks=1)
    assert ran(outcomes) == ["calibrate", "report"]
    again = read_params(out / "params.h5").connectors["calibrated"]
    np.testing.assert_array_equal(again.K0, params.connectors["calibrated"].K0)
    assert read_reference(out / "reference.h5").experiments == ("indentation", "gravity_static")
    assert read_report(out / "report.json")["errors"]["gravity_static"] is None
    assert not (out / "figures" / "gravity_static.png").exists()


def test_tiny_scene_lists_every_default_experiment():
    assert load_scene(SCENES / "tiny.toml").experiments == DEFAULT_EXPERIMENTS
