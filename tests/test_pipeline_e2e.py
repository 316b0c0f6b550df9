"""End to end on the tiny scene: every stage, report keys, content caching, calibrated < baseline.

One full run (FE reference with 2 MPI ranks, calibration with small budgets,
gravity, report) is shared by the tests; each test that changes something
works on its own copy of the output folder.
The reruns compute their FE items in the test process (one rank): the MPI path is
the first run's, and two more mpirun launches cost ~5 s CPU without checking more.
"""
import dataclasses
import json
import math
import shutil
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from calibration.results import read_params
from forcecal.h5io import read_reference
from forcecal.scene import load_scene
from pipelines.gravity import read_gravity
from pipelines.report import CURVE_KEYS, ERROR_KEYS, TIMING_KEYS, build_report, check_report
from pipelines.stages import ORDER, run_pipeline
from tests.conftest import ROOT, SCENES

pytestmark = [pytest.mark.slow, pytest.mark.fe, pytest.mark.mpi]

# the tiny scene with smaller calibration budgets and a shorter gravity run: the test is
# about the pipeline, not about how far the optimiser gets (it still beats the baseline).
# The calibration evaluates its points in the test process (workers = 1, a setting outside
# every stage key): on the tiny scene two worker processes cost ~3 s more CPU per calibration
# (their start and the traffic) and, even with a core free, save at most ~1 s of wall time (the
# default budgets, idle machine: 7.7-8.7 s inline, 7.1-8.1 s with two); in `make test` the other
# core runs the other pytest worker. They check nothing the tests of the process transport
# (test_calibration_fit's command-line and workers tests, test_calibration_pool) do not
FAST = {"calibration": {"static_max_evaluations": 60, "relaxation_max_evaluations": 80,
                        "local_max_evaluations": 25, "local_max_sweeps": 1, "workers": 1},
        "gravity": {"duration": 0.1}}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, str):
        return json.dumps(v)
    return repr(v)


