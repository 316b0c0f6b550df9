"""End-to-end calibration on synthetic references made by the particle model itself:
parameter recovery, order independence, parallel == serial, checkpoint/resume, params.h5,
command line and MPI."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from calibration.core import calibrate, checkpoint_path
from calibration.reach import strain_range
from calibration.local import PHASE_KIND, LocalParametrisation, run_local_phase
from calibration.parametrisation import GlobalParams, StrainRange, build_rings, global_shape
from calibration.metrics import relative_rms_error
from calibration.network import linear_indentation
from calibration.pool import Experiments, Pool, particle_backend
from calibration.provenance import code_fingerprint
from calibration.results import EXPERIMENTS, read_params
from calibration.synthetic import (box_scene, noisy_params, ring_perturbed_params,
                                   synthetic_reference)
from forcecal.h5io import read_reference
from forcecal.problem import Problem, build_problem
from forcecal.scene import replace
from particle.evaluators import normal_force
from particle.params import PARAM_NAMES
from tests.conftest import ROOT

# quick budgets: the box has 4 calibration + 8 held-out points and 197 connectors
SETTINGS = {"static_max_evaluations": 80, "relaxation_max_evaluations": 160,
            "local_max_evaluations": 60, "local_max_sweeps": 3, "local_sweep_tolerance": 1e-4,
            "workers": 1}
TRUE_GLOBAL = GlobalParams(K0=30.0, alpha=1.0, beta=10.0, k1=26.0, tau1=0.5, k2=19.0, tau2=10.0)
STRAIN = StrainRange(-0.2, 0.05)  # what the box's 2 mm indentation reaches (linear estimate)
NOISE = 0.1  # log-normal sigma of the per-connector factors of the non-uniform truth


def _box_scene(directory, **calibration):
    # the paper's cover (+ far points): the recovery levels below were measured on its points
    points = {"calibration": "cover", "n_calibration": 4, "n_held_out": 8}
    return box_scene(directory, test_points=points,
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
    """Reference from per-connector random factors (a form neither tuning phase can represent),
    and the uninterrupted calibration fitted to it."""
    true = noisy_params(TRUE_GLOBAL, len(box_problem.mesh.edges), sigma=NOISE)
    d = box.path.parent / "nonuniform"
    synthetic_reference(box, true, d / "reference.h5")
    result = calibrate(box, d / "reference.h5", d / "params.h5", progress=False)
    return d, true, result


@pytest.fixture(scope="module")
def oracle_errors(box, box_problem, nonuniform):
    """Errors of the truth's own global part (uniform TRUE_GLOBAL) against the non-uniform
    truth at every test point: what the best possible global model gets wrong."""
    d, _, _ = nonuniform
    uniform = synthetic_reference(box, TRUE_GLOBAL.connector_params(len(box_problem.mesh.edges)),
                                  d / "uniform.h5")
    truth = read_reference(d / "reference.h5")
    return {e: relative_rms_error(getattr(uniform, e).force_normal, getattr(truth, e).force_normal)
            for e in EXPERIMENTS}


def _reached(problem: Problem, depth: float) -> StrainRange:
    """The strains the experiments reach (linear network at ``depth``, no margin)."""
    lin = linear_indentation(problem.mesh, problem.fixed, problem.test_points, problem.normals)
    return strain_range(lin.strain, depth, 1.0)


def _spring_error(got, want, strain: StrainRange) -> np.ndarray:
    """(E,) per connector, max over ``strain`` of |K_got(eps) / K_want(eps) - 1|."""
    eps = np.linspace(strain.low, strain.high, 101)
    K = lambda p: p.K0[:, None] + p.a[:, None] * eps + p.b[:, None] * eps ** 2  # noqa: E731
    return np.max(np.abs(K(got) / K(want) - 1.0), axis=1)


def _tau_error(got, want) -> np.ndarray:
    return np.abs(np.concatenate([(got.b1 / got.k1) / (want.b1 / want.k1),
                                  (got.b2 / got.k2) / (want.b2 / want.k2)]) - 1.0)


def test_global_fit_recovers_uniform_parameters(box, box_problem, tmp_path):
    scene = replace(box, calibration={"local": False})
    true = TRUE_GLOBAL.connector_params(len(box_problem.mesh.edges))
    synthetic_reference(scene, true, tmp_path / "reference.h5")
    result = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5", progress=False)
    got, want = result.global_params.as_dict(), TRUE_GLOBAL.as_dict()
    # the truth is in the searched family, so its global parameters are the exact optimum and
    # the fit stops at the tolerances: measured K0, the arms and the relaxation times within
    # 2e-5, alpha and beta (which trade off along a weakly determined direction, see below)
    # within 1.2e-3, the spring law K(eps) over the strains reached within 6e-5, every test
    # point's curves within 1e-5; asserted with 10-50x margins
    for k in ("K0", "k1", "tau1", "k2", "tau2"):
        assert got[k] == pytest.approx(want[k], rel=1e-3), k
    for k in ("alpha", "beta"):
        assert got[k] == pytest.approx(want[k], rel=1e-2), k
    reached = _reached(box_problem, 0.002)
    assert _spring_error(result.connectors["global"], true, reached).max() < 1e-3
    for experiment in ("indentation", "relaxation"):  # calibration and held-out points
        assert result.variants["global"].errors[experiment].max() < 1e-4
    assert not result.local_sweeps["static"] and not result.local_sweeps["relaxation"]


def test_calibration_recovers_nonuniform_parameters(nonuniform, oracle_errors):
    """Every connector's K0, k_i and tau_i carries its own random factor (sigma 0.1): neither
    one global set nor ring offsets can represent that, and 4 curves cannot identify 197
    connectors, so what can be recovered is (a) the calibration curves, (b) the global
    parameters as the central values of the factors, (c) the held-out curves to the accuracy
    the truth's own global part has there (the factors shift each point's curve by up to 6 %,
    which no model fitted elsewhere can know; measured: calibrated 1.9 % / 1.5 % mean against
    1.7 % / 1.3 % for the truth's global part, indentation / relaxation).

    alpha and beta are not asserted one by one: in the static coordinates (alpha s, beta s^2)
    the direction (0.50, 0.86) moves the box's curves by only 0.5 % RMS per unit (condition
    number 93 of the sensitivities of (log K0, alpha s, beta s^2)), so any misfit of the
    global model slides them along it: here alpha x3.6 and beta x2.4 while the global
    model's curves stay within 1.6 % (mean). K0 moves with them (+6.5 %)."""
    _, true, result = nonuniform
    cal = result.is_calibration
    calibrated, glob = result.variants["calibrated"], result.variants["global"]
    g, t = result.global_params.as_dict(), TRUE_GLOBAL.as_dict()
    for experiment in ("indentation", "relaxation"):
        # (a) the fitted curves match the known model's to <= 0.5 % relative RMS
        assert calibrated.errors[experiment][cal].max() <= 5e-3, experiment
        # and local tuning is what gets them there: the uniform model cannot
        assert glob.errors[experiment][cal].mean() > 3 * calibrated.errors[experiment][cal].mean()
        # (c) held-out points, never fitted, against the truth's global part there
        held_out, oracle = calibrated.errors[experiment][~cal], oracle_errors[experiment][~cal]
        assert held_out.mean() <= 1.5 * oracle.mean(), experiment
    # (b) measured: K0 +6.5 %, the arms and times within 5.4 %
    for k in ("K0", "k1", "tau1", "k2", "tau2"):
        assert g[k] == pytest.approx(t[k], rel=0.1), k
    for phase in ("static", "relaxation"):
        sweeps = result.local_sweeps[phase]
        assert sweeps and sweeps[0].accepted and sweeps[0].end_cost < sweeps[0].start_cost


