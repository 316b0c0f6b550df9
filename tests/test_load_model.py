"""``forcecal.load_model``: the calibrated model of a ``params.h5``, ready to run.

The file comes from a real (small) calibration: a box with the viscoelastic volume term,
fitted by the paper's method to a synthetic reference (no FE), so the loaded model must
give back, to the Newton tolerance, the force curves the calibration recorded for it.
"""
import dataclasses
import subprocess
import sys

import h5py
import numpy as np
import pytest

import forcecal
from calibration import calibrate, read_params
from calibration.loading import load_calibrated
from calibration.parametrisation import GlobalParams
from calibration.synthetic import box_scene, synthetic_reference
from forcecal.errors import DataFileError
from forcecal.problem import build_problem
from forcecal.schedules import indentation_depths, relaxation_schedule
from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
from particle.volume import network_bulk_modulus
from tests.conftest import ROOT

TRUTH = GlobalParams(K0=30.0, alpha=1.0, beta=10.0, k1=26.0, tau1=0.5, k2=19.0, tau2=10.0)


def calibrated_box(directory, volume="viscoelastic"):
    """A box scene and the ``params.h5`` of its calibration (global + one local sweep, small
    budgets: about 5 s) against a synthetic reference with the volume term; returns
    (scene, path)."""
    scene = box_scene(directory, test_points={"calibration": "cover", "n_calibration": 4,
                                              "n_held_out": 8},
                      indentation={"depth": 0.002}, relaxation={"depth": 0.002},
                      calibration={"workers": 1, "static_max_evaluations": 40,
                                   "relaxation_max_evaluations": 40,
                                   "local_max_evaluations": 20, "local_max_sweeps": 1},
                      particle={"volume": volume})
    mesh = build_problem(scene).mesh
    kv = network_bulk_modulus(mesh, TRUTH.K0)
    truth = dataclasses.replace(TRUTH, kv=kv, kv1=0.3 * kv if volume == "viscoelastic" else 0,
                                kv2=1.2 * kv if volume == "viscoelastic" else 0)
    synthetic_reference(scene, truth.connector_params(len(mesh.edges)),
                        directory / "reference.h5")
    calibrate(scene, directory / "reference.h5", directory / "params.h5", progress=False)
    return scene, directory / "params.h5"


@pytest.fixture(scope="module")
def box_run(tmp_path_factory):
    return calibrated_box(tmp_path_factory.mktemp("load_model"))


def test_the_loaded_model_is_the_calibrated_one(box_run):
    scene, path = box_run
    model = forcecal.load_model(path)
    result = read_params(path)
    problem, fitted = result.problem, result.connectors["calibrated"]
    mesh = problem.mesh
    assert (model.n_particles, model.n_connectors, model.n_tets) == (
        mesh.n_vertices, len(mesh.edges), mesh.n_tets)
    np.testing.assert_array_equal(model.rest_positions, mesh.vertices)
    np.testing.assert_array_equal(np.nonzero(model.fixed)[0], np.sort(problem.fixed))
    # masses lumped from the scene's density: they add up to the body's mass
    assert model.masses.sum() == pytest.approx(scene.material.density * mesh.signed_volumes.sum(),
                                               rel=1e-12)
    for name in ("K0", "a", "b", "k1", "b1", "k2", "b2"):
        np.testing.assert_array_equal(getattr(model.params, name), getattr(fitted, name))
    assert len(np.unique(model.params.K0)) > 1  # local tuning made them differ
    # the volume term with its arms, the global fit's one value on every tet
    assert model.params.has_volume_arms
    for name in ("kv", "kv1", "bv1", "kv2", "bv2"):
        np.testing.assert_array_equal(getattr(model.params, name),
                                      np.full(mesh.n_tets, getattr(fitted, name)[0]))


