"""A failed validation is a result, not a crash: each way a particle model can fail its
validation, provoked on a small box scene, is recorded and the run goes on to its report.

The scene: a 6 x 6 x 2 cm box (48 vertices, 197 connectors) standing on its clamped base, 4
calibration + 8 held-out points, 2 mm indentation, and a reference made by the particle model
itself with known parameters (:func:`calibration.synthetic.synthetic_reference`, its gravity
test included), so no FE runs here. One calibration (global fit only, small budgets) is shared;
each test then provokes one failure with physically too-soft springs or a scene key:

* springs ``K(eps) = K0 (1 + eps / 0.2)`` that lose their stiffness at 20 % compression
  (positive on the calibration's strain range, [-0.187, 0.043]): two test points' springs reach
  it before the full 2 mm (measured: at 1.8 mm, points 17 and 32);
* the same shape with ``K0`` = 30 N/m and a root at 50 % compression: the box has no static
  equilibrium beyond 0.79 g (measured: Newton's last converged load 0.789 g);
* ``particle.strain_margin`` = 0: the release is verified on [min(0, 2 eps_static),
  max(0, 2 eps_static)] exactly, and a connector that the sag stretches is compressed early in
  the swing (measured: at 4 ms);
* the second held-out body test with the box hung from its top face (``[second_support]`` z
  max) and springs ``K0 (1 - eps / 0.5)``, ``K0`` = 20 N/m, that soften in tension: the box
  stands on its base (compression stiffens them) but hung from its top has no static
  equilibrium beyond 0.71 g (measured: Newton's last converged load 0.711 g).
"""
import dataclasses
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from calibration.core import calibrate
from calibration.gravity_check import gravity_outcome
from calibration.parametrisation import GlobalParams
from calibration.results import read_params, write_params
from calibration.synthetic import box_scene, synthetic_reference, synthetic_second_support
from calibration.validation import ValidationFailure
from forcecal.h5io import read_reference, write_reference
from forcecal.problem import build_problem
from forcecal.scene import HELD_OUT_EXPERIMENTS, load_scene, replace
from particle.model import build_model
from particle.params import ConnectorParams
from pipelines.cache import Cache
from pipelines.cli import main as pipelines_main
from pipelines.gravity import read_gravity
from pipelines.report import read_report
from pipelines.runners.common import Context
from pipelines.runners.gravity import run_gravity_stage
from pipelines.runners.reference import mpirun_environment
from pipelines.runners.report import run_report
from pipelines.stages import STAGES

TRUTH = GlobalParams(K0=30.0, alpha=1.0, beta=10.0, k1=26.0, tau1=0.5, k2=19.0, tau2=10.0)
DEPTH = 0.002
BUDGET = {"local": False, "static_max_evaluations": 40, "relaxation_max_evaluations": 40,
          "workers": 1}


def _scene(directory, **sections):
    """The box scene; no PNG figures unless ``outputs`` asks (most tests read report.json
    alone, and the figures are a third of a report stage's time)."""
    sections = {"outputs": {"figures": False}, **sections}
    return box_scene(directory, test_points={"calibration": "cover", "n_calibration": 4,
                                             "n_held_out": 8},
                     indentation={"depth": DEPTH}, relaxation={"depth": DEPTH},
                     calibration=BUDGET, gravity={"duration": 0.3}, **sections)


def softening(n: int, K0: float, root: float) -> ConnectorParams:
    """Springs ``K0 (1 + eps / root)``: stiffness zero at compression ``root``."""
    return ConnectorParams(K0=np.full(n, K0), a=np.full(n, K0 / root), b=np.zeros(n),
                           k1=np.full(n, 0.5 * K0), b1=np.full(n, 0.25 * K0),
                           k2=np.full(n, 0.5 * K0), b2=np.full(n, 5.0 * K0))