def test_local_tuning_recovers_ring_parameters_given_the_global_part(box, box_problem):
    """A truth of exactly the searched form (global values times ring factors x0.74..x1.35,
    alpha/beta shifted too) and local tuning started from its global part: the ring offsets
    are then identified, connector by connector.

    Started from global tuning instead, the global phase absorbs the calibration points' ring
    factors into its one set (alpha 15.6 and beta 157 for 1 and 10, K0 +26 %: the weak
    direction of the docstring above), and the rings then compensate for that: the curves
    match to 0.4 % but ring springs differ by up to 18 % and held-out curves by up to 7 %.
    Hence the end-to-end case above uses a truth whose global part global tuning recovers.
    """
    true, _, _ = ring_perturbed_params(box_problem, TRUE_GLOBAL, STRAIN)
    got, _, errors = _local_phases(box_problem, box, true, 1, ("static", "relaxation"))
    reached = _reached(box_problem, 0.002)
    # measured: K(eps) <= 1.1 % over the strains reached, K0 <= 0.15 %, k_i and tau_i <= 1.1 %,
    # every test point's curves (held-out included) <= 0.02 %
    assert _spring_error(got, true, reached).max() < 3e-2
    np.testing.assert_allclose(got.K0, true.K0, rtol=5e-3)
    np.testing.assert_allclose(got.k1, true.k1, rtol=3e-2)
    np.testing.assert_allclose(got.k2, true.k2, rtol=3e-2)
    assert _tau_error(got, true).max() < 3e-2
    for experiment, error in errors.items():
        assert error.max() < 5e-4, experiment


