"""The cross-validation of whole calibrations (studies/fold_cv.py) on a synthetic box."""
import numpy as np

from calibration.synthetic import box_scene, synthetic_reference
from forcecal.problem import build_problem
from studies.fold_cv import EXPERIMENTS, sections, study
from tests.test_calibration_fit import SETTINGS, TRUE_GLOBAL


def test_every_calibration_point_is_predicted_once_and_the_better_fit_is_chosen(tmp_path):
    """Box, 8 calibration points in 2 folds, a uniform truth (the global fit's family holds
    it): the global fit (no local tuning) on 4 points predicts the other 4 as well as it fits
    them, far better than a fit stopped after one evaluation per phase, which is not
    chosen."""
    scene = box_scene(tmp_path, test_points={"calibration": "cover", "n_calibration": 8,
                                             "n_held_out": 8},
                      indentation={"depth": 0.002}, relaxation={"depth": 0.002},
                      calibration={**SETTINGS, "local": False, "cv_folds": 2})
    problem = build_problem(scene)
    synthetic_reference(scene, TRUE_GLOBAL.connector_params(len(problem.mesh.edges)),
                        tmp_path / "reference.h5")
    result = study(tmp_path / "box.toml", tmp_path, {
        "fitted": {}, "one evaluation": {"static_max_evaluations": 1,
                                         "relaxation_max_evaluations": 1}})
    points = sorted(int(p) for p in problem.calibration)
    assert result["points"] == points
    assert sorted(p for fold in result["folds"] for p in fold) == points
    fitted, stopped = result["variants"]["fitted"], result["variants"]["one evaluation"]
    for v in (fitted, stopped):
        assert all(len(v["per_point"][e]) == len(points) for e in EXPERIMENTS)
        assert all(np.all(np.isfinite(v["per_point"][e])) for e in EXPERIMENTS)
    assert max(max(fitted["per_point"][e]) for e in EXPERIMENTS) < 3e-3
    # the whole force vector's error, beside: never below the normal force's (same scale),
    # and small where the fit holds the truth
    for v in (fitted, stopped):
        for e in EXPERIMENTS:
            assert np.all(np.asarray(v["per_point_vector"][e])
                          >= np.asarray(v["per_point"][e]) - 1e-12), e
    assert max(max(fitted["per_point_vector"][e]) for e in EXPERIMENTS) < 3e-3
    assert stopped["score"] > 10.0 * fitted["score"]
    assert result["chosen"] == "fitted"


def test_a_variant_changes_calibration_keys_or_whole_sections():
    """Bare keys are [calibration]'s; a table value changes its own section."""
    assert sections({}) == {}
    assert sections({"kv_per_tet": False}) == {"calibration": {"kv_per_tet": False}}
    assert sections({"particle": {"volume_element": "nodal"}, "kv_per_tet": False}) == {
        "particle": {"volume_element": "nodal"}, "calibration": {"kv_per_tet": False}}