def _spy(calls: list):
    """A :func:`gravity_outcome` that records its arguments and result in ``calls``."""
    def spy(*args):
        out = gravity_outcome(*args)
        calls.append((args, out))
        return out
    return spy


#: the calibration's gravity checks of the fixture's fit: (arguments, result) per call
CHECK_CALLS: list = []


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """(folder, scene) of a calibrated box whose models all complete their validation."""
    d = tmp_path_factory.mktemp("validation")
    scene = _scene(d)
    n = len(build_problem(scene).mesh.edges)
    synthetic_reference(scene, TRUTH.connector_params(n), d / "reference.h5", gravity=True)
    CHECK_CALLS.clear()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("calibration.gravity_check.gravity_outcome", _spy(CHECK_CALLS))
        calibrate(scene, d / "reference.h5", d / "params.h5", progress=False)
    return d, scene


def _copy(calibrated, tmp_path, **sections):
    """A copy of the calibrated folder, its scene with ``sections`` changed."""
    d, _ = calibrated
    for name in ("box.vtu", "reference.h5", "params.h5"):
        shutil.copy(d / name, tmp_path / name)
    return tmp_path, _scene(tmp_path, **sections)


def _gravity_and_report(folder, scene) -> dict:
    """The gravity and report stages on ``folder``; the report written."""
    ctx = Context(scene, folder, progress=False, ranks=1,
                  experiments=scene.experiments, upstream=("reference.h5", "params.h5",
                                                           "gravity.h5"))
    run_gravity_stage(dataclasses.replace(ctx, experiments=tuple(
        e for e in scene.experiments if e in HELD_OUT_EXPERIMENTS)))
    outputs = run_report(ctx)
    assert "report.json" in outputs
    return read_report(folder / "report.json")


def _swap(folder, model: str, params: ConnectorParams) -> None:
    """Give ``model``'s connectors of ``params.h5`` the parameters ``params``."""
    result = read_params(folder / "params.h5")
    write_params(folder / "params.h5", dataclasses.replace(
        result, connectors={**result.connectors, model: params}))


def test_a_run_whose_models_complete_has_no_failures_and_a_verdict(calibrated, tmp_path):
    folder, scene = _copy(calibrated, tmp_path)
    report = _gravity_and_report(folder, scene)
    assert report["failures"] == []
    checks = report["verdict"]["checks"]
    # the scene does not ask for the second support: its two checks are not run
    assert {c["status"] for n, c in checks.items()
            if not n.startswith("second_support")} <= {"passed", "failed"}
    assert checks["carries_its_weight"]["calibrated"] == 1.0
    assert checks["static_sag"]["calibrated"] == report["errors"]["gravity_static"]
    rt = report["realtime"]
    assert rt["status"] == "measured" and rt["calls"] == 2000 and rt["substeps_per_ms"] >= 1
    assert 0 < rt["step_min_us"] <= rt["step_median_us"] <= rt["step_p99_us"] <= rt[
        "step_max_us"]
    assert rt["step_cpu_us"] > 0
    assert rt["dt_s"] * rt["substeps_per_ms"] == pytest.approx(1e-3)
    assert rt["dt_s"] <= scene.particle.dt_safety * rt["critical_dt_s"] * (1 + 1e-12)
    # the fastest mode's shares: each connector's part of a Rayleigh quotient, so they sum
    # to 1 over all connectors and are listed largest first
    shares = [e["share"] for e in rt["limiting_edges"]]
    assert shares == sorted(shares, reverse=True) and 0 < sum(shares) <= 1 + 1e-12
    assert rt["edge_min_m"] <= min(e["rest_length_m"] for e in rt["limiting_edges"])