def test_local_tuning_recovers_punch_ring_parameters(tmp_path):
    """The same recovery with a flat punch (radius 21 mm on 20 mm cells: the centre and its 4
    or 6 top-face neighbours held) on a 4 x 4 x 2 box: each point's ring is the connectors
    leaving its footprint, the only ones its curves constrain (its first ring lies inside the
    footprint and moves rigidly). Measured: K(eps) <= 5.1 % over the strains reached, K0
    <= 2.9 %, k_i <= 0.9 %, tau_i <= 4.3 %, every test point's curves <= 0.19 %; the punch's
    smaller strains (2 mm depth spread over 5 particles) leave alpha/beta less determined than
    at a vertex."""
    from forcecal.indenter import indenter_footprints
    scene = box_scene(tmp_path, cells=(4, 4, 2), size=(0.08, 0.08, 0.02),
                      test_points={"calibration": [20, 26, 50, 56],  # top face, off the clamp
                                   "held_out": [23, 38, 41, 35, 53, 8, 32, 44]},
                      indentation={"depth": 0.002, "indenter": "punch", "radius": 0.021},
                      relaxation={"depth": 0.002}, calibration=SETTINGS)
    problem = build_problem(scene)
    footprints = indenter_footprints(problem.mesh, problem.fixed, problem.test_points,
                                     problem.normals, "punch", 0.021)
    n_cal = len(problem.calibration)
    true, _, _ = ring_perturbed_params(problem, TRUE_GLOBAL, STRAIN,
                                       footprints=footprints[:n_cal])
    got, _, errors = _local_phases(problem, scene, true, 1, ("static", "relaxation"),
                                   footprints)
    lin = linear_indentation(problem.mesh, problem.fixed, problem.test_points, problem.normals,
                             footprints=footprints)
    reached = strain_range(lin.strain, 0.002, 1.0)
    assert _spring_error(got, true, reached).max() < 8e-2
    np.testing.assert_allclose(got.K0, true.K0, rtol=5e-2)
    np.testing.assert_allclose(got.k1, true.k1, rtol=2e-2)
    np.testing.assert_allclose(got.k2, true.k2, rtol=2e-2)
    assert _tau_error(got, true).max() < 7e-2
    for experiment, error in errors.items():
        assert error.max() < 4e-3, experiment


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
            # the curves are the force vectors' inward-normal components, to every digit
            forces = back.variants[variant].forces[experiment]
            np.testing.assert_array_equal(forces, result.variants[variant].forces[experiment])
            np.testing.assert_array_equal(normal_force(forces, back.problem.normals),
                                          back.variants[variant].curves[experiment])
    assert back.global_params == result.global_params and back.initial == result.initial
    for phase in ("static", "relaxation"):
        a, b = back.global_fits[phase], result.global_fits[phase]
        np.testing.assert_array_equal(a.history.evaluation_cost, b.history.evaluation_cost)
        np.testing.assert_array_equal(a.history.iteration_cost, b.history.iteration_cost)
        for sa, sb in zip(back.local_sweeps[phase], result.local_sweeps[phase], strict=True):
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


def _assert_same_fit(result, reference_run) -> None:
    """The same fits as ``reference_run`` to round-off (1e-10 relative): the
    evaluators forget their warm starts wherever calibration checkpoints, so a resumed run
    makes the same evaluations as an uninterrupted one."""
    for variant in ("global", "calibrated"):
        for name in PARAM_NAMES:
            np.testing.assert_allclose(getattr(result.connectors[variant], name),
                                       getattr(reference_run.connectors[variant], name),
                                       rtol=1e-10, atol=0.0)
    for variant, curves in reference_run.variants.items():
        for e, error in curves.errors.items():
            np.testing.assert_allclose(result.variants[variant].errors[e], error, rtol=1e-10)