def write_scene(path, changes: dict) -> None:
    """Copy scenes/tiny.toml to ``path`` with ``changes`` ({section: {key: value}}) applied."""
    doc = tomllib.loads((SCENES / "tiny.toml").read_text())
    for section, keys in [*FAST.items(), *changes.items()]:
        doc[section] = {**doc.get(section, {}), **keys}
    lines = [f"{k} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for section, table in doc.items():
        if isinstance(table, dict):
            lines += [f"\n[{section}]"] + [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    path.write_text("\n".join(lines) + "\n")


def ran(outcomes) -> list[str]:
    return [o.stage for o in outcomes if o.ran]


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """(scene path, output folder, outcomes) of a complete run from scratch."""
    base = tmp_path_factory.mktemp("pipeline")
    scene_path = base / "tiny.toml"
    write_scene(scene_path, {})
    out = base / "out"
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, ranks=2)
    return scene_path, out, outcomes


def copy_run(first_run, tmp_path):
    scene_path, out, _ = first_run
    shutil.copy(scene_path, tmp_path / "tiny.toml")
    shutil.copytree(out, tmp_path / "out")
    return tmp_path / "tiny.toml", tmp_path / "out"


def test_first_run_runs_every_stage_and_writes_every_output(first_run):
    _, out, outcomes = first_run
    assert ran(outcomes) == list(ORDER)
    for name in ("reference.h5", "params.h5", "gravity.h5", "report.json", "gravity_fe.xdmf",
                 "gravity_fe.h5", "gravity_particle.xdmf", "gravity_particle.h5"):
        assert (out / name).is_file(), name
    for name in ("calibration", "held_out", "gravity_static", "gravity_dynamic", "errors"):
        assert (out / "figures" / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    gravity = read_gravity(out / "gravity.h5")
    assert set(gravity.models) == {"calibrated", "baseline"}


def test_report_has_every_key_finite_and_calibration_beats_the_baseline(first_run):
    _, out, _ = first_run
    report = json.loads((out / "report.json").read_text())
    assert report["scene"] == "tiny"
    assert report["mesh"] == {"nodes": 78, "tets": 186, "connectors": 336}
    assert len(report["test_points"]["calibration"]) == 9
    assert len(report["test_points"]["held_out"]) == 8
    for group, keys in (("errors", ERROR_KEYS), ("baseline_errors", ERROR_KEYS),
                        ("timings_s", TIMING_KEYS)):
        assert set(keys) <= set(report[group])
        for k in keys:
            assert isinstance(report[group][k], float) and math.isfinite(report[group][k]), k
    for k in ("forcecal", "python", "numpy", "scipy", "numba", "dolfinx", "gmsh"):
        assert report["versions"][k], k
    assert report["versions"]["dolfinx"] == "0.5.2"
    # the whole point of calibrating: the fitted curves beat the closed-form springs at the
    # points fitted (the one global parameter set alone need not: on this coarse mesh the
    # baseline's per-edge stiffness follows the tet volumes better than a uniform spring)
    for key in ("indentation_calibrated", "relaxation_calibrated"):
        assert report["errors"][key] < report["baseline_errors"][key], key
    # the whole force vector: never below its normal component's error (same scale), and
    # its tangential part is the rest of it
    vector = report["force_vector_errors"]
    for model, normal in (("calibrated", report["errors"]), ("baseline",
                                                            report["baseline_errors"])):
        for key in CURVE_KEYS:
            whole, tangential = vector[model][key], vector[f"{model}_tangential"][key]
            assert normal[key] <= whole + 1e-12 and tangential <= whole + 1e-12, (model, key)
            assert whole <= normal[key] + tangential + 1e-12, (model, key)
    # the baseline is one model: its "global" and "calibrated" errors are the same points
    assert report["baseline_errors"]["indentation_global"] == report["baseline_errors"][
        "indentation_calibrated"]
    # every model completed its validation; the verdict judges what the report measured
    assert report["failures"] == []
    checks = report["verdict"]["checks"]
    assert checks["static_sag"]["calibrated"] == report["errors"]["gravity_static"]
    assert checks["held_out_relaxation"]["baseline"] == report["baseline_errors"][
        "relaxation_held_out"]
    assert checks["release_period"]["calibrated"] == abs(
        report["gravity"]["dynamic_metrics"]["calibrated"]["period_error"])
    assert report["verdict"]["passed"] == all(c["status"] == "passed" for c in checks.values())
    assert report["realtime"]["status"] == "measured"
    assert report["realtime"]["substeps_per_ms"] >= 1


def test_a_params_file_without_force_vectors_reports_them_as_null(first_run):
    """A ``params.h5`` written before the force vectors were stored (their group removed):
    the report keeps every other number and says why ``force_vector_errors`` is null."""
    _, out, _ = first_run
    params = read_params(out / "params.h5")
    older = dataclasses.replace(params, variants={
        v: dataclasses.replace(c, forces=None) for v, c in params.variants.items()})
    report = build_report("tiny", read_reference(out / "reference.h5"), older,
                          read_gravity(out / "gravity.h5"))
    check_report(report)
    assert report["force_vector_errors"] is None
    assert any("no force vectors" in w for w in report["warnings"])
    assert report["errors"] == json.loads((out / "report.json").read_text())["errors"]


def test_second_run_skips_every_stage_and_says_why(first_run, tmp_path):
    scene_path, out = copy_run(first_run, tmp_path)
    r = subprocess.run([sys.executable, "-m", "pipelines", "demo", "--scene", str(scene_path),
                        "--out", str(out), "--no-progress"], capture_output=True, text=True,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    for stage in ORDER:
        assert f"{stage:<10} skipped" in r.stdout
        assert f"{stage:<9} up to date, skipped" in r.stderr
    # the command ends with the verdict table of the report kept
    assert r.stdout.splitlines()[-2].startswith("verdict: ")
    assert r.stdout.splitlines()[-1].startswith("real time (1 kHz): ")


def test_deleted_output_reruns_only_its_stage(first_run, tmp_path):
    scene_path, out = copy_run(first_run, tmp_path)
    (out / "figures" / "errors.png").unlink()
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False)
    assert ran(outcomes) == ["report"]
    assert outcomes[-1].reasons == ("output figures/errors.png is missing",)
    assert (out / "figures" / "errors.png").is_file()


def test_force_reruns_the_named_stage_only(first_run, tmp_path):
    scene_path, out = copy_run(first_run, tmp_path)
    outcomes = run_pipeline(load_scene(scene_path), out, until="gravity", force=("gravity",),
                            progress=False)
    assert [o.stage for o in outcomes] == ["reference", "calibrate", "gravity"]
    assert ran(outcomes) == ["gravity"] and outcomes[-1].reasons == ("--force",)


def test_reference_computed_outside_the_pipeline_is_adopted(first_run, tmp_path):
    scene_path, out = copy_run(first_run, tmp_path)
    (out / "cache" / "reference.json").unlink()  # as if python -m reference_fe had made it
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False)
    assert ran(outcomes) == []


def test_calibration_keys_rerun_calibration_and_downstream_not_the_reference(first_run,
                                                                              tmp_path):
    scene_path, out = copy_run(first_run, tmp_path)
    before = (out / "reference.h5").read_bytes()
    write_scene(scene_path, {"calibration": {"local_max_evaluations": 20}})
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False)
    assert ran(outcomes) == ["calibrate", "gravity", "report"]
    assert outcomes[1].reasons == ("scene [calibration] changed",)
    assert outcomes[2].reasons == ("params.h5 changed",)
    assert (out / "reference.h5").read_bytes() == before