def test_the_calibrations_gravity_check_is_the_gravity_stages_run(calibrated, tmp_path,
                                                                   monkeypatch):
    """One check, so the two cannot disagree: the calibration's gravity check of the fit it
    keeps and the gravity stage's run of the calibrated model call the same function with the
    same scene, geometry, parameters, record times and strain range, and get the same test."""
    folder, scene = _copy(calibrated, tmp_path)
    stage_calls: list = []
    monkeypatch.setattr("pipelines.gravity.gravity_outcome", _spy(stage_calls))
    _gravity_and_report(folder, scene)
    (check_args, (check_run, check_failure)), = CHECK_CALLS  # the fit completed: one call
    (stage_args, (stage_run, stage_failure)), = [c for c in stage_calls
                                                 if c[0][5] == "calibrated"]
    check_scene, check_problem, check_params, check_times, check_range = check_args[:5]
    stage_scene, stage_problem, stage_params, stage_times, stage_range = stage_args[:5]
    assert check_scene.gravity == stage_scene.gravity
    assert check_scene.particle == stage_scene.particle
    assert check_scene.material == stage_scene.material
    for name in ("vertices", "tets"):
        assert np.array_equal(getattr(check_problem.mesh, name), getattr(stage_problem.mesh,
                                                                         name))
    assert np.array_equal(check_problem.fixed, stage_problem.fixed)
    for field in dataclasses.fields(check_params):
        a, b = getattr(check_params, field.name), getattr(stage_params, field.name)
        assert (a is None and b is None) or np.array_equal(a, b), field.name
    assert np.array_equal(check_times, stage_times) and check_range == stage_range
    assert check_failure is None and stage_failure is None
    assert np.array_equal(check_run.static_displacement, stage_run.static_displacement)
    assert np.array_equal(check_run.displacement, stage_run.displacement)


def test_a_baseline_that_cannot_reach_the_depth_is_recorded_at_its_points(calibrated,
                                                                           tmp_path,
                                                                           monkeypatch):
    folder, scene = _copy(calibrated, tmp_path, outputs={"figures": True})
    problem = build_problem(scene)
    n = len(problem.mesh.edges)
    monkeypatch.setattr("calibration.core.van_gelder_params",
                        lambda mesh, material: softening(n, 30.0, 0.2))
    result = calibrate(scene, folder / "reference.h5", folder / "params.h5", progress=False)
    indentation = [f for f in result.failures if f.experiment == "indentation"]
    assert {f.model for f in result.failures} == {"baseline"}
    # points 17 (calibration) and 32 (held-out) stop at the last depth before 2 mm
    assert [(f.point, f.role) for f in indentation] == [(17, "calibration"), (32, "held_out")]
    for f in indentation:
        assert f.reached == pytest.approx(0.9 * DEPTH)
        assert f.reason.startswith(f"ParameterError: test point {f.point}: connector")
        assert "where its stiffness K(eps) <= 0" in f.reason
    # the params.h5 round trip: NaN rows at those points only, the rest of the curves kept
    back = read_params(folder / "params.h5")
    assert back.failures == result.failures
    curves = back.variants["baseline"].curves["indentation"]
    failed = [int(np.nonzero(problem.test_points == f.point)[0][0]) for f in indentation]
    assert np.isnan(curves[failed]).all()
    assert np.isfinite(np.delete(curves, failed, axis=0)).all()
    assert np.isfinite(back.variants["calibrated"].curves["indentation"]).all()
    report = _gravity_and_report(folder, scene)
    recorded = [f for f in report["failures"] if f["experiment"] == "indentation"]
    assert recorded == [f.as_dict() for f in indentation]
    assert recorded[1]["reached"] == {"depth_m": pytest.approx(0.0018)}
    # the baseline's held-out error is the mean over the 7 points it completed
    per_point = report["per_point_errors"]["baseline_indentation"]
    assert per_point[failed[1]] is None
    held = [e for e, cal in zip(per_point, report["per_point_errors"]["is_calibration"])
            if not cal and e is not None]
    assert len(held) == 7
    assert report["baseline_errors"]["indentation_held_out"] == pytest.approx(np.mean(held))
    # a baseline that failed the experiment is no comparison; the calibrated model is judged
    # on its goal alone
    check = report["verdict"]["checks"]["held_out_indentation"]
    assert check["baseline"] is None and check["calibrated"] == report["errors"][
        "indentation_held_out"]
    assert (check["status"] == "passed") == (check["calibrated"] <= check["goal"])
    assert (folder / "figures" / "errors.png").is_file()
    assert (folder / "figures" / "held_out.png").is_file()


