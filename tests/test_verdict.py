"""The verdict (pipelines.verdict): each check against its goal and the baseline, from a report.

Pure functions on dicts: no model runs here (the runs that record failures and write the
verdict are in tests/test_validation_failures.py).
"""
import copy
import json

import pytest

from forcecal.errors import SceneError
from forcecal.scene import VerdictSection, keys_table, scene_from_dict
from pipelines.verdict import (AT_LEAST, CHECKS, NOT_ASKED, OPT_IN, CheckSpec, Measured,
                               judge, judge_check, measurements, verdict_markdown, verdict_text)

ERROR = CheckSpec("indentation")
WEIGHT = CheckSpec("gravity_static", AT_LEAST, "g")


@pytest.mark.parametrize("measured, goal, spec, no_worse, status, reason", [
    (Measured(0.10, 0.12), 0.15, ERROR, True, "passed", None),
    (Measured(0.15, 0.20), 0.15, ERROR, True, "passed", None),  # at the goal: met
    (Measured(0.16, 0.20), 0.15, ERROR, True, "failed", "16.00 % is not at most the goal 15.00 %"),
    (Measured(0.10, 0.09), 0.15, ERROR, True, "failed",
     "10.00 % is worse than the closed-form baseline's 9.00 %"),
    (Measured(0.10, 0.09), 0.15, ERROR, False, "passed", None),  # comparison not required
    (Measured(0.10, None), 0.15, ERROR, True, "passed", None),  # a failed baseline: no comparison
    (Measured(0.10, 0.20, failure="did not complete"), 0.15, ERROR, True, "failed",
     "did not complete"),
    (Measured(None, 0.20, not_run="not in the scene"), 0.15, ERROR, True, "not_run",
     "not in the scene"),
    (Measured(None, None), 0.15, ERROR, True, "not_run", "not measured"),
    (Measured(1.0, 1.0), 1.0, WEIGHT, True, "passed", None),
    (Measured(0.67, 1.0, failure="gravity load 0.67 -> 0.68"), 1.0, WEIGHT, True, "failed",
     "gravity load 0.67 -> 0.68"),
    (Measured(0.9, 0.5), 0.8, WEIGHT, True, "passed", None),  # at least the goal, above baseline
    (Measured(0.7, 0.5), 0.8, WEIGHT, True, "failed", "0.7 g is not at least the goal 0.8 g"),
    (Measured(0.9, 1.0), 0.8, WEIGHT, True, "failed",
     "0.9 g is worse than the closed-form baseline's 1 g"),
])
def test_one_check_against_its_goal_and_the_baseline(measured, goal, spec, no_worse, status,
                                                       reason):
    entry = judge_check(measured, goal, spec, no_worse)
    assert entry == {"calibrated": measured.calibrated, "baseline": measured.baseline,
                     "goal": goal, "status": status,
                     "passed": None if status == "not_run" else status == "passed",
                     "reason": reason}


def test_the_verdict_passes_only_when_every_check_passed():
    goals = VerdictSection()
    good = {name: Measured(1.0 if spec.direction == AT_LEAST else 0.01, None)
            for name, spec in CHECKS.items()}
    verdict = judge(good, goals)
    assert verdict["passed"] is True and verdict["require_no_worse_than_baseline"] is True
    assert set(verdict["checks"]) == set(CHECKS)
    assert {c["goal"] for n, c in verdict["checks"].items()} == {
        getattr(goals, n) for n in CHECKS}
    for name, status in (("release_rms", "not_run"), ("static_sag", "failed")):
        measured = dict(good)
        measured[name] = (Measured(None, None, not_run="no gravity") if status == "not_run"
                          else Measured(0.5, 0.1))
        verdict = judge(measured, goals)
        assert verdict["passed"] is False and verdict["checks"][name]["status"] == status
        assert sum(c["status"] == "passed" for c in verdict["checks"].values()) == len(CHECKS) - 1


