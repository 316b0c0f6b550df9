"""Bad input to the calibration: every case is a clear ForcecalError naming the problem, or a
warning recorded in the result and in params.h5 -- never a silent success."""
import dataclasses
import json

import h5py
import numpy as np
import pytest

from calibration.core import calibrate, checkpoint_path
from calibration.pool import particle_backend
from calibration.results import read_params
from calibration.synthetic import box_scene, synthetic_reference
from forcecal.errors import DataFileError, MeshError
from forcecal.h5io import read_reference, write_reference
from forcecal.problem import build_problem
from forcecal.scene import replace
from particle.params import ConnectorParams

TABLES = dict(test_points={"n_calibration": 4, "n_held_out": 8},
              indentation={"depth": 0.002}, relaxation={"depth": 0.002},
              calibration={"local": False, "workers": 1})


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    scene = box_scene(d, **TABLES)
    n = len(build_problem(scene).mesh.edges)
    params = ConnectorParams.uniform(n, K0=30.0, k1=26.0, b1=13.0, k2=19.0, b2=190.0)
    synthetic_reference(scene, params, d / "reference.h5")
    return scene, d / "reference.h5"


def _run(scene, reference, tmp_path):
    return calibrate(scene, reference, tmp_path / "params.h5", progress=False)


def test_missing_corrupt_and_nan_references(case, tmp_path):
    scene, reference = case
    with pytest.raises(DataFileError, match="does not exist"):
        _run(scene, tmp_path / "nope.h5", tmp_path)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(reference.read_bytes()[:3000])
    with pytest.raises(DataFileError, match="not a readable HDF5 file"):
        _run(scene, truncated, tmp_path)
    nan = tmp_path / "nan.h5"
    nan.write_bytes(reference.read_bytes())
    with h5py.File(nan, "a") as fh:
        fh["indentation/force_normal"][1, 3] = np.nan
    with pytest.raises(DataFileError, match="indentation/force_normal contains 1 NaN"):
        _run(scene, nan, tmp_path)
    nan.write_bytes(reference.read_bytes())
    with h5py.File(nan, "a") as fh:
        fh["relaxation/force_normal"][2, 5] = np.nan
    with pytest.raises(DataFileError, match="relaxation/force_normal contains 1 NaN"):
        _run(scene, nan, tmp_path)
    assert not (tmp_path / "params.h5").exists()


def test_reference_of_another_scene_is_refused(case, tmp_path):
    scene, reference = case
    other_mesh = box_scene(tmp_path / "other", cells=(3, 2, 2), **TABLES)
    with pytest.raises(DataFileError, match="different mesh"):
        _run(other_mesh, reference, tmp_path)
    with pytest.raises(DataFileError, match="held_out nodes differ"):
        _run(replace(scene, test_points={"n_held_out": 9}), reference, tmp_path)
    with pytest.raises(DataFileError, match="indentation/displacement does not match"):
        _run(replace(scene, indentation={"depth": 0.003}), reference, tmp_path)
    with pytest.raises(DataFileError, match="another material") as info:
        _run(replace(scene, material={"C10": 2500.0}), reference, tmp_path)
    # the key that differs, with both values; not the whole sections
    assert "material.C10 = 2000.0 (scene: 2500.0)" in str(info.value)
    assert "MaterialSection" not in str(info.value) and "C01" not in str(info.value)
    # curves of another FE discretisation are another target
    ref = read_reference(reference)
    p2 = tmp_path / "p2.h5"
    write_reference(p2, dataclasses.replace(ref, fe=scene.fe))
    with pytest.raises(DataFileError, match="fe.element = 'P2' \\(scene: 'TH'\\)"):
        _run(replace(scene, fe={"element": "TH"}), p2, tmp_path)


def test_fixed_calibration_point_is_refused(case, tmp_path):
    scene, reference = case
    fixed = int(build_problem(scene).fixed[0])
    with pytest.raises(MeshError, match=f"test point\\(s\\) \\[{fixed}\\] are fixed nodes"):
        _run(replace(scene, test_points={"calibration": [fixed, 47]}), reference, tmp_path)