@pytest.mark.parametrize("model", ["baseline", "calibrated"])
def test_a_model_that_cannot_carry_its_weight_is_a_result(calibrated, tmp_path, model):
    folder, scene = _copy(calibrated, tmp_path, outputs={"figures": True})
    n = len(build_problem(scene).mesh.edges)
    _swap(folder, model, softening(n, 30.0, 0.5))
    report = _gravity_and_report(folder, scene)
    gravity = read_gravity(folder / "gravity.h5")
    other = "calibrated" if model == "baseline" else "baseline"
    # the failure recorded, the other model's whole test kept
    (failure,) = gravity.failures
    assert (failure.model, failure.experiment, failure.point, failure.role) == (
        model, "gravity_static", None, None)
    assert failure.reached == pytest.approx(0.789, abs=0.005)
    assert failure.reason.startswith("ConvergenceError: gravity load 0.789")
    assert set(gravity.models) == {other} and gravity.models[other].displacement is not None
    assert report["failures"] == [failure.as_dict()]
    assert report["failures"][0]["reached"] == {"load_factor": pytest.approx(0.789, abs=0.005)}
    errors = report["errors" if model == "calibrated" else "baseline_errors"]
    assert errors["gravity_static"] is None and errors["gravity_dynamic"] is None
    assert report["gravity"][f"{model}_max_static_sag_m"] is None
    checks = report["verdict"]["checks"]
    weight = checks["carries_its_weight"]
    assert weight[model] == pytest.approx(0.789, abs=0.005) and weight[other] == 1.0
    if model == "calibrated":
        assert report["verdict"]["passed"] is False
        for name in ("static_sag", "release_period", "release_first_peak", "release_rms",
                     "carries_its_weight"):
            assert checks[name]["status"] == "failed", name
            assert checks[name]["reason"].startswith("gravity_static stopped at load_factor")
        assert report["timings_s"]["gravity_particle"] is None
        # what exists is drawn and written: the FE's sag and release, no particle field
        assert not (folder / "gravity_particle.xdmf").exists()
    else:
        assert weight["status"] == "passed"
        assert checks["static_sag"]["baseline"] is None
    assert (folder / "gravity_fe.xdmf").is_file()
    for name in ("gravity_static", "gravity_dynamic"):
        assert (folder / "figures" / f"{name}.png").is_file()


#: the box hung from its top face: the second held-out body test of the box scene
TOP = {"axis": "z", "side": "max", "tolerance": 1e-4}


def _with_second_support(folder, scene):
    """``scene`` asking for the second support (:data:`TOP`), and the folder's synthetic
    reference with its test (the particle model with the truth, as the rest)."""
    scene = replace(scene, second_support=TOP, experiments=[*scene.experiments,
                                                            "second_support"])
    ref = read_reference(folder / "reference.h5")
    n = len(ref.problem.mesh.edges)
    write_reference(folder / "reference.h5", dataclasses.replace(
        ref, second_support=synthetic_second_support(scene, ref.problem,
                                                     TRUTH.connector_params(n))))
    return scene