class Interrupted(Exception):
    pass


class InterruptingBackend:
    """The particle backend, but the n-th static evaluation after the global relaxation
    phase began raises (i.e. inside the local static sweep)."""

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

        # forgetting warm starts where calibration checkpoints is what makes a resumed run
        # repeat an uninterrupted one, and the Nelder-Mead fits' Newton tolerance is part of
        # the result: the wrappers forward both
        indentation.forget, relax.forget = static.forget, relaxation.forget
        indentation.set_tolerance, relax.set_tolerance = (static.set_tolerance,
                                                          relaxation.set_tolerance)
        return {"indentation": indentation, "relaxation": relax}


def test_interrupted_calibration_resumes_to_the_same_result(box, nonuniform, tmp_path,
                                                            monkeypatch):
    d, _, reference_run = nonuniform
    # the code does not change between the two runs (in a working tree others edit, it may)
    code = code_fingerprint()
    monkeypatch.setattr("calibration.provenance.code_fingerprint", lambda: code)
    out = tmp_path / "params.h5"
    # 1 sweep-start evaluation + point 0's fit (~20) + some of the next points'
    with pytest.raises(Interrupted):
        calibrate(box, d / "reference.h5", out, progress=False, backend=InterruptingBackend(75))
    assert not out.exists()
    saved = json.loads(checkpoint_path(out).read_text())["stages"]
    assert {"global_static", "global_relaxation", "local_static"} <= set(saved)
    assert "0" in saved["local_static"]["sweeps"][0]["fits"]
    result = calibrate(box, d / "reference.h5", out, progress=False)
    _assert_same_fit(result, reference_run)
    assert result.global_params == reference_run.global_params
    # the global phases and the local fits done before the interruption (point 0's and
    # maybe more) were loaded, not recomputed; an infeasible point (cost +inf) is refused
    # before any curve is computed
    n_cal = len(result.problem.calibration)

    def feasible(fit) -> int:
        return int(np.isfinite(fit.history.evaluation_cost).sum())

    loaded = n_cal * sum(feasible(fit) for fit in result.global_fits.values())
    done = [int(j) for j in saved["local_static"]["sweeps"][0]["fits"]]
    loaded += n_cal + sum(feasible(result.local_sweeps["static"][0].fits[j]) for j in done)
    assert result.evaluations["point_curves"] == reference_run.evaluations["point_curves"] - loaded
    assert not checkpoint_path(out).exists()


def _local_phases(problem: Problem, scene, reference_params, workers: int,
                  phases: tuple[str, ...], footprints=None):
    """The local ``phases`` of ``problem`` fitted in turn to ``reference_params``' curves,
    starting from the true global parameters with zero ring offsets (``footprints``: the
    test points' punch footprints, None for the vertex indenter).

    Returns the fitted parameters, the last phase's sweeps and the relative errors of the
    fitted curves at every test point."""
    from forcecal.schedules import indentation_depths, relaxation_schedule
    times, depths = relaxation_schedule(scene.relaxation)
    exp = Experiments(problem, scene.material.density, indentation_depths(scene.indentation),
                      times, depths, STRAIN.bounds, footprints)
    n_cal = len(problem.calibration)
    rings = build_rings(problem.mesh, problem.calibration,
                        None if footprints is None else footprints[:n_cal])
    local = LocalParametrisation(TRUE_GLOBAL, rings,
                                 STRAIN, scene.calibration.stiffness_floor * TRUE_GLOBAL.K0,
                                 np.zeros((n_cal, 3)), np.zeros((n_cal, 4)))
    everything = np.arange(len(problem.test_points))
    with Pool(exp, reference_params, workers=workers) as pool:
        for phase in phases:
            reference = pool.curves(PHASE_KIND[phase], reference_params, np.arange(n_cal))
            local, sweeps = run_local_phase(pool, local, phase, reference, scene.calibration,
                                            None, lambda record: None, progress=False)
        errors = {e: relative_rms_error(pool.curves(e, local.params(), everything),
                                        pool.curves(e, reference_params, everything))
                  for e in EXPERIMENTS}
    return local.params(), sweeps, errors


