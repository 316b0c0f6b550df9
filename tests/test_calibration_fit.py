"""End-to-end calibration on synthetic references made by the particle model itself:
parameter recovery, order independence, parallel == serial, checkpoint/resume, params.h5,
command line and MPI."""
import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from calibration.core import calibrate, checkpoint_path
from calibration.local import LocalModel, run_local_stage
from calibration.parametrisation import GlobalParams, StrainRange, build_rings
from calibration.pool import Experiments, Pool, particle_backend
from calibration.results import read_params
from calibration.synthetic import box_scene, ring_perturbed_params, synthetic_reference
from forcecal.problem import Problem, build_problem
from forcecal.scene import replace
from particle.model import PARAM_NAMES
from tests.conftest import ROOT

# quick budgets: the box has 4 calibration + 8 held-out points and 197 connectors
SETTINGS = {"static_max_evaluations": 80, "relaxation_max_evaluations": 160,
            "local_max_evaluations": 60, "local_max_sweeps": 3, "local_sweep_tolerance": 1e-4,
            "workers": 1}
TRUE_GLOBAL = GlobalParams(K0=30.0, alpha=1.0, beta=10.0, k1=26.0, tau1=0.5, k2=19.0, tau2=10.0)
STRAIN = StrainRange(-0.2, 0.05)  # what the box's 2 mm indentation reaches (linear estimate)


def _box_scene(directory, **calibration):
    return box_scene(directory, test_points={"n_calibration": 4, "n_held_out": 8},
                     indentation={"depth": 0.002}, relaxation={"depth": 0.002},
                     calibration={**SETTINGS, **calibration})


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    return _box_scene(tmp_path_factory.mktemp("box"))


@pytest.fixture(scope="module")
def box_problem(box):
    return build_problem(box)


@pytest.fixture(scope="module")
def nonuniform(box, box_problem):
    """Reference from global + ring factors, and the uninterrupted calibration fitted to it."""
    # K0, k_i, tau_i x0.74..x1.35 per ring, alpha/beta shifted too
    true, _, _ = ring_perturbed_params(box_problem, TRUE_GLOBAL, STRAIN)
    d = box.path.parent / "nonuniform"
    synthetic_reference(box, true, d / "reference.h5")
    result = calibrate(box, d / "reference.h5", d / "params.h5", progress=False)
    return d, true, result


def test_global_fit_recovers_uniform_parameters(box, box_problem, tmp_path):
    scene = replace(box, calibration={"local": False})
    true = TRUE_GLOBAL.connector_params(len(box_problem.mesh.edges))
    synthetic_reference(scene, true, tmp_path / "reference.h5")
    result = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5", progress=False)
    got, want = result.global_params.as_dict(), TRUE_GLOBAL.as_dict()
    # K0, the arms and the relaxation times are pinned by the curves' scale and time constants
    # (0.5 %); alpha and beta trade off against each other over the strains reached, which the
    # 10 indentation samples constrain less (3 %)
    for k in ("K0", "k1", "tau1", "k2", "tau2"):
        assert got[k] == pytest.approx(want[k], rel=5e-3), k
    for k in ("alpha", "beta"):
        assert got[k] == pytest.approx(want[k], rel=3e-2), k
    for experiment in ("indentation", "relaxation"):
        assert result.variants["global"].errors[experiment].max() < 1e-3
    assert not result.local_sweeps["static"] and not result.local_sweeps["relaxation"]


def test_local_tuning_recovers_nonuniform_curves(nonuniform):
    _, _, result = nonuniform
    cal = result.is_calibration
    calibrated, glob = result.variants["calibrated"], result.variants["global"]
    for experiment in ("indentation", "relaxation"):
        # the fitted curves match the known model's to <= 0.5 % relative RMS
        assert calibrated.errors[experiment][cal].max() <= 5e-3, experiment
        # and local tuning is what gets them there: the uniform model cannot
        assert glob.errors[experiment][cal].mean() > 3 * calibrated.errors[experiment][cal].mean()
    for stage in ("static", "relaxation"):
        sweeps = result.local_sweeps[stage]
        assert sweeps and sweeps[0].accepted and sweeps[0].end_cost < sweeps[0].start_cost
    assert result.evaluations["point_curves"] > 0