def test_a_gravity_key_reruns_the_calibration_whose_gravity_check_reads_it(first_run,
                                                                           tmp_path):
    """The calibration's gravity check runs the particle release with [gravity], and its
    springs are kept stiff on the strain range of the FE sag: a [gravity] change (here only
    the static solve's load steps, a key of the FE's gravity runs alone) reruns it."""
    scene_path, out = copy_run(first_run, tmp_path)
    write_scene(scene_path, {"gravity": {"static_load_steps": 5}})
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, until="calibrate")
    assert ran(outcomes) == ["reference", "calibrate"]
    assert "scene [gravity] changed" in outcomes[1].reasons


def test_material_change_reruns_everything(first_run, tmp_path):
    scene_path, out = copy_run(first_run, tmp_path)
    write_scene(scene_path, {"material": {"C10": 2200.0}})
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, ranks=1)
    assert ran(outcomes) == list(ORDER)
    assert outcomes[0].reasons == ("scene [material] changed",)
    assert "reference.h5 changed" in outcomes[1].reasons
    assert read_reference(out / "reference.h5").material.C10 == 2200.0


def test_a_failed_fe_gravity_test_reports_the_force_checks_and_why_gravity_did_not_run(
        first_run, tmp_path):
    """The FE reference recorded that its gravity test failed (reference.h5 as
    reference_fe.run writes it then: no gravity experiments, fe_failures.gravity and the
    keys it failed with): the pipeline adopts it, calibrates without the gravity check,
    skips the gravity stage and reports the force errors with the FE failure as the reason
    the gravity parts did not run."""
    from forcecal.h5io import write_reference

    scene_path, out = copy_run(first_run, tmp_path)
    ref = read_reference(out / "reference.h5")
    keys = json.loads(ref.meta["experiment_keys"])
    gravity = ("gravity_static", "gravity_dynamic")
    failure = {"experiment": "gravity_static", "reason": "gravity static: step 1/4 did not "
               "converge", "reached": {"load_factor": 0.0039}}
    meta = {**ref.meta, "experiment_keys": json.dumps({e: k for e, k in keys.items()
                                                       if e not in gravity}),
            "failed_experiment_keys": json.dumps({e: keys[e] for e in gravity}),
            "fe_failures": json.dumps({"replaced": [], "dropped": [], "gravity": failure})}
    write_reference(out / "reference.h5", dataclasses.replace(ref, gravity=None, meta=meta))
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False)
    assert ran(outcomes) == ["calibrate", "report"]  # the reference is adopted as it is
    assert outcomes[2].reasons == ("none of its experiments in the scene's list",)
    report = json.loads((out / "report.json").read_text())
    assert report["experiments"] == ["indentation", "relaxation"]
    assert report["fe_failures"]["gravity"] == failure
    for e in gravity:
        assert report["not_run"][e].startswith("the FE gravity test failed (gravity_static: "
                                               "gravity static: step 1/4 did not converge)")
    assert math.isfinite(report["errors"]["indentation_held_out"])
    assert report["mesh_preflight"]["vertices"] == 78  # what the FE stage saw