def _report() -> dict:
    """A report's measured keys: every experiment run, 2 held-out points, no failures."""
    dynamic = {"period_error": -0.05, "first_peak_error": 0.07, "rms_error": 0.25}
    return {
        "errors": {"indentation_held_out": 0.12, "relaxation_held_out": 0.14,
                   "gravity_static": 0.05, "gravity_dynamic": 0.25},
        "baseline_errors": {"indentation_held_out": 0.13, "relaxation_held_out": 0.13,
                            "gravity_static": 0.08, "gravity_dynamic": 0.22},
        "gravity": {"dynamic_metrics": {"calibrated": dynamic,
                                        "baseline": {"period_error": 0.11,
                                                     "first_peak_error": -0.03}}},
        "test_points": {"calibration": [1, 2], "held_out": [3, 4]},
        "second_support": {"errors": {"static_sag": 0.06, "release_rms": 0.28},
                           "baseline_errors": {"static_sag": 0.09, "release_rms": 0.31}},
        "not_run": {}, "failures": []}


def test_measurements_of_a_complete_run_and_the_default_goals():
    checks = judge(measurements(_report()), VerdictSection())["checks"]
    assert {n: (c["calibrated"], c["baseline"], c["status"]) for n, c in checks.items()} == {
        "held_out_indentation": (0.12, 0.13, "passed"),
        "held_out_relaxation": (0.14, 0.13, "failed"),  # within the goal, worse than baseline
        "static_sag": (0.05, 0.08, "passed"),
        "release_period": (0.05, 0.11, "passed"),  # |signed errors|
        "release_first_peak": (0.07, 0.03, "failed"),
        "release_rms": (0.25, 0.22, "failed"),
        "carries_its_weight": (1.0, 1.0, "passed"),
        "second_support_static_sag": (0.06, 0.09, "passed"),
        "second_support_release_rms": (0.28, 0.31, "passed")}
    loose = judge(measurements(_report()), VerdictSection(no_worse_than_baseline=False))
    assert loose["passed"] is True


def test_held_out_points_beyond_the_fitted_strains_are_named_whatever_the_status():
    """A held-out point whose connectors the calibrated model drives beyond the strains the
    calibration points reached is judged on an extrapolated spring law: its check says so in
    its reason, passed or failed; points within them, a failed point (null) and a report
    without strain ranges add nothing."""
    report = _report()
    report["strain_ranges"] = {
        "indentation": {"calibrated": {"calibration": [-0.16, 0.20],
                                       "held_out": {"3": [-0.47, 0.83], "4": [-0.1, 0.1]}},
                        "global": {"calibration": [-0.1, 0.1], "held_out": {"3": [-0.5, 0.9],
                                                                           "4": [-0.2, 0.1]}}},
        "relaxation": {"calibrated": {"calibration": [-0.16, 0.20],
                                      "held_out": {"3": None, "4": [-0.15, 0.2]}}}}
    checks = judge(measurements(report), VerdictSection())["checks"]
    note = ("held-out point(s) [3] drive connectors to strains [-0.47, 0.83], beyond the range "
            "the calibration points reached [-0.16, 0.2]: the fitted spring law is "
            "extrapolated there")
    assert checks["held_out_indentation"]["status"] == "passed"
    assert checks["held_out_indentation"]["reason"] == note
    # only the calibrated model's ranges count; the relaxation's point 4 is within them
    assert checks["held_out_relaxation"]["reason"] == ("14.00 % is worse than the closed-form "
                                                       "baseline's 13.00 %")
    report["errors"]["indentation_held_out"] = 0.2
    failed = judge(measurements(report), VerdictSection())["checks"]["held_out_indentation"]
    assert failed["reason"] == f"20.00 % is not at most the goal 15.00 %; {note}"
    assert "strain" not in str(judge(measurements(_report()), VerdictSection()))