def test_forces_of_the_wrong_sign_are_refused(case, tmp_path):
    scene, reference = case
    ref = read_reference(reference)
    flipped = tmp_path / "flipped.h5"
    write_reference(flipped, type(ref)(
        problem=ref.problem, material=ref.material, gravity=None,
        indentation=type(ref.indentation)(ref.indentation.displacement, -ref.indentation.force,
                                          -ref.indentation.force_normal),
        relaxation=ref.relaxation))
    node = int(ref.problem.test_points[0])
    with pytest.raises(DataFileError, match=f"indentation force of test point\\(s\\) \\[{node},"):
        _run(scene, flipped, tmp_path)


def test_exhausted_budgets_are_recorded_as_warnings(case, tmp_path):
    scene, reference = case
    starved = replace(scene, calibration={"static_max_evaluations": 3,
                                          "relaxation_max_evaluations": 4})
    result = _run(starved, reference, tmp_path)
    budget = [w for w in result.warnings if "stopped at its budget" in w]
    assert any(w.startswith("global static fit") for w in budget)
    assert any(w.startswith("global relaxation fit") for w in budget)
    assert not result.global_fits["static"].converged
    assert read_params(tmp_path / "params.h5").warnings == result.warnings
    assert "warning: global static fit" in result.summary()


def test_a_damaged_params_file_is_refused_naming_what_is_wrong(case, tmp_path):
    """Attributes that are not JSON, missing attributes and missing groups of params.h5 are
    DataFileErrors naming the file and the entry, not a JSONDecodeError or KeyError."""
    scene, reference = case
    good = tmp_path / "params.h5"
    _run(scene, reference, tmp_path)
    assert read_params(good).settings["calibration"]["local"] is False
    damaged = tmp_path / "damaged.h5"

    def refused(edit, match):
        damaged.write_bytes(good.read_bytes())
        with h5py.File(damaged, "a") as fh:
            edit(fh)
        with pytest.raises(DataFileError, match=match):
            read_params(damaged)

    refused(lambda fh: fh.attrs.__setitem__("settings", "{not json"),
            r"damaged.h5:/ attribute 'settings' = '\{not json' is not JSON")
    refused(lambda fh: fh.attrs.__delitem__("wall_time"), "attribute 'wall_time' is missing")
    refused(lambda fh: fh["history/global_static"].attrs.__setitem__("warnings", "[oops"),
            "history/global_static attribute 'warnings'.*is not JSON")
    refused(lambda fh: fh.__delitem__("strain_range"),
            "damaged.h5: .*strain_range.*a group or attribute of the forcecal.params schema "
            "is missing")


def constant_backend(experiments, points, params):
    """Evaluators whose curves do not depend on the parameters: no optimiser can gain."""
    def constant(samples):
        return lambda params, pts=None: np.full((len(pts), samples), 1e-3)
    return {"indentation": constant(len(experiments.depths)),
            "relaxation": constant(len(experiments.times))}


def test_an_optimiser_that_cannot_reduce_the_cost_is_reported(case, tmp_path):
    scene, reference = case
    flat = replace(scene, calibration={"local": True, "local_max_evaluations": 20,
                                       "local_max_sweeps": 2})
    result = calibrate(flat, reference, tmp_path / "params.h5", progress=False,
                       backend=constant_backend)
    expected = ["global static fit: Nelder-Mead did not reduce the cost",
                "global relaxation fit: Nelder-Mead did not reduce the cost",
                "local static phase: fits that did not reduce their cost: sweep 1 4/4",
                "local static sweep 1: no damped Jacobi update lowered the total cost",
                "local relaxation phase: fits that did not reduce their cost: sweep 1 4/4",
                "local relaxation sweep 1: no damped Jacobi update lowered the total cost"]
    for start in expected:
        assert any(w.startswith(start) for w in result.warnings), start
    # a rejected first sweep ends the phase
    assert [len(result.local_sweeps[s]) for s in ("static", "relaxation")] == [1, 1]
    back = read_params(tmp_path / "params.h5")
    assert back.warnings == result.warnings
    # evaluators without force_vectors: the curves are validated, no forces stored
    shape = read_reference(reference).indentation.force_normal.shape
    for variants in (result.variants, back.variants):
        assert all(v.forces is None and v.curves["indentation"].shape == shape
                   for v in variants.values())


