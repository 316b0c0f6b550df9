"""The sag study (pipelines/bench/sag_split.py): its split ratios, its sag ratio and its rows."""
import dataclasses

import numpy as np
import pytest

from forcecal.errors import ParameterError
from particle.statics import gravity_static
from particle.testing import box_model
from pipelines.bench.sag_split import mean_sag_ratio, sag_rows, split_ratios
from pipelines.report import gravity_static_error

GRAVITY = np.array([0.0, 0.0, -9.81])


def volume_box():
    """A clamped box, springs + a volume term of 2 kPa on every tet."""
    model = box_model((3, 3, 2), density=1000.0, K0=20.0, a=5.0, b=10.0)
    return model.with_params(dataclasses.replace(model.params, kv=np.full(model.n_tets, 2e3)))


def test_split_ratios_are_the_geometric_means_of_calibrated_over_global():
    """K0 halved on every connector, kv x2 on m tets and x8 on the other n - m: the
    geometric means 0.5 and 2^((m + 3 (n - m))/n); a global kv of one value broadcasts."""
    p = volume_box().params
    n = len(p.kv)
    m = n // 3
    kv = np.where(np.arange(n) < m, 2.0, 8.0) * p.kv
    calibrated = dataclasses.replace(p, K0=0.5 * p.K0, kv=kv)
    global_one_kv = dataclasses.replace(p, kv=p.kv[:1])
    got = split_ratios(global_one_kv, calibrated)
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


def test_sag_rows_repeat_the_static_sag_and_a_stiffer_kv_sags_less():
    """The unscaled row is the gravity stage's Newton sag itself (error 0 and ratio 1
    against it); scaling kv up makes the body sag less, monotonically."""
    model = volume_box()
    fe = gravity_static(model, GRAVITY)
    rows = sag_rows({"calibrated": model}, GRAVITY, fe, (1.0, 2.0, 4.0))
    assert [r["kv_factor"] for r in rows] == [1.0, 2.0, 4.0]
    assert np.array_equal(rows[0]["displacement"], fe)
    assert rows[0]["error"] == 0.0 and rows[0]["mean_sag_ratio"] == pytest.approx(1.0, rel=1e-12)
    ratios = [r["mean_sag_ratio"] for r in rows]
    assert ratios[0] > ratios[1] > ratios[2] > 0.0
    stiffer = gravity_static(model.with_params(
        dataclasses.replace(model.params, kv=2.0 * model.params.kv)), GRAVITY)
    assert rows[1]["error"] == pytest.approx(gravity_static_error(fe, stiffer, model.free_nodes),
                                             rel=1e-12)
    with pytest.raises(ParameterError, match="kv factors"):
        sag_rows({"calibrated": model}, GRAVITY, fe, (1.0, 0.0))
