"""The benchmark's own logic (no timing is asserted): Pareto fronts, derived scenes, sliced
references, recognising a resumed reference run."""
import json

import numpy as np
import pytest

from forcecal.scene import load_scene
from pipelines.bench import _complete_run_seconds
from pipelines.bench_configs import (Config, derived_scene, pareto_front, scene_toml,
                                     sliced_reference)
from tests.conftest import SCENES
from tests.test_h5io import _fake_reference


def test_pareto_front_keeps_exactly_the_undominated_points():
    rows = [{"wall_s": t, "errors": {"overall": e}} for t, e in
            [(1.0, 0.5), (2.0, 0.2), (3.0, 0.3), (4.0, 0.1), (2.0, 0.2), (0.5, 0.9)]]
    # (3, 0.3) is beaten by (2, 0.2); the repeated (2, 0.2) does not dominate its twin
    assert pareto_front(rows) == [True, True, False, True, True, True]


def test_derived_scene_round_trips_through_toml(tmp_path):
    base = load_scene(SCENES / "tiny.toml")
    changes = {"calibration": {"local": False, "static_max_evaluations": 7},
               "test_points": {"calibration": [3, 5, 8]}}
    scene = derived_scene(base, "bench-x", changes, tmp_path)
    assert scene.path == tmp_path / "scene.toml" and scene.name == "bench-x"
    assert scene.calibration.local is False and scene.calibration.static_max_evaluations == 7
    assert scene.test_points.calibration == (3, 5, 8)
    assert not scene.outputs.figures and not scene.outputs.fields
    for section in ("mesh", "material", "fixed", "indentation", "relaxation", "gravity", "fe",
                    "particle"):
        assert scene.fingerprint(section) == base.fingerprint(section), section
    mtime = scene.path.stat().st_mtime_ns
    derived_scene(base, "bench-x", changes, tmp_path)  # unchanged: the file is not rewritten
    assert scene.path.stat().st_mtime_ns == mtime
    assert "[calibration]" in scene_toml(json.loads(json.dumps(base.to_dict(), default=list)))


def test_sliced_reference_keeps_the_curves_of_its_points(tmp_path, liver_scene, liver_problem):
    reference = _fake_reference(liver_problem, liver_scene.material)
    picked = [int(p) for p in liver_problem.calibration[[0, 5, 9]]]
    held = [int(p) for p in liver_problem.held_out]
    config = Config("calibration points", "3 points", {},
                    {"test_points": {"calibration": picked, "held_out": held}}, reference="slice")
    scene = derived_scene(liver_scene, "bench-slice", config.changes, tmp_path)
    sliced = sliced_reference(reference, scene)
    np.testing.assert_array_equal(sliced.problem.calibration, picked)
    np.testing.assert_array_equal(sliced.problem.held_out, liver_problem.held_out)
    rows = [0, 5, 9] + list(range(len(liver_problem.calibration), len(liver_problem.test_points)))
    np.testing.assert_array_equal(sliced.indentation.force, reference.indentation.force[rows])
    np.testing.assert_array_equal(sliced.relaxation.force_normal,
                                  reference.relaxation.force_normal[rows])
    assert sliced.gravity is reference.gravity
    assert sliced.meta["scene_fingerprint"] != reference.meta["scene_fingerprint"]


@pytest.mark.parametrize("total, complete", [(100.0, True), (40.0, False)])
def test_a_resumed_reference_run_is_not_taken_as_a_wall_time(liver_scene, liver_problem, total,
                                                             complete):
    """Items computed 2 x 80 s of CPU on 2 ranks: a 100 s run did them all, a 40 s run cannot
    have (it resumed from checkpoints of an earlier one)."""
    reference = _fake_reference(liver_problem, liver_scene.material)
    reference.meta.update(n_ranks=2, timings_s=json.dumps(
        {"mesh": 1.0, "indentation": 40.0, "relaxation": 80.0, "gravity_static": 10.0,
         "gravity_dynamic": 30.0, "total": total}))
    assert _complete_run_seconds(reference) == ((2, total) if complete else None)