def test_failures_fail_their_checks_and_a_failed_baseline_is_no_comparison():
    report = _report()
    report["failures"] = [
        # the calibrated model at a held-out point: held_out_indentation fails
        {"model": "calibrated", "experiment": "indentation", "point": 4, "role": "held_out",
         "reached": {"depth_m": 0.0048}, "reason": "ConvergenceError: Newton"},
        # at a calibration point: no held-out check is about it
        {"model": "calibrated", "experiment": "relaxation", "point": 1, "role": "calibration",
         "reached": {"time_s": 0.1}, "reason": "ConvergenceError: Newton"},
        # the baseline cannot carry its weight: no comparison for the gravity checks
        {"model": "baseline", "experiment": "gravity_static", "point": None, "role": None,
         "reached": {"load_factor": 0.67}, "reason": "ConvergenceError: gravity load"}]
    for key in ("gravity_static", "gravity_dynamic"):
        report["baseline_errors"][key] = None
    del report["gravity"]["dynamic_metrics"]["baseline"]
    checks = judge(measurements(report), VerdictSection())["checks"]
    held = checks["held_out_indentation"]
    assert held["status"] == "failed" and held["calibrated"] == 0.12
    assert held["reason"] == ("did not complete indentation at 1 held-out point(s) [4] (point 4 "
                              "stopped at depth_m = 0.0048: ConvergenceError: Newton)")
    assert checks["held_out_relaxation"]["status"] == "failed"  # worse than baseline only
    assert "baseline" in checks["held_out_relaxation"]["reason"]
    # without the baseline's comparison the release's first peak and RMS now pass
    for name in ("static_sag", "release_period", "release_first_peak", "release_rms"):
        assert checks[name]["status"] == "passed" and checks[name]["baseline"] is None, name
    assert (checks["carries_its_weight"]["calibrated"], checks["carries_its_weight"]["baseline"],
            checks["carries_its_weight"]["status"]) == (1.0, 0.67, "passed")


def test_a_calibrated_model_that_cannot_carry_its_weight_fails_every_gravity_check():
    report = _report()
    report["failures"] = [{"model": "calibrated", "experiment": "gravity_static", "point": None,
                           "role": None, "reached": {"load_factor": 0.67},
                           "reason": "ConvergenceError: gravity load 0.67 -> 0.68 failed"}]
    report["errors"]["gravity_static"] = report["errors"]["gravity_dynamic"] = None
    del report["gravity"]["dynamic_metrics"]["calibrated"]
    checks = judge(measurements(report), VerdictSection())["checks"]
    for name in ("static_sag", "release_period", "release_first_peak", "release_rms",
                 "carries_its_weight"):
        assert checks[name]["status"] == "failed", name
        assert checks[name]["reason"] == ("gravity_static stopped at load_factor = 0.67: "
                                          "ConvergenceError: gravity load 0.67 -> 0.68 failed")
    assert checks["carries_its_weight"]["calibrated"] == 0.67
    assert checks["held_out_indentation"]["status"] == "passed"


def test_the_weight_carried_is_the_smallest_load_factor_recorded():
    """A calibration may record a load its fitted model had no equilibrium for (a body load,
    written to params.h5 as a ``gravity_static`` failure) next to the gravity stage's run: the
    model carried the smallest of them."""
    report = _report()
    record = {"model": "calibrated", "experiment": "gravity_static", "point": None,
              "role": None, "reason": "ConvergenceError: no equilibrium"}
    report["failures"] = [{**record, "reached": {"load_factor": 0.9}},
                          {**record, "reached": {"load_factor": 0.8}}]
    check = judge(measurements(report), VerdictSection())["checks"]["carries_its_weight"]
    assert (check["calibrated"], check["baseline"], check["status"]) == (0.8, 1.0, "failed")
    assert check["reason"].startswith("gravity_static stopped at load_factor = 0.8: ")


def test_a_release_that_fails_fails_the_release_checks_only():
    report = _report()
    report["failures"] = [{"model": "calibrated", "experiment": "gravity_dynamic", "point": None,
                           "role": None, "reached": {"time_s": 1.25},
                           "reason": "StabilityError: connector 3 left its range"}]
    report["errors"]["gravity_dynamic"] = None
    del report["gravity"]["dynamic_metrics"]["calibrated"]
    checks = judge(measurements(report), VerdictSection())["checks"]
    assert [n for n, c in checks.items() if c["status"] == "failed"] == [
        "held_out_relaxation", "release_period", "release_first_peak", "release_rms"]
    assert checks["release_rms"]["reason"].startswith("gravity_dynamic stopped at time_s = 1.25")
    assert checks["static_sag"]["status"] == checks["carries_its_weight"]["status"] == "passed"