def test_the_loaded_model_gives_back_the_curves_the_calibration_recorded(box_run):
    """Its static and relaxation curves at every test point against ``params.h5``'s
    ``curves/calibrated/*`` (the same evaluators, Newton rtol 1e-8: measured within
    2.9e-9 of the largest force; asserted within 1e-7)."""
    scene, path = box_run
    calibrated = load_calibrated(path)
    model, problem = calibrated.model, calibrated.problem
    stored = read_params(path).variants["calibrated"].curves
    strain = calibrated.strain_range
    times, depths = relaxation_schedule(scene.relaxation)
    curves = {
        "indentation": IndentationEvaluator(model, problem.test_points, problem.normals,
                                            indentation_depths(scene.indentation),
                                            strain_range=strain)(model.params),
        "relaxation": RelaxationEvaluator(model, problem.test_points, problem.normals, times,
                                          depths, strain_range=strain)(model.params)}
    for experiment, curve in curves.items():
        want = stored[experiment]
        assert np.abs(curve - want).max() < 1e-7 * np.abs(want).max(), experiment


def test_every_variant_loads_and_the_baseline_has_no_volume_term(box_run):
    _, path = box_run
    result = read_params(path)
    for variant in ("baseline", "global", "calibrated"):
        calibrated = load_calibrated(path, variant)
        assert calibrated.variant == variant and calibrated.source == str(path)
        np.testing.assert_array_equal(calibrated.model.params.K0,
                                      result.connectors[variant].K0)
        assert calibrated.volume == (None if variant == "baseline" else "viscoelastic")
        assert calibrated.strain_range == result.strain.bounds


def test_importing_forcecal_imports_no_model_code():
    code = ("import sys, forcecal; print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'calibration', 'particle', 'numba', 'pipelines', 'h5py'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    assert out.strip() == "[]"
    from calibration.loading import load_model
    assert forcecal.load_model is load_model
    with pytest.raises(AttributeError, match="no attribute 'load_modle'"):
        forcecal.load_modle  # noqa: B018


def _edited(source, target, edit):
    target.write_bytes(source.read_bytes())
    with h5py.File(target, "r+") as fh:
        edit(fh)
    return target


def test_bad_files_and_variants_are_refused_naming_the_problem(box_run, tmp_path):
    _, path = box_run
    with pytest.raises(DataFileError, match="does not exist"):
        forcecal.load_model(tmp_path / "missing.h5")
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"not an HDF5 file" * 10)
    with pytest.raises(DataFileError, match="not a readable HDF5 file"):
        forcecal.load_model(garbage)
    with pytest.raises(DataFileError, match="unknown variant 'fitted'.*baseline, global, "
                                            "calibrated"):
        forcecal.load_model(path, variant="fitted")

    def no_density(fh):
        settings = fh.attrs["settings"].replace('"density": 1060.0', '"density": -1.0')
        fh.attrs["settings"] = settings

    with pytest.raises(DataFileError, match="material.density = -1.0"):
        forcecal.load_model(_edited(path, tmp_path / "density.h5", no_density))

    def no_volume_arms(fh):
        for name in ("kv1", "bv1", "kv2", "bv2"):
            del fh[f"connectors/calibrated/{name}"]

    with pytest.raises(DataFileError, match="volume term 'elastic' but the scene's "
                                            "particle.volume = 'viscoelastic'"):
        forcecal.load_model(_edited(path, tmp_path / "arms.h5", no_volume_arms))

    def no_kv(fh):
        del fh["connectors/calibrated/kv"]

    with pytest.raises(DataFileError, match="arms need kv"):
        forcecal.load_model(_edited(path, tmp_path / "kv.h5", no_kv))

    def short_K0(fh):
        k0 = fh["connectors/calibrated/K0"][()]
        del fh["connectors/calibrated/K0"]
        fh["connectors/calibrated/K0"] = k0[:-1]

    with pytest.raises(DataFileError, match="K0"):
        forcecal.load_model(_edited(path, tmp_path / "short.h5", short_K0))