def test_the_second_support_is_reported_and_judged_and_changes_nothing_else(calibrated,
                                                                            tmp_path):
    """The second held-out body test adds its block and its two checks; the calibration it
    was never fitted to recovers the truth, so the calibrated model matches the synthetic
    reference there too, far better than the baseline; every other number is the report's
    without it."""
    folder, scene = _copy(calibrated, tmp_path)
    without = _gravity_and_report(folder, scene)
    report = _gravity_and_report(folder, _with_second_support(folder, scene))
    block = report["second_support"]
    assert without["second_support"] is None and report["failures"] == []
    assert (block["axis"], block["side"], block["fixed_vertices"]) == ("z", "max", 16)
    for key in ("static_sag", "release_rms"):
        assert block["errors"][key] < 0.01 < block["baseline_errors"][key], key
    assert block["dynamic_metrics"]["calibrated"]["rms_error"] == block["errors"]["release_rms"]
    checks = report["verdict"]["checks"]
    for name, key in (("second_support_static_sag", "static_sag"),
                      ("second_support_release_rms", "release_rms")):
        assert (checks[name]["calibrated"], checks[name]["baseline"], checks[name]["status"]) == (
            block["errors"][key], block["baseline_errors"][key], "passed")
        assert name not in without["verdict"]["checks"]  # not asked for: not judged
    assert without["not_run"]["second_support"].startswith("not in the scene's experiments")
    assert report["experiments"] == without["experiments"] + ["second_support"]
    for key in ("errors", "baseline_errors", "strain_ranges"):
        assert report[key] == without[key], key
    wall = "particle_dynamic_s"  # a wall time
    assert {k: v for k, v in report["gravity"].items() if k != wall} == {
        k: v for k, v in without["gravity"].items() if k != wall}
    assert {n: c for n, c in report["verdict"]["checks"].items()
            if not n.startswith("second_support")} == without["verdict"]["checks"]


def test_a_model_that_cannot_carry_the_load_with_the_second_support_is_a_result(calibrated,
                                                                               tmp_path):
    folder, scene = _copy(calibrated, tmp_path)
    n = len(build_problem(scene).mesh.edges)
    _swap(folder, "calibrated", softening(n, 20.0, -0.5))  # softens in tension
    report = _gravity_and_report(folder, _with_second_support(folder, scene))
    gravity = read_gravity(folder / "gravity.h5")
    (failure,) = gravity.failures
    assert (failure.model, failure.experiment, failure.point, failure.role) == (
        "calibrated", "second_support_static", None, None)
    assert failure.reached == pytest.approx(0.711, abs=0.005)
    assert failure.reason.startswith("ConvergenceError: gravity load 0.71")
    # the scene's gravity test completed; of the second support's, the baseline's alone
    assert gravity.models["calibrated"].displacement is not None
    assert set(gravity.second_support.models) == {"baseline"}
    assert report["failures"] == [failure.as_dict()]
    block = report["second_support"]
    assert block["errors"] == {"static_sag": None, "release_rms": None}
    assert block["calibrated_max_static_sag_m"] is None and "calibrated" not in block[
        "dynamic_metrics"]
    checks = report["verdict"]["checks"]
    for name in ("second_support_static_sag", "second_support_release_rms"):
        assert checks[name]["status"] == "failed"
        assert checks[name]["reason"].startswith("second_support_static stopped at "
                                                 "load_factor = 0.71")
    # carries_its_weight is the scene's gravity test's: it carried that
    assert checks["carries_its_weight"]["calibrated"] == 1.0
    assert checks["static_sag"]["calibrated"] == report["errors"]["gravity_static"]


def test_a_release_that_leaves_its_strain_range_keeps_the_sag(calibrated, tmp_path):
    folder, scene = _copy(calibrated, tmp_path, particle={"strain_margin": 0.0})
    report = _gravity_and_report(folder, scene)
    calibrated_failures = [f for f in report["failures"] if f["model"] == "calibrated"]
    assert [f["experiment"] for f in calibrated_failures] == ["gravity_dynamic"]
    failure = ValidationFailure.from_dict(calibrated_failures[0], "report")
    assert 0 < failure.reached < scene.gravity.duration
    assert failure.reason.startswith("StabilityError: connector")
    assert "the range the step dt" in failure.reason
    gravity = read_gravity(folder / "gravity.h5")
    assert gravity.models["calibrated"].displacement is None  # the sag is kept
    assert report["errors"]["gravity_static"] is not None
    assert report["errors"]["gravity_dynamic"] is None
    checks = report["verdict"]["checks"]
    assert checks["carries_its_weight"]["status"] == "passed"
    for name in ("release_period", "release_first_peak", "release_rms"):
        assert checks[name]["status"] == "failed"
        assert checks[name]["reason"].startswith("gravity_dynamic stopped at time_s")