def test_checks_not_measured_are_not_run_with_the_reason():
    report = _report()
    report["not_run"] = {"gravity_dynamic": "not in the scene's experiments"}
    report["errors"]["gravity_dynamic"] = report["baseline_errors"]["gravity_dynamic"] = None
    report["gravity"]["dynamic_metrics"] = None
    report["test_points"]["held_out"] = []
    report["errors"]["indentation_held_out"] = report["errors"]["relaxation_held_out"] = None
    verdict = judge(measurements(report), VerdictSection())
    statuses = {n: c["status"] for n, c in verdict["checks"].items()}
    assert statuses == {"held_out_indentation": "not_run", "held_out_relaxation": "not_run",
                        "static_sag": "passed", "release_period": "not_run",
                        "release_first_peak": "not_run", "release_rms": "not_run",
                        "carries_its_weight": "passed", "second_support_static_sag": "passed",
                        "second_support_release_rms": "passed"}
    assert verdict["checks"]["release_rms"]["reason"] == "not in the scene's experiments"
    assert verdict["checks"]["held_out_indentation"]["reason"] == "the scene has no held-out points"
    assert all(verdict["checks"][n]["passed"] is None for n, s in statuses.items()
               if s == "not_run")
    assert verdict["passed"] is False
    # the FE stage's record of a failed FE gravity test: every gravity check not run
    fe = copy.deepcopy(_report())
    fe["fe_failures"] = {"gravity": {"experiment": "gravity_static", "reason": "diverged"}}
    checks = judge(measurements(fe), VerdictSection())["checks"]
    for name in ("static_sag", "release_rms", "carries_its_weight"):
        assert checks[name]["status"] == "not_run", name
        assert checks[name]["reason"] == "the FE gravity test failed: diverged"
        assert checks[name]["calibrated"] is None and checks[name]["baseline"] is None


def test_a_failed_whole_body_fit_fails_carries_its_weight_with_the_reason():
    """A calibration whose model has no equilibrium under a body load it was fitted to is a
    failed calibration: the verdict's weight check fails with its reason."""
    report = _report()
    assert judge(measurements(report), VerdictSection())["checks"]["carries_its_weight"][
        "status"] == "passed"
    report["body"] = {"status": "failed", "failure": "the calibrated model does not carry "
                      "the whole-body data it was fitted to: ConvergenceError: load 0 at 0.8"}
    check = judge(measurements(report), VerdictSection())["checks"]["carries_its_weight"]
    assert check["status"] == "failed"
    assert check["reason"] == f"failed calibration: {report['body']['failure']}"
    report["body"]["status"] = "not fitted"  # not asked for, or not usable: no failure
    assert judge(measurements(report), VerdictSection())["checks"]["carries_its_weight"][
        "status"] == "passed"


def test_a_scene_that_does_not_ask_for_the_second_support_is_judged_without_it():
    """The opt-in second support's checks are left out of the verdict when the scene's
    experiments do not hold it (a scene is judged on the tests it asks for), and judged
    (not run, so not passed) when it asks for them and its stage gave nothing."""
    from pipelines.report import check_verdict
    asked = judge(measurements(_report()), VerdictSection())
    report = _report()
    report.pop("second_support")
    report["not_run"] = {"second_support": f"{NOT_ASKED} ['indentation']: not computed"}
    verdict = judge(measurements(report), VerdictSection())
    assert set(verdict["checks"]) == set(CHECKS) - set(OPT_IN)
    assert verdict["checks"] == {n: c for n, c in asked["checks"].items() if n not in OPT_IN}
    # the same report with every other check passed passes
    passing = judge({n: Measured(1.0 if CHECKS[n].direction == AT_LEAST else 0.01, None)
                     for n in verdict["checks"]}, VerdictSection())
    assert passing["passed"] is True and set(passing["checks"]) == set(verdict["checks"])
    check_verdict(verdict)
    check_verdict(passing)
    report["not_run"] = {"second_support": "in the scene's experiments but its stage "
                                           "produced no results"}
    verdict = judge(measurements(report), VerdictSection())
    assert verdict["checks"]["second_support_static_sag"]["status"] == "not_run"
    assert verdict["passed"] is False


