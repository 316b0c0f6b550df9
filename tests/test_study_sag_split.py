"""The sag study (studies/sag_split.py): its split ratios, its sag ratio and its rows."""
import dataclasses

import numpy as np
import pytest

from forcecal.errors import ParameterError
from particle.statics import gravity_static
from tests.particle_models import box_model
from calibration.synthetic import box_scene
from forcecal.problem import build_problem
from forcecal.schedules import indentation_depths
from particle.evaluators import IndentationEvaluator
from particle.model import build_model
from studies.sag_split import (DISTANCES, calibration_errors, footprint_distance,
                                       heights, mean_sag_ratio, sag_rows, split_ratios,
                                       variants)
from pipelines.report import gravity_static_error

GRAVITY = np.array([0.0, 0.0, -9.81])


def volume_box():
    """A clamped box, springs + a volume term of 2 kPa on every tet."""
    model = box_model((3, 3, 2), density=1000.0, K0=20.0, a=5.0, b=10.0)
    return model.with_params(dataclasses.replace(model.params, kv=np.full(model.n_tets, 2e3)))


def test_split_ratios_are_the_geometric_means_of_calibrated_over_global():
    """K0 halved on every connector, kv x2 on m tets and x8 on the other n - m: the
    geometric means 0.5 and 2^((m + 3 (n - m))/n)."""
    p = volume_box().params
    n = len(p.kv)
    m = n // 3
    kv = np.where(np.arange(n) < m, 2.0, 8.0) * p.kv
    calibrated = dataclasses.replace(p, K0=0.5 * p.K0, kv=kv)
    got = split_ratios(p, calibrated)
    assert got["K0"] == pytest.approx(0.5, rel=1e-12)
    assert got["kv"] == pytest.approx(2.0 ** ((m + 3 * (n - m)) / n), rel=1e-12)
    assert split_ratios(dataclasses.replace(p, kv=None), dataclasses.replace(p, kv=None))["kv"] \
        is None


def test_mean_sag_ratio_compares_the_sags_along_gravity():
    """Twice the FE's sag along gravity and any sideways motion: ratio 2."""
    fe = np.zeros((4, 3))
    fe[:, 2] = [-1.0, -2.0, -3.0, 0.0]
    particle = 2.0 * fe
    particle[:, 0] = 5.0  # sideways: not counted
    assert mean_sag_ratio(fe, particle, np.array([0, 1, 2]), GRAVITY) == pytest.approx(2.0)


def test_variants_put_back_the_global_values_where_and_what_they_say():
    """Each mix takes exactly its connectors and tets from the global set, and the calibrated
    values elsewhere."""
    model = volume_box()
    cal = model.params
    glob = dataclasses.replace(cal, K0=2.0 * cal.K0, a=2.0 * cal.a, b=2.0 * cal.b,
                               kv=np.full(model.n_tets, 5e3))
    x = model.rest_positions
    ch = heights(x[model.edges].mean(axis=1), GRAVITY)
    th = heights(x[model.tets].mean(axis=1), GRAVITY)
    sets = variants(glob, cal, ch, th, (2.0,))
    assert list(sets) == ["global", "calibrated", "calibrated springs, global kv",
                          "global springs, calibrated kv",
                          "global springs x K0 mean, calibrated kv",
                          "calibrated, global below half height",
                          "calibrated, global above half height", "calibrated, kv x2"]
    assert np.array_equal(sets["calibrated springs, global kv"].K0, cal.K0)
    assert np.all(sets["calibrated springs, global kv"].kv == 5e3)
    assert np.array_equal(sets["global springs, calibrated kv"].K0, glob.K0)
    assert np.array_equal(sets["global springs, calibrated kv"].kv, cal.kv)
    even = sets["global springs x K0 mean, calibrated kv"]  # the level of cal / glob: 0.5
    np.testing.assert_allclose(even.K0, cal.K0, rtol=1e-12)
    np.testing.assert_allclose(even.b, cal.b, rtol=1e-12)
    assert np.array_equal(even.kv, cal.kv)
    middle = 0.5 * (min(ch.min(), th.min()) + max(ch.max(), th.max()))
    below = sets["calibrated, global below half height"]
    assert np.array_equal(below.K0, np.where(ch < middle, glob.K0, cal.K0))
    assert np.array_equal(below.kv, np.where(th < middle, 5e3, cal.kv))
    assert 0 < (ch < middle).sum() < len(ch)  # both halves hold connectors
    assert np.array_equal(sets["calibrated, kv x2"].kv, 2.0 * cal.kv)
    assert heights(np.array([0.0, 0.0, 0.3]), GRAVITY) == pytest.approx(0.3)
    with pytest.raises(ParameterError, match="kv factors"):
        variants(glob, cal, ch, th, (1.0, 0.0))
    # with distances from the footprints: the global values beyond each distance
    cd, td = 0.01 * np.arange(len(ch)) / len(ch) * 5, 0.01 * np.arange(len(th)) / len(th) * 5
    sets = variants(glob, cal, ch, th, (), (cd, td))
    for d in DISTANCES:
        far = sets[f"calibrated, global beyond {1e3 * d:g} mm of the footprints"]
        assert np.array_equal(far.K0, np.where(cd > d, glob.K0, cal.K0))
        assert np.array_equal(far.kv, np.where(td > d, 5e3, cal.kv))
        assert 0 < (cd > d).sum() < len(cd)