class Interrupted(Exception):
    pass


def interrupted_at_third_relaxation(experiments, points, params):
    """The particle backend, raising at its third relaxation evaluation (global phase 2)."""
    evaluators = particle_backend(experiments, points, params)
    calls = []

    def relaxation(p, pts=None):
        calls.append(1)
        if len(calls) == 3:
            raise Interrupted("injected interruption")
        return evaluators["relaxation"](p, pts)

    return {"indentation": evaluators["indentation"], "relaxation": relaxation}


def test_a_checkpoint_of_other_code_is_discarded(case, tmp_path, monkeypatch, caplog):
    scene, reference = case
    fresh = _run(scene, reference, tmp_path / "fresh")
    out = tmp_path / "params.h5"
    with pytest.raises(Interrupted):
        calibrate(scene, reference, out, progress=False, backend=interrupted_at_third_relaxation)
    assert "global_static" in json.loads(checkpoint_path(out).read_text())["stages"]
    monkeypatch.setattr("calibration.provenance.code_fingerprint", lambda: "edited code")
    result = _run(scene, reference, tmp_path)
    assert (f"discarding checkpoint {checkpoint_path(out)}: code changed since it was written"
            in caplog.text)
    # nothing was loaded: the global static fit was computed again
    assert result.evaluations == fresh.evaluations


def test_a_depth_that_collapses_connectors_is_refused_before_any_fe_naming_the_key(tmp_path):
    """The calibration's limit on the depths (the linear network's largest compression x
    calibration.strain_margin below 100 %) needs the mesh only: the pipeline refuses such a
    scene before the FE reference starts, naming the keys over the limit and the limit. On the
    box with margin 3 the limit is 5.35 mm (1.5: 10.7 mm, beyond half its mean edge)."""
    from calibration.reach import check_experiment_depths
    from forcecal.errors import SceneError
    from pipelines.stages import run_pipeline

    deep = box_scene(tmp_path, test_points={"n_calibration": 4, "n_held_out": 8},
                     indentation={"depth": 0.006}, relaxation={"depth": 0.004},
                     calibration={"strain_margin": 3.0})
    with pytest.raises(SceneError, match=r"^indentation\.depth = 0\.006 m: indenting 0\.006 m "
                       r"compresses connectors by 1\.12 \(linear estimate of the connector "
                       r"network x calibration\.strain_margin 3; connector .*\): they would "
                       r"collapse\. Set indentation\.depth below 0\.00535 m, the largest depth "
                       r"this mesh accepts$"):
        check_experiment_depths(deep)
    both = replace(deep, relaxation={"depth": 0.006})
    with pytest.raises(SceneError, match="Set indentation.depth and relaxation.depth below"):
        check_experiment_depths(both)
    no_relaxation = replace(both, experiments=["indentation"])
    with pytest.raises(SceneError, match="Set indentation.depth below"):
        check_experiment_depths(no_relaxation)
    # just below the limit the strain range is the calibration's: 99.x % compression
    fine = replace(deep, indentation={"depth": 0.0053})
    assert -1.0 < check_experiment_depths(fine).strain.low < -0.99
    # the pipeline stops at its first stage, before any FE work item
    with pytest.raises(SceneError, match="indentation.depth = 0.006 m"):
        run_pipeline(deep, tmp_path / "run", until="reference", progress=False)
    assert not (tmp_path / "run" / "reference.h5").exists()
    assert not (tmp_path / "run" / "reference.h5.parts").exists()