def _cli(capsys, scene_path, out, *extra) -> tuple[int, str]:
    """``python -m pipelines report`` in-process: (exit code, stdout)."""
    code = pipelines_main(["report", "--scene", str(scene_path), "--out", str(out),
                           "--no-progress", *extra])
    return code, capsys.readouterr().out


def _record_upstream_stages(folder, scene) -> None:
    """Record the reference, calibrate and gravity stages of ``folder`` as done (their cache
    records), so the pipeline runs the report stage alone (the reference is synthetic: no FE)."""
    ctx = Context(scene, folder, progress=False, ranks=1)
    cache = Cache(folder)
    for name, output in (("reference", "reference.h5"), ("calibrate", "params.h5"),
                         ("gravity", "gravity.h5")):
        cache.store(name, STAGES[name].inputs(ctx), [output], 0.0)


def test_require_pass_exits_3_on_a_failed_verdict_and_0_on_a_passed_one(calibrated, tmp_path,
                                                                       capsys):
    folder, scene = _copy(calibrated, tmp_path)
    # every check measured: a check not run (the second support's, unless asked for) has not
    # passed
    scene = _with_second_support(folder, scene)
    text = (f"experiments = {json.dumps(list(scene.experiments))}\n" + scene.path.read_text()
            + "\n[second_support]\n" + "".join(f"{k} = {json.dumps(v)}\n"
                                               for k, v in TOP.items()))
    scene.path.write_text(text)
    _gravity_and_report(folder, scene)  # gravity.h5 for the pipeline's report stage
    _record_upstream_stages(folder, scene)
    strict = text + "\n[verdict]\nstatic_sag = 0.0\n"
    scene.path.write_text(strict)
    code, out = _cli(capsys, scene.path, folder, "--require-pass")
    assert code == 3
    assert "verdict: FAILED" in out and "static_sag: failed: " in out
    assert "real time (1 kHz)" in out
    report = json.loads((folder / "report.json").read_text())
    assert report["verdict"]["checks"]["static_sag"]["status"] == "failed"
    # without --require-pass the same verdict exits 0 (the table still says FAILED)
    code, out = _cli(capsys, scene.path, folder)
    assert code == 0 and "verdict: FAILED" in out
    loose = text + "\n[verdict]\n" + "\n".join(
        f"{k} = 100.0" for k in ("held_out_indentation", "held_out_relaxation", "static_sag",
                                 "release_period", "release_first_peak", "release_rms",
                                 "second_support_static_sag", "second_support_release_rms")) + (
        "\ncarries_its_weight = 0.01\nno_worse_than_baseline = false\n")
    scene.path.write_text(loose)
    code, out = _cli(capsys, scene.path, folder, "--require-pass")
    assert code == 0, out
    assert "verdict: PASSED (9 checks)" in out
    # a change of [verdict] reran the report stage alone
    assert [line.split()[:2] for line in out.splitlines()[:4]] == [
        ["reference", "skipped"], ["calibrate", "skipped"], ["gravity", "skipped"],
        ["report", "ran"]]
    assert "scene [verdict] changed" in out.splitlines()[3]
    assert load_scene(scene.path).verdict.no_worse_than_baseline is False