def test_params_file_round_trip(nonuniform):
    d, _, result = nonuniform
    back = read_params(d / "params.h5")
    for variant in ("baseline", "global", "calibrated"):
        for name in PARAM_NAMES:
            np.testing.assert_array_equal(getattr(back.connectors[variant], name),
                                          getattr(result.connectors[variant], name))
        for experiment in ("indentation", "relaxation"):
            np.testing.assert_array_equal(back.variants[variant].errors[experiment],
                                          result.variants[variant].errors[experiment])
    assert back.global_params == result.global_params and back.initial == result.initial
    for stage in ("static", "relaxation"):
        a, b = back.global_fits[stage], result.global_fits[stage]
        np.testing.assert_array_equal(a.history.evaluation_cost, b.history.evaluation_cost)
        np.testing.assert_array_equal(a.history.iteration_cost, b.history.iteration_cost)
        for sa, sb in zip(back.local_sweeps[stage], result.local_sweeps[stage], strict=True):
            assert (sa.start_cost, sa.end_cost, sa.halvings) == (sb.start_cost, sb.end_cost,
                                                                 sb.halvings)
            for fa, fb in zip(sa.fits, sb.fits, strict=True):
                np.testing.assert_array_equal(fa.history.evaluation_cost,
                                              fb.history.evaluation_cost)
                assert fa.warnings == fb.warnings
    assert back.warnings == result.warnings
    assert back.reference_fingerprint == result.reference_fingerprint
    assert back.summary() == result.summary()
    assert not checkpoint_path(d / "params.h5").exists()  # removed after success


class Interrupted(Exception):
    pass


class InterruptingBackend:
    """The particle backend, but the n-th static evaluation after the global relaxation
    stage began raises (i.e. inside the local static sweep)."""

    def __init__(self, n: int):
        self.n, self.count, self.relaxation_started = n, 0, False

    def __call__(self, experiments, points, params):
        evaluators = particle_backend(experiments, points, params)
        static, relaxation = evaluators["indentation"], evaluators["relaxation"]

        def indentation(p, pts=None):
            if self.relaxation_started:
                self.count += 1
                if self.count == self.n:
                    raise Interrupted(f"injected interruption at evaluation {self.n}")
            return static(p, pts)

        def relax(p, pts=None):
            self.relaxation_started = True
            return relaxation(p, pts)

        return {"indentation": indentation, "relaxation": relax}


def test_interrupted_calibration_resumes_to_the_same_result(box, nonuniform, tmp_path):
    d, _, reference_run = nonuniform
    out = tmp_path / "params.h5"
    # 1 sweep-start evaluation + point 0's fit (<= 60) + some of the next points'
    with pytest.raises(Interrupted):
        calibrate(box, d / "reference.h5", out, progress=False, backend=InterruptingBackend(75))
    assert not out.exists()
    saved = json.loads(checkpoint_path(out).read_text())["stages"]
    assert {"global_static", "global_relaxation", "local_static"} <= set(saved)
    assert "0" in saved["local_static"]["sweeps"][0]["fits"]
    result = calibrate(box, d / "reference.h5", out, progress=False)
    # same fits; only the particle solver's warm starts differ (Newton rtol 1e-8)
    for name in PARAM_NAMES:
        np.testing.assert_allclose(getattr(result.connectors["calibrated"], name),
                                   getattr(reference_run.connectors["calibrated"], name),
                                   rtol=1e-6)
    assert result.global_params == reference_run.global_params
    # the global stages and point 0's local fit were loaded, not recomputed; an infeasible
    # point (cost +inf) is refused before any curve is computed
    n_cal = len(result.problem.calibration)

    def feasible(fit) -> int:
        return int(np.isfinite(fit.history.evaluation_cost).sum())

    loaded = n_cal * sum(feasible(fit) for fit in result.global_fits.values())
    loaded += n_cal + feasible(result.local_sweeps["static"][0].fits[0])  # sweep start + fit
    assert result.evaluations["point_curves"] == reference_run.evaluations["point_curves"] - loaded
    assert not checkpoint_path(out).exists()