def test_footprint_distance_is_the_distance_to_the_nearest_held_particle():
    held = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    points = np.array([[0.0, 3.0, 4.0], [0.9, 0.0, 0.0], [1.0, 0.0, -2.0]])
    np.testing.assert_allclose(footprint_distance(points, held), [5.0, 0.1, 2.0], rtol=1e-12)


def test_calibration_errors_are_the_reports_indentation_errors(tmp_path):
    """The set that made the reference curves fits them exactly; linear springs twice as
    stiff hold the same equilibria with twice the forces, so each point's error is its
    curve's RMS over its largest value."""
    scene = box_scene(tmp_path, test_points={"n_calibration": 3, "n_held_out": 8},
                      indentation={"depth": 0.001})
    problem = build_problem(scene)
    model = box_model((3, 3, 2), density=1000.0, K0=20.0)
    truth = model.params
    stiffer = dataclasses.replace(truth, K0=2.0 * truth.K0)
    depths = indentation_depths(scene.indentation)
    built = build_model(problem, 1000.0, truth)
    reference = IndentationEvaluator(built, problem.test_points[:3], problem.normals[:3],
                                     depths)(truth)
    got = calibration_errors(problem, 1000.0, depths, reference, None, (-0.5, 0.5),
                             {"truth": truth, "stiffer": stiffer})
    assert got["truth"] == 0.0
    rms_over_max = np.sqrt(np.mean(reference ** 2, axis=1)) / np.abs(reference).max(axis=1)
    assert got["stiffer"] == pytest.approx(rms_over_max.mean(), rel=1e-6)


def test_sag_rows_repeat_the_static_sag_and_a_stiffer_kv_sags_less():
    """The calibrated row is the gravity stage's Newton sag itself (error 0 and ratio 1
    against it); scaling kv up makes the body sag less, monotonically."""
    model = volume_box()
    fe = gravity_static(model, GRAVITY)
    sets = {f"kv x{f:g}": dataclasses.replace(model.params, kv=f * model.params.kv)
            for f in (1.0, 2.0, 4.0)}
    rows = sag_rows(model, sets, GRAVITY, fe, (-0.5, 0.5))
    assert [r["label"] for r in rows] == list(sets)
    assert np.array_equal(rows[0]["displacement"], fe)
    assert rows[0]["error"] == 0.0 and rows[0]["mean_sag_ratio"] == pytest.approx(1.0, rel=1e-12)
    ratios = [r["mean_sag_ratio"] for r in rows]
    assert ratios[0] > ratios[1] > ratios[2] > 0.0
    stiffer = gravity_static(model.with_params(sets["kv x2"]), GRAVITY)
    assert rows[1]["error"] == pytest.approx(gravity_static_error(fe, stiffer, model.free_nodes),
                                             rel=1e-12)