def test_asking_for_the_second_support_computes_and_judges_it_and_refits_nothing(first_run,
                                                                                 tmp_path):
    """The second held-out body test (the tiny liver hung from its top, [second_support]'s
    default): one more FE item, the reference's other experiments taken over, the calibration
    not rerun (no fit reads it), the particle models run with its clamp and judged."""
    scene_path, out = copy_run(first_run, tmp_path)
    experiments = ["indentation", "relaxation", "gravity_static", "gravity_dynamic",
                   "second_support"]
    scene_path.write_text(f"experiments = {json.dumps(experiments)}\n"
                          + scene_path.read_text())
    outcomes = run_pipeline(load_scene(scene_path), out, progress=False, ranks=1)
    assert ran(outcomes) == ["reference", "gravity", "report"]
    ref = read_reference(out / "reference.h5")
    assert json.loads(ref.meta["items_computed"]) == {"second_support": 1}
    assert json.loads(ref.meta["reused"]) == experiments[:4]
    support = ref.second_support
    assert len(support.fixed) == 10 and np.all(support.runs.static_displacement[support.fixed]
                                               == 0.0)
    assert json.loads(ref.meta["timings_s"])["second_support"] > 0.0
    report = json.loads((out / "report.json").read_text())
    assert report["experiments"] == experiments
    block = report["second_support"]
    assert (block["fixed_vertices"], block["tracked_node"]) == (10, support.runs.tracked_node)
    assert block["fe_max_static_sag_m"] > 1e-4 and block["fe_seconds"] > 0.0
    # a model that cannot carry the load hung from the top is a result (measured: this
    # calibration, small budgets, stops at 0.53 g; the baseline sags within 10 % of the FE)
    failed = {f["model"]: f for f in report["failures"]}
    assert {f["experiment"] for f in report["failures"]} <= {"second_support_static",
                                                             "second_support_dynamic"}
    checks = report["verdict"]["checks"]
    for model, group in (("calibrated", "errors"), ("baseline", "baseline_errors")):
        for name, key in (("second_support_static_sag", "static_sag"),
                          ("second_support_release_rms", "release_rms")):
            value = block[group][key]
            # a failed sag leaves both measures null, a failed release its RMS
            null = model in failed and (key == "release_rms" or failed[model][
                "experiment"] == "second_support_static")
            assert value is None if null else 0.0 < value < 1.0, (model, key)
            assert checks[name][model] == value
            if model == "calibrated" and model in failed:
                assert checks[name]["status"] == "failed"
                assert checks[name]["reason"].startswith(failed[model]["experiment"])
    first = json.loads((first_run[1] / "report.json").read_text())
    assert "second_support_static_sag" not in first["verdict"]["checks"]  # not asked for
    assert report["errors"] == first["errors"]  # the rest of the report is the first run's