@pytest.mark.mpi
@pytest.mark.skipif(not shutil.which("mpirun"), reason="needs mpirun")
def test_under_mpi_rank_0_decides_and_every_rank_returns_its_code(calibrated, tmp_path):
    """``mpirun -n 2 python -m pipelines report --require-pass`` with a verdict that fails: the
    report stage runs on rank 0, which reads the verdict, and both ranks end with exit code 3
    (each rank's own return value recorded, not only mpirun's)."""
    folder, scene = _copy(calibrated, tmp_path)
    _gravity_and_report(folder, scene)
    _record_upstream_stages(folder, scene)
    scene.path.write_text(scene.path.read_text() + "\n[verdict]\nstatic_sag = 0.0\n")
    record = ("import os, sys; from pipelines.cli import main; code = main(sys.argv[1:]); "
              "open(os.path.join(sys.argv[-1], 'rank-' + os.environ['OMPI_COMM_WORLD_RANK']), "
              "'w').write(str(code)); sys.exit(code)")
    r = subprocess.run(["mpirun", "-n", "2", sys.executable, "-c", record, "report", "--scene",
                        str(scene.path), "--no-progress", "--require-pass", "--out", str(folder)],
                       capture_output=True, text=True, cwd=tmp_path, timeout=600,
                       env=mpirun_environment())  # without what an in-process MPI set
    assert r.returncode == 3, r.stderr[-3000:]
    assert [(folder / f"rank-{k}").read_text() for k in (0, 1)] == ["3", "3"]
    # printed by rank 0; the second support's checks are not judged (not asked for)
    assert r.stdout.count("verdict: FAILED (failed: static_sag)") == 1, r.stdout[-2000:]


def test_what_sets_the_step_of_one_free_particle_is_its_own_connectors():
    """One free corner of a clamped cube: the fastest mode moves that particle alone, so its
    connectors share the Rayleigh quotient equally (uniform springs: equal stiffness bounds)
    and every other connector has none."""
    from forcecal.mesh import box_mesh
    from forcecal.problem import Problem
    from particle.model import build_model
    from pipelines.realtime import session_strain_range, step_limiters
    mesh = box_mesh((1, 1, 1), (0.01, 0.01, 0.01))
    free = int(np.argmax(mesh.vertices.sum(axis=1)))
    problem = Problem(mesh=mesh, fixed=np.setdiff1d(np.arange(mesh.n_vertices), [free]),
                      calibration=np.array([free]), held_out=np.zeros(0, np.int64),
                      tracked_node=free)
    params = ConnectorParams.uniform(len(mesh.edges), K0=100.0, k1=10.0, b1=1.0, k2=10.0,
                                     b2=10.0)
    model = build_model(problem, 1000.0, params)
    limiters = step_limiters(model, session_strain_range(params), count=len(mesh.edges))
    incident = np.any(mesh.edges == free, axis=1)
    shares = {e["connector"]: e["share"] for e in limiters["limiting_edges"]}
    assert {e for e, v in shares.items() if v > 1e-12} == set(np.nonzero(incident)[0].tolist())
    for e in np.nonzero(incident)[0]:
        assert shares[int(e)] == pytest.approx(1.0 / incident.sum(), rel=1e-9)
    assert all(free in t["particles"] for t in limiters["limiting_tets"] if t["share"] > 0)
    assert limiters["edge_min_m"] == pytest.approx(0.01)


def test_a_haptic_session_that_cannot_run_is_a_failed_real_time_check(tmp_path):
    from pipelines.realtime import realtime_block
    scene = _scene(tmp_path, particle={"dt": 0.01})  # 10 ms: above the box's stable step
    problem = build_problem(scene)
    model = build_model(problem, scene.material.density,
                        TRUTH.connector_params(len(problem.mesh.edges)))
    block = realtime_block(scene, problem, model)
    assert block["status"] == "failed"
    assert block["reason"].startswith("TimeStepError: time step dt = 0.01 s")
    assert block["step_p99_us"] is None and block["substeps_per_ms"] is None
    assert block["limiting_edges"]  # what sets the step is known before the session fails