def test_the_second_support_checks_judge_its_block_and_its_failures():
    """The second held-out body test's checks read ``second_support``'s errors against their
    goals (and the baseline's); a scene without it has them not run, the others unchanged; a
    failed FE test is the reason; a model's failure of its sag fails both, of its release the
    RMS only; a baseline that failed it is no comparison."""
    checks = judge(measurements(_report()), VerdictSection(second_support_static_sag=0.05))[
        "checks"]
    assert checks["second_support_static_sag"]["reason"] == "6.00 % is not at most the goal 5.00 %"
    report = _report()
    report["second_support"]["errors"]["static_sag"] = 0.10  # worse than the baseline's 9 %
    assert judge(measurements(report), VerdictSection())["checks"][
        "second_support_static_sag"]["reason"] == ("10.00 % is worse than the closed-form "
                                                   "baseline's 9.00 %")
    why = "not in the scene's experiments ['indentation']: not computed (FE or particle)"
    report = _report()
    report["second_support"], report["not_run"] = None, {"second_support": why}
    checks = judge(measurements(report), VerdictSection())["checks"]
    assert not set(OPT_IN) & set(checks)  # not asked for: not judged
    assert checks["static_sag"]["status"] == "passed"  # the gravity test's checks as before
    fe = copy.deepcopy(report)
    fe["not_run"] = {}
    fe["fe_failures"] = {"gravity": None, "second_support": {
        "experiment": "second_support_static", "reason": "diverged"}}
    checks = judge(measurements(fe), VerdictSection())["checks"]
    assert checks["second_support_release_rms"]["reason"] == (
        "the FE second-support test failed: diverged")
    assert checks["release_rms"]["status"] == "failed"  # worse than its baseline, as before
    record = {"point": None, "role": None, "reason": "ConvergenceError: no equilibrium"}
    report = _report()
    report["second_support"]["errors"] = {"static_sag": None, "release_rms": None}
    report["second_support"]["baseline_errors"]["release_rms"] = None
    report["failures"] = [
        {**record, "model": "calibrated", "experiment": "second_support_static",
         "reached": {"load_factor": 0.5}},
        {**record, "model": "baseline", "experiment": "second_support_dynamic",
         "reached": {"time_s": 0.2}}]
    checks = judge(measurements(report), VerdictSection())["checks"]
    for name in ("second_support_static_sag", "second_support_release_rms"):
        assert checks[name]["status"] == "failed"
        assert checks[name]["reason"] == ("second_support_static stopped at load_factor = 0.5: "
                                          "ConvergenceError: no equilibrium")
    assert checks["second_support_static_sag"]["baseline"] == 0.09
    assert checks["second_support_release_rms"]["baseline"] is None
    assert checks["carries_its_weight"]["status"] == "passed"  # the gravity test's weight


def test_tables_show_every_check_and_the_reasons():
    verdict = judge(measurements(_report()), VerdictSection())
    text = verdict_text(verdict)
    assert text.splitlines()[0].split() == ["check", "calibrated", "baseline", "goal", "status"]
    assert "held_out_indentation" in text and "12.00 %" in text and "<= 15.00 %" in text
    assert "carries_its_weight" in text and ">= 1 g" in text
    assert text.splitlines()[-1] == ("verdict: FAILED (failed: held_out_relaxation, "
                                     "release_first_peak, release_rms)")
    markdown = verdict_markdown(verdict)
    assert "| `release_rms` | 25.00 % | 22.00 % | <= 30.00 % | **failed** |" in markdown
    json.dumps(verdict)  # what report.json holds


def test_verdict_keys_are_declared_with_defaults_and_bounds():
    scene = scene_from_dict({"verdict": {"static_sag": 0.3, "no_worse_than_baseline": False}})
    assert scene.verdict.static_sag == 0.3 and scene.verdict.held_out_indentation == 0.15
    assert set(CHECKS) | {"no_worse_than_baseline"} == set(
        VerdictSection.__dataclass_fields__)
    for name in CHECKS:
        assert f"`verdict.{name}`" in keys_table()
    with pytest.raises(SceneError, match="carries_its_weight = 1.5: the fraction"):
        scene_from_dict({"verdict": {"carries_its_weight": 1.5}})
    with pytest.raises(SceneError, match="verdict.release_rms"):
        scene_from_dict({"verdict": {"release_rms": -0.1}})