def _local_static(problem: Problem, scene, reference_params, workers: int):
    """Local static sweeps on ``problem`` starting from the true global parameters."""
    from forcecal.schedules import indentation_depths, relaxation_schedule
    times, depths = relaxation_schedule(scene.relaxation)
    exp = Experiments(problem, scene.material.density, indentation_depths(scene.indentation),
                      times, depths, STRAIN.bounds)
    n_cal = len(problem.calibration)
    with Pool(exp, reference_params, workers=workers) as pool:
        reference = pool.curves("indentation", reference_params, np.arange(n_cal))
        model = LocalModel(TRUE_GLOBAL, build_rings(problem.mesh, problem.calibration), STRAIN,
                           scene.calibration.stiffness_floor * TRUE_GLOBAL.K0,
                           np.zeros((n_cal, 3)), np.zeros((n_cal, 4)))
        model, sweeps = run_local_stage(pool, model, "static", reference, scene.calibration,
                                        None, lambda record: None, progress=False)
    return model.params(), sweeps


def test_local_tuning_is_independent_of_point_order_and_workers(box, box_problem, nonuniform):
    _, true, _ = nonuniform
    p = box_problem
    scene = replace(box, calibration={"local_max_sweeps": 1, "local_max_evaluations": 25})
    sorted_run, _ = _local_static(p, scene, true, workers=1)
    order = np.array([2, 0, 3, 1])
    permuted = Problem(p.mesh, p.fixed, p.calibration[order], p.held_out, p.tracked_node)
    permuted_run, _ = _local_static(permuted, scene, true, workers=1)
    parallel_run, sweeps = _local_static(p, scene, true, workers=2)
    assert sweeps[0].end_cost < sweeps[0].start_cost
    # the Jacobi update sees the same per-point problems in any order, on any worker; only the
    # summation order of the total cost differs (round-off)
    for name in PARAM_NAMES:
        np.testing.assert_allclose(getattr(permuted_run, name), getattr(sorted_run, name),
                                   rtol=1e-9)
        np.testing.assert_allclose(getattr(parallel_run, name), getattr(sorted_run, name),
                                   rtol=1e-9)


def test_command_line(nonuniform, tmp_path):
    d, _, _ = nonuniform
    scene = _box_scene(tmp_path, local=False, relaxation_max_evaluations=40)
    out = tmp_path / "params.h5"
    cmd = [sys.executable, "-m", "calibration", "--scene", str(scene.path), "--reference",
           str(d / "reference.h5"), "--out", str(out), "--no-progress", "--workers", "2"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "relative RMS error" in done.stdout and "held-out" in done.stdout
    settings = read_params(out).settings
    assert settings["calibration"] == dataclasses.asdict(scene.calibration)
    assert settings["mesh"] == dataclasses.asdict(scene.mesh) and "particle" not in settings
    bad = subprocess.run(cmd[:6] + [str(tmp_path / "missing.h5")] + cmd[7:], capture_output=True,
                         text=True, cwd=ROOT, timeout=600)
    assert bad.returncode == 2 and "missing.h5 does not exist" in bad.stderr


@pytest.mark.mpi
def test_mpi_ranks_give_the_serial_result(box, nonuniform, tmp_path):
    d, _, reference_run = nonuniform
    out = tmp_path / "params.h5"
    env = {**os.environ, "OMPI_MCA_rmaps_base_oversubscribe": "1"}
    cmd = ["mpirun", "-n", "3", sys.executable, "-m", "calibration", "--scene", str(box.path),
           "--reference", str(d / "reference.h5"), "--out", str(out), "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "MpiTransport" in done.stderr
    result = read_params(out)
    for name in PARAM_NAMES:
        np.testing.assert_allclose(getattr(result.connectors["calibrated"], name),
                                   getattr(reference_run.connectors["calibrated"], name),
                                   rtol=1e-6)
