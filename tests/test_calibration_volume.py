"""Calibration method 'paper' with the volume term: kv fitted with K0, a, b (global static fit)."""
import dataclasses

import numpy as np
import pytest

from calibration.core import calibrate
from calibration.results import read_params
from calibration.synthetic import synthetic_reference
from forcecal.errors import DataFileError
from forcecal.problem import build_problem
from forcecal.scene import replace
from particle.volume import network_bulk_modulus
from tests.test_calibration_fit import TRUE_GLOBAL, _box_scene


def test_global_fit_recovers_kv_from_a_uniform_block(tmp_path):
    """A synthetic reference made by the particle model itself (uniform springs + kv = 3 x the
    network's bulk modulus, the initial guess being 1 x) on the box: the global static fit
    (Nelder-Mead over alpha, beta, log kv/K0; K0 in closed form) recovers kv and K0. The
    truth is in the searched family, so the optimum is exact and the fit stops at its
    tolerances: measured kv within 1.4e-5, K0 within 3e-6 (155 evaluations); asserted
    within 1e-3."""
    # a 3-D static search: a larger budget than the springs-only tests' 80
    scene = replace(_box_scene(tmp_path), calibration={"local": False,
                                                       "static_max_evaluations": 200},
                    particle={"volume": True})
    mesh = build_problem(scene).mesh
    kv = 3.0 * network_bulk_modulus(mesh, TRUE_GLOBAL.K0)
    truth = dataclasses.replace(TRUE_GLOBAL, kv=kv)
    synthetic_reference(scene, truth.connector_params(len(mesh.edges)), tmp_path / "ref.h5")
    result = calibrate(scene, tmp_path / "ref.h5", tmp_path / "params.h5", progress=False)
    glob = result.global_params
    # the start: the network's bulk modulus for the K0 of the springs-only slopes
    assert result.initial.kv == pytest.approx(network_bulk_modulus(mesh, result.initial.K0))
    assert glob.kv == pytest.approx(kv, rel=1e-3)
    assert glob.K0 == pytest.approx(TRUE_GLOBAL.K0, rel=1e-3)
    for experiment in ("indentation", "relaxation"):  # calibration and held-out points
        assert result.variants["global"].errors[experiment].max() < 1e-3
    back = read_params(tmp_path / "params.h5")
    assert back.global_params.kv == glob.kv
    assert back.connectors["global"].kv.tolist() == [glob.kv]
    assert back.connectors["baseline"].kv is None  # Van Gelder: springs only
    assert back.settings["model"] == {"particle.volume": True}


def test_global_fit_recovers_the_volume_arms_from_a_uniform_block(tmp_path):
    """``particle.volume = "viscoelastic"``: a synthetic reference with volume arms whose
    ratios differ from the start's (the material's Prony ratios 0.875 / 0.625: here kv1 = 0.3
    kv, kv2 = 1.2 kv). The static fit sees only the long-term kv (recovered as without arms);
    the relaxation fit, over the springs' arms and log(kv_i/kv), recovers the volume arms
    too. The truth is in the searched family: measured kv1 within 6e-4, kv2 within 1e-4, the
    springs' arms within 4e-4 (418 evaluations); asserted within 1e-2 (Nelder-Mead in 6-D
    stops at its tolerances)."""
    scene = replace(_box_scene(tmp_path), calibration={"local": False,
                                                       "static_max_evaluations": 200,
                                                       "relaxation_max_evaluations": 600},
                    particle={"volume": "viscoelastic"})
    mesh = build_problem(scene).mesh
    kv = 3.0 * network_bulk_modulus(mesh, TRUE_GLOBAL.K0)
    truth = dataclasses.replace(TRUE_GLOBAL, kv=kv, kv1=0.3 * kv, kv2=1.2 * kv)
    synthetic_reference(scene, truth.connector_params(len(mesh.edges)), tmp_path / "ref.h5")
    result = calibrate(scene, tmp_path / "ref.h5", tmp_path / "params.h5", progress=False)
    start, glob = result.initial, result.global_params
    assert start.kv1 / start.kv == pytest.approx(0.35 / 0.4)  # the Prony ratios
    assert start.kv2 / start.kv == pytest.approx(0.25 / 0.4)
    for name in ("kv", "K0", "kv1", "kv2", "k1", "tau1", "k2", "tau2"):
        assert getattr(glob, name) == pytest.approx(getattr(truth, name), rel=1e-2), name
    for experiment in ("indentation", "relaxation"):  # calibration and held-out points
        assert result.variants["global"].errors[experiment].max() < 1e-3
    back = read_params(tmp_path / "params.h5")
    assert (back.global_params.kv1, back.global_params.kv2) == (glob.kv1, glob.kv2)
    calibrated = back.connectors["calibrated"]
    assert calibrated.kv1.tolist() == [glob.kv1]
    assert calibrated.bv2.tolist() == [glob.tau2 * glob.kv2]
    assert back.settings["model"] == {"particle.volume": "viscoelastic"}


def test_global_fit_recovers_kv_of_the_nodal_volume_element(tmp_path):
    """``particle.volume_element = "nodal"`` through the whole calibration: the synthetic
    reference, the workers' evaluators, params.h5 (its settings record the element) and the
    model loaded back all use the nodal term. On the box of the per-tet test (same truth: kv
    = 3 x the network's bulk modulus, uniform springs) the nodal curves are those of another
    model (the per-tet model's at the truth differ from them by up to 2x the largest nodal
    force: that model locks), and the global static fit recovers kv and K0 as it does per tet
    (the truth is in the searched family: measured kv within 1.1e-5, K0 within 2.6e-5;
    asserted within 1e-3, the per-tet test's tolerance)."""
    from calibration.loading import calibrated_model
    from particle.model import build_model
    from particle.evaluators import IndentationEvaluator
    scene = replace(_box_scene(tmp_path), calibration={"local": False,
                                                       "static_max_evaluations": 200},
                    particle={"volume": True, "volume_element": "nodal"})
    problem = build_problem(scene)
    kv = 3.0 * network_bulk_modulus(problem.mesh, TRUE_GLOBAL.K0)
    truth = dataclasses.replace(TRUE_GLOBAL, kv=kv)
    params = truth.connector_params(len(problem.mesh.edges))
    ref = synthetic_reference(scene, params, tmp_path / "ref.h5")
    per_tet = IndentationEvaluator(build_model(problem, scene.material.density, params),
                                   problem.test_points, problem.normals,
                                   ref.indentation.displacement)(params)
    nodal = ref.indentation.force_normal
    assert np.abs(per_tet - nodal).max() > 0.5 * np.abs(nodal).max()
    result = calibrate(scene, tmp_path / "ref.h5", tmp_path / "params.h5", progress=False)
    glob = result.global_params
    assert glob.kv == pytest.approx(kv, rel=1e-3)
    assert glob.K0 == pytest.approx(TRUE_GLOBAL.K0, rel=1e-3)
    assert result.variants["global"].errors["indentation"].max() < 1e-3
    back = read_params(tmp_path / "params.h5")
    assert back.settings["model"] == {"particle.volume": True,
                                      "particle.volume_element": "nodal"}
    assert calibrated_model(back, "global").model.volume_element == "nodal"
    edited = dataclasses.replace(back, settings={**back.settings, "model": {
        "particle.volume": True, "particle.volume_element": "hex"}})
    with pytest.raises(DataFileError, match="particle.volume_element = 'hex' is not one of"):
        calibrated_model(edited, "global")