def _cli(scene_path, reference, out, *extra) -> list[str]:
    return [sys.executable, "-m", "calibration", "--scene", str(scene_path), "--reference",
            str(reference), "--out", str(out), "--no-progress", *extra]


def _cost_evaluations(result) -> dict[str, int]:
    return {k: v for k, v in result.evaluations.items() if k.endswith("_cost_evaluations")}


def test_killed_command_line_run_resumes_to_the_same_result(box, nonuniform, tmp_path):
    """SIGKILL the whole process group (master + 2 worker processes) once the local relaxation
    phase has checkpointed its first point fit, rerun the same command, compare."""
    d, _, reference_run = nonuniform
    out = tmp_path / "params.h5"
    cmd = _cli(box.path, d / "reference.h5", out, "--workers", "2")
    saved = checkpoint_path(out)
    with open(tmp_path / "killed.log", "w") as log:
        run = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=log, start_new_session=True)
        try:
            phases, reached = {}, False
            deadline = time.monotonic() + 300  # a hang guard, not a timing assert
            while not reached and run.poll() is None and time.monotonic() < deadline:
                if saved.exists():  # written atomically: never half a file
                    phases = json.loads(saved.read_text())["stages"]
                    sweeps = phases.get("local_relaxation", {}).get("sweeps", [])
                    reached = bool(sweeps and sweeps[0]["fits"])
                time.sleep(0.02)
            reached = reached and run.poll() is None
        finally:
            os.killpg(run.pid, signal.SIGKILL)  # the run's own session: master and workers
            run.wait()
    assert reached, (tmp_path / "killed.log").read_text()[-3000:]
    assert run.returncode == -signal.SIGKILL and not out.exists()
    assert {"global_static", "global_relaxation", "local_static"} <= set(phases)
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "resuming from checkpoint" in done.stderr
    result = read_params(out)
    _assert_same_fit(result, reference_run)
    assert result.global_params == reference_run.global_params
    assert _cost_evaluations(result) == _cost_evaluations(reference_run)
    # the finished work was loaded, not recomputed
    assert result.evaluations["point_curves"] < reference_run.evaluations["point_curves"]
    assert not saved.exists()


@pytest.mark.parametrize("phase", ["static", "relaxation"])
def test_local_tuning_is_independent_of_point_order_and_workers(box, box_problem, nonuniform,
                                                                phase):
    _, true, _ = nonuniform
    p = box_problem
    # tolerance 0: both sweeps run, so the second sweep's per-point starts (simplex sizes
    # from the first sweep's corrections, fatol scales) are exercised in every order too
    scene = replace(box, calibration={"local_max_sweeps": 2, "local_max_evaluations": 25,
                                      "local_sweep_tolerance": 0.0})
    sorted_run, sweeps, _ = _local_phases(p, scene, true, 1, (phase,))
    order = np.array([2, 0, 3, 1])
    permuted = Problem(p.mesh, p.fixed, p.calibration[order], p.held_out, p.tracked_node)
    permuted_run, _, _ = _local_phases(permuted, scene, true, 1, (phase,))
    parallel_run, _, _ = _local_phases(p, scene, true, 2, (phase,))
    assert len(sweeps) == 2 and all(s.accepted and s.end_cost < s.start_cost for s in sweeps)
    # the Jacobi update sees the same per-point problems in any order, on any worker (a
    # connector's mean over its rings is summed in vertex order; only the total cost's sum
    # differs, which decides nothing here). Identical arithmetic gives identical results; a
    # round-off difference anywhere (a BLAS reduction of another memory alignment in a fresh
    # worker process) can move a Newton iteration across its stopping test, a curve by up to
    # its tolerance (1e-8 of the force), and the fits with it: measured, the reference
    # curves' K0 times 1 + 1e-15 moved these parameters by 6.6e-10 (static) and 1.6e-9
    # (relaxation; a run under load once differed by 1.7e-9). Hence 1e-8, the curves' own
    # tolerance.
    for name in PARAM_NAMES:
        np.testing.assert_allclose(getattr(permuted_run, name), getattr(sorted_run, name),
                                   rtol=1e-8)
        np.testing.assert_allclose(getattr(parallel_run, name), getattr(sorted_run, name),
                                   rtol=1e-8)


