"""The sag trade-off diagnostic (studies/sag_tradeoff.py): its regions, its scalings,
its constrained Gauss-Newton step, and the sag studies' refusal of a run without gravity."""
import dataclasses

import numpy as np
import pytest

from calibration.synthetic import box_scene, synthetic_reference
from forcecal.errors import DataFileError, ParameterError
from tests.particle_models import box_model
from studies._finished_run import FinishedRun
from studies.sag_tradeoff import constrained_step, regions, scaled


def volume_box():
    model = box_model((3, 3, 2), density=1000.0, K0=20.0, a=5.0, b=10.0)
    return model.with_params(dataclasses.replace(model.params, kv=np.full(model.n_tets, 2e3)))


def test_regions_label_every_connector_and_tet_by_the_nearest_centre():
    model = volume_box()
    x = model.rest_positions
    mid_c, mid_t = x[model.edges].mean(axis=1), x[model.tets].mean(axis=1)
    c, t = regions(mid_c, mid_t, 4)
    assert set(np.unique(c)) == {0, 1, 2, 3} and len(t) == model.n_tets
    # each tet is in the region whose connectors' centre is nearest to it
    centres = np.array([mid_c[c == r].mean(axis=0) for r in range(4)])
    nearest = np.argmin(((mid_t[:, None] - centres[None]) ** 2).sum(axis=2), axis=1)
    assert np.mean(nearest == t) > 0.9  # k-means centres are the regions' means, up to ties
    assert regions(mid_c, None, 2)[1] is None
    with pytest.raises(ParameterError, match="regions"):
        regions(mid_c, mid_t, 0)


def test_scaled_multiplies_each_regions_springs_and_kv_by_its_factors():
    p = volume_box().params
    n_c, n_t = len(p.K0), len(p.kv)
    c, t = np.arange(n_c) % 2, np.arange(n_t) % 2
    x = np.log([2.0, 1.0, 1.0, 3.0])  # region 0: springs x2; region 1: kv x3
    got = scaled(p, c, t, x)
    np.testing.assert_allclose(got.K0, np.where(c == 0, 2.0, 1.0) * p.K0, rtol=1e-12)
    np.testing.assert_allclose(got.b / got.K0, p.b / p.K0, rtol=1e-12)  # the shape kept
    np.testing.assert_allclose(got.kv, np.where(t == 1, 3.0, 1.0) * p.kv, rtol=1e-12)
    assert np.array_equal(got.k1, p.k1)
    same = scaled(p, c, t, np.zeros(4))
    assert np.array_equal(same.K0, p.K0) and np.array_equal(same.kv, p.kv)


def test_the_constrained_step_meets_its_target_with_the_least_misfit():
    """J = I and r = 0: the least |d|^2 with g . d = target is target g / |g|^2, whatever
    the regularisation; a target beyond the radius is halved until the step fits."""
    g = np.array([3.0, 4.0, 0.0])
    d, met = constrained_step(np.eye(3), g, np.zeros(3), 0.5)
    np.testing.assert_allclose(d, 0.5 * g / 25.0, rtol=1e-10)
    assert met == 0.5
    d, met = constrained_step(np.eye(3), g, np.zeros(3), 10.0, radius=0.25)
    halvings = np.log2(10.0 / met)  # the target halved k >= 1 times
    assert halvings >= 1 and halvings == pytest.approx(round(halvings), abs=1e-12)
    assert np.abs(d).max() <= 0.25 and g @ d == pytest.approx(met, rel=1e-10)
    # a residual the step can reduce: it does, along the constraint
    J = np.diag([1.0, 2.0, 1.0])
    r = np.array([0.0, 0.0, 1.0])
    d, _ = constrained_step(J, g, r, 0.0)
    assert g @ d == pytest.approx(0.0, abs=1e-12)
    assert np.sum((r + J @ d) ** 2) < np.sum(r ** 2)


def test_the_studies_refuse_a_reference_without_gravity(tmp_path):
    """A finished run whose reference has no gravity experiments gives the sag studies a
    DataFileError naming its folder, not an AttributeError from deep inside."""
    scene = box_scene(tmp_path, test_points={"n_calibration": 3, "n_held_out": 8})
    model = box_model((3, 3, 2), density=1000.0, K0=20.0)
    reference = synthetic_reference(scene, model.params, tmp_path / "reference.h5")
    assert reference.gravity is None
    done = FinishedRun(scene, tmp_path, reference, None, None)
    with pytest.raises(DataFileError, match=f"{tmp_path}: the reference has no gravity sag"):
        done.fe_static_sag()