def test_command_line(nonuniform, tmp_path):
    d, _, _ = nonuniform
    scene = _box_scene(tmp_path, local=False, relaxation_max_evaluations=40)
    out = tmp_path / "params.h5"
    cmd = _cli(scene.path, d / "reference.h5", out, "--workers", "2")
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
    cmd = ["mpirun", "-n", "3", *_cli(box.path, d / "reference.h5", out)]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "MpiTransport" in done.stderr
    result = read_params(out)
    _assert_same_fit(result, reference_run)


def test_punch_calibration_recovers_uniform_parameters(tmp_path):
    """A scene with ``indenter = "punch"``: the reference holds every particle of each
    footprint (5 on this grid) and so does the calibration, which recovers the parameters."""
    scene = box_scene(tmp_path, cells=(4, 4, 3), size=(0.08, 0.08, 0.03),
                      test_points={"n_calibration": 4, "n_held_out": 8,
                                   "calibration": [27, 35, 67, 75],
                                   "held_out": [11, 31, 43, 47, 51, 55, 59, 71]},
                      indentation={"depth": 0.002, "indenter": "punch", "radius": 0.02},
                      relaxation={"depth": 0.002}, calibration={**SETTINGS, "local": False})
    problem = build_problem(scene)
    assert np.allclose(problem.mesh.vertices[problem.test_points, 2], 0.03)  # the top face
    true = TRUE_GLOBAL.connector_params(len(problem.mesh.edges))
    reference = synthetic_reference(scene, true, tmp_path / "reference.h5")
    vertex = synthetic_reference(replace(scene, indentation={"indenter": "vertex", "radius": 0.0}),
                                 true, tmp_path / "vertex.h5")
    # a punch of 5 particles pushes back much harder than its centre alone
    assert np.all(reference.indentation.force_normal > 2 * vertex.indentation.force_normal)
    result = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5", progress=False)
    got, want = result.global_params.as_dict(), TRUE_GLOBAL.as_dict()
    for k in ("K0", "k1", "tau1", "k2", "tau2"):
        assert got[k] == pytest.approx(want[k], rel=1e-3), k
    for experiment in ("indentation", "relaxation"):
        assert result.variants["global"].errors[experiment].max() < 1e-4


def test_global_fit_with_van_gelder_shape_recovers_a_shaped_truth(box, box_problem, tmp_path):
    """``calibration.global_shape = "van_gelder"``: the global set is one value per parameter
    spread over the connectors by Van Gelder's geometric weights. A truth of that form is
    recovered as exactly as a uniform truth by the uniform fit (above); the uniform fit cannot
    represent it."""
    mesh = box_problem.mesh
    shape = global_shape(mesh, "van_gelder")
    assert shape.mean() == pytest.approx(1.0, rel=1e-12)
    assert shape.max() / shape.min() > 3.0  # the box's edges differ: a test of the shape
    true = TRUE_GLOBAL.connector_params(len(mesh.edges), shape)
    np.testing.assert_allclose(true.K0, TRUE_GLOBAL.K0 * shape, rtol=1e-14)
    np.testing.assert_allclose(true.b1 / true.k1, TRUE_GLOBAL.tau1, rtol=1e-14)
    synthetic_reference(box, true, tmp_path / "reference.h5")
    fits = {}
    for name in ("van_gelder", "uniform"):
        scene = replace(box, calibration={"local": False, "global_shape": name})
        fits[name] = calibrate(scene, tmp_path / "reference.h5", tmp_path / f"{name}.h5",
                               progress=False)
    # measured: K0 within 1e-7, the arms and times within 5e-5, alpha and beta 3e-4, K(eps)
    # over the strains reached 1.5e-5, every curve 3e-6 (as the uniform truth above); the
    # uniform fit's best curves are 72 % (indentation) and 60 % (relaxation) off at worst
    got = fits["van_gelder"].global_params.as_dict()
    for k in ("K0", "k1", "tau1", "k2", "tau2"):
        assert got[k] == pytest.approx(TRUE_GLOBAL.as_dict()[k], rel=1e-3), k
    reached = _reached(box_problem, 0.002)
    assert _spring_error(fits["van_gelder"].connectors["global"], true, reached).max() < 1e-3
    shaped, uniform = fits["van_gelder"].variants["global"], fits["uniform"].variants["global"]
    for experiment in ("indentation", "relaxation"):
        assert shaped.errors[experiment].max() < 1e-4
        assert uniform.errors[experiment].max() > 0.1, experiment
