"""Whole-body data of the particle model (:mod:`particle.body`) and in the gradient fit
(:mod:`calibration.body`): closed forms, exact Jacobians against finite differences, the
record of a model that does not carry a fitted load, recovery of known parameters from
synthetic whole-body + curve data."""
import dataclasses

import numpy as np
import pytest

from calibration.body import BodyData, body_record
from calibration.core import calibrate
from calibration.gradient import Coordinates
from calibration.synthetic import synthetic_body, synthetic_reference
from forcecal.errors import ParameterError
from forcecal.h5io import read_reference, write_reference
from forcecal.mesh import box_mesh
from forcecal.problem import build_problem
from forcecal.scene import BODY_DATA_CHOICES, BODY_KINDS, replace
from particle.body import (BodyTarget, RestOperators, body_response, incremental_form,
                           incremental_form_numpy, incremental_tangent, load_rows, model_modes,
                           parameter_layout)
from particle.model import ModelBuilder
from particle.params import ConnectorParams
from particle.statics import weight_equilibrium
from tests.test_calibration_gradient import _box, _recovery, smooth_truth


def _box_model(arms: bool, seed: int = 1):
    """A 60 x 40 x 40 mm box of 3 x 2 x 2 cells clamped at z = 0, random springs (a softening
    and stiffening shape) and per-tet kv, with volume arms or without."""
    mesh = box_mesh((3, 2, 2), (0.06, 0.04, 0.04))
    rng = np.random.default_rng(seed)
    E, T = len(mesh.edges), len(mesh.tets)
    K0 = 50.0 * np.exp(0.3 * rng.standard_normal(E))
    values = dict(K0=K0, a=-0.3 * K0, b=2.0 * K0, k1=0.6 * K0, b1=0.3 * K0, k2=0.4 * K0,
                  b2=4.0 * K0, kv=4000.0 * np.exp(0.3 * rng.standard_normal(T)))
    if arms:
        values.update(kv1=np.full(T, 2000.0), bv1=np.full(T, 1000.0), kv2=np.full(T, 1000.0),
                      bv2=np.full(T, 1.0e4))
    builder = ModelBuilder()
    builder.add_particles(mesh.vertices, mesh.lumped_masses(1060.0), mesh.vertices[:, 2] < 1e-9)
    builder.add_connectors(mesh.edges)
    return builder.finalize(ConnectorParams(**values), mesh.tets)


def _three_springs(k: tuple[float, float, float], mass: float, length: float = 0.01):
    """One free particle at the origin held by three fixed particles along +x, +y, +z."""
    builder = ModelBuilder()
    builder.add_particle([0.0, 0.0, 0.0], mass)
    for axis in range(3):
        builder.add_particle(np.eye(3)[axis] * length, 1.0, fixed=True)
    builder.add_connectors([[0, 1], [0, 2], [0, 3]])
    K0 = np.array(k, dtype=float)
    zero = np.zeros(3)
    return builder.finalize(ConnectorParams(K0=K0, a=zero, b=zero, k1=0.5 * K0, b1=K0,
                                            k2=zero + 1e-9, b2=zero + 1.0))


def test_modes_and_a_static_load_of_a_particle_on_three_springs():
    """Closed forms: eigenvalues ``k_i / m`` at rest (long-term: K0; instantaneous: K0 + k1 +
    k2), and under a weight ``m g`` along x a displacement ``m g / k_x`` (the transverse
    springs, stretched by ``u^2 / (2 L)``, add ``1e-6`` relative along x and move the particle
    by ``u^2 / (2 L) = 5e-7 m`` along y and z: second order); the load's residual rows
    against that displacement are zero."""
    model = _three_springs((100.0, 200.0, 400.0), 0.01)
    ops = RestOperators.of(model)
    for modulus, factor in (("long_term", 1.0), ("instantaneous", 1.5)):
        values, vectors, _ = model_modes(model, ops, modulus, 2)
        np.testing.assert_allclose(values, factor * np.array([100.0, 200.0]) / 0.01, rtol=1e-10)
        np.testing.assert_allclose(np.abs(vectors[:, 0]), [10.0, 0.0, 0.0], atol=1e-8)
    g = np.array([1.0, 0.0, 0.0])  # u = 1e-4 m, 1 % of the springs' length
    x = weight_equilibrium(model, g, 2)
    np.testing.assert_allclose(x[0], [0.01 * 1.0 / 100.0, 0.0, 0.0], rtol=2e-6, atol=6e-7)
    rows = load_rows(model, g, x - model.rest_positions, 2)
    assert np.abs(rows.residual).max() < 1e-9


def test_incremental_form_is_the_tangent_and_its_gradient_is_exact():
    """The quadratic form of the instantaneous incremental tangent about a loaded state equals
    ``phi^T K_t phi`` of the assembled tangent to round-off, and its position gradient a
    central difference to 1e-7 (both volume terms)."""
    rng = np.random.default_rng(2)
    for arms in (False, True):
        model = _box_model(arms)
        x = weight_equilibrium(model, np.array([9.81, 0.0, 0.0]), 4)
        phi = np.zeros_like(x)
        phi[model.free_nodes] = rng.standard_normal((len(model.free_nodes), 3))
        q, gradient, _ = incremental_form(model, x, phi)
        K = incremental_tangent(model, RestOperators.of(model).pattern, x)
        v = phi[model.free_nodes].ravel()
        assert q == pytest.approx(v @ K @ v, rel=1e-12)
        step = np.zeros_like(x)
        step[model.free_nodes] = rng.standard_normal((len(model.free_nodes), 3))
        h = 1e-7
        fd = (incremental_form(model, x + h * step, phi)[0]
              - incremental_form(model, x - h * step, phi)[0]) / (2 * h)
        assert np.sum(gradient * step) == pytest.approx(fd, rel=1e-7)


@pytest.mark.parametrize("volume", ["springs", "elastic kv", "viscoelastic kv"])
def test_compiled_incremental_form_matches_its_numpy_twin(volume):
    """The compiled passes do the numpy expressions' operations in their order: the form, its
    position gradient and its parameter derivatives agree to round-off (1e-13 of each
    array's largest entry; bitwise on the machines measured, but numpy's SIMD sums may order
    differently on another CPU)."""
    rng = np.random.default_rng(5)
    model = _box_model(volume == "viscoelastic kv")
    if volume == "springs":
        model = model.with_params(dataclasses.replace(model.params, kv=None))
    x = weight_equilibrium(model, np.array([0.0, 9.81, -9.81]), 4)
    for _ in range(3):
        phi = np.zeros_like(x)
        phi[model.free_nodes] = rng.standard_normal((len(model.free_nodes), 3))
        q, gradient, explicit = incremental_form(model, x, phi)
        q_np, gradient_np, explicit_np = incremental_form_numpy(model, x, phi)
        assert q == pytest.approx(q_np, rel=1e-13)
        for got, want in ((gradient, gradient_np), (explicit, explicit_np)):
            assert got.shape == want.shape
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(want).max())


@pytest.mark.parametrize("arms", [False, True], ids=["elastic kv", "viscoelastic kv"])
def test_whole_body_jacobians_match_finite_differences(arms):
    """Every item's residual Jacobian (loads, rest modes at both moduli, modes about each
    load's equilibrium, the unsupported body's modes at both moduli) along a random direction
    of every parameter block, against central differences: measured within 1e-7 of the
    largest difference, 5.6e-7 for the unsupported body's long-term modes (asserted 1e-5)."""
    model = _box_model(arms)
    p = model.params
    other = model.with_params(dataclasses.replace(p, K0=1.2 * p.K0, b=0.5 * p.b))
    target = BodyTarget.of(synthetic_body(other, np.array([0.0, 0.0, -9.81]), 3, 4),
                           BODY_KINDS)
    response = body_response(model, target, 4)
    assert len(response.parts) == len(target.items) == 2 + 6 + 6 + 6
    layout = parameter_layout(model.n_connectors, model.n_tets, arms)
    rng = np.random.default_rng(3)
    direction = {name: 1e-4 * getattr(p, name) * rng.standard_normal(cols.stop - cols.start)
                 for name, cols in layout.items()}
    dense = np.concatenate([direction[name] for name in layout])
    plus = body_response(model.with_params(dataclasses.replace(
        p, **{n: getattr(p, n) + d for n, d in direction.items()})), target, 4)
    minus = body_response(model.with_params(dataclasses.replace(
        p, **{n: getattr(p, n) - d for n, d in direction.items()})), target, 4)
    for part, a, b, name in zip(response.parts, plus.parts, minus.parts, target.items):
        fd = (a.residual - b.residual) / 2.0
        np.testing.assert_allclose(part.jacobian() @ dense, fd, atol=1e-5 * np.abs(fd).max(),
                                   err_msg=name)
    # the residuals alone (a trial step's objective) are the same numbers: the loads' bit for
    # bit, the modes' to ARPACK's round-off (its random start vector: two calls with the
    # Jacobian differ by up to 4e-15 held, 1.3e-13 free-free, whose shifted factor is less
    # well conditioned)
    alone = body_response(model, target, 4, jacobian=False)
    assert all(part.fields is None for part in alone.parts)
    np.testing.assert_array_equal(alone.parts[0].residual, response.parts[0].residual)
    np.testing.assert_allclose(alone.residual, response.residual, rtol=0, atol=1e-12)


def test_chain_matrix_is_the_chain_rule():
    """The sparse chain matrix from the parameter layout to the fit's coordinates equals
    :meth:`Coordinates.chain` of a dense Jacobian (per-tet kv and volume arms)."""
    model = _box_model(True)
    p = model.params
    E, T = model.n_connectors, model.n_tets
    coords = Coordinates(0.1, E, T, volume_tau=p.volume_arm_tau)
    rng = np.random.default_rng(4)
    layout = parameter_layout(E, T, True)
    jac = rng.standard_normal((2, max(s.stop for s in layout.values())))
    by_name = {n: jac[:, s] for n, s in layout.items()}
    dense = coords.chain(np.stack([by_name[n] for n in ("K0", "a", "b", "k1", "b1", "k2", "b2")],
                                  axis=1), by_name["kv"], p,
                         np.stack([by_name[n] for n in ("kv1", "bv1", "kv2", "bv2")], axis=1))
    np.testing.assert_allclose(jac @ coords.chain_matrix(p, T).toarray(), dense, rtol=1e-12)


def test_a_model_that_does_not_carry_a_fitted_load_is_a_failed_calibration():
    """The record of a fit whose calibrated model has no equilibrium under a fitted load:
    status "failed" with the reason (no exception); the baseline's errors are still there.
    The load: 5 g sideways, which the box carries (22 mm) and the same box with strongly
    softening springs (b = -20 K0) does not (a limit point)."""
    model = _box_model(False)
    body = synthetic_body(model, np.array([0.0, 0.0, -9.81]), 2, 2)
    heavy = dataclasses.replace(body, load_acceleration=5 * 9.81)
    data = BodyData(model, heavy, ("loads",), 4)
    soft = dataclasses.replace(model.params, b=-20.0 * model.params.K0)
    record = body_record(data, 1.0, {"baseline": model.params, "calibrated": soft})
    assert record["status"] == "failed" and "does not carry" in record["failure"]
    assert "failure" in record["variants"]["calibrated"]
    assert "item_errors" in record["variants"]["baseline"]
    fine = body_record(BodyData(model, body, ("loads",), 4), 1.0, {"calibrated": model.params})
    assert fine["status"] == "fitted" and max(fine["variants"]["calibrated"]["item_errors"]) < 1e-8
    assert body_record(BodyData(model, body, (), 4), None, {"calibrated": model.params}
                       )["status"] == "not fitted"


def test_gradient_fit_recovers_the_truth_from_curves_and_whole_body_data(tmp_path):
    """Synthetic reference made by the particle model with a smooth per-connector truth
    (:func:`~tests.test_calibration_gradient.smooth_truth`) and its whole-body data (rest
    modes, loads, modes about the loads, the unsupported body's modes), only 4 calibration
    points on the box, every kind of whole-body data fitted, the weight by cross-validation
    (it picks 100, the grid's end: exact data). Measured: the curves to 0.00 %, the held-out
    points at 0.054 / 0.065 of the global fit's errors, every whole-body item within 0.09 %
    (global fit: 0.2-22 %), K(eps) within 0.54 % (median) and 5.4 % (max) of the truth, the
    arms 0.0-2.4 % (without the unsupported body's modes: held-out 0.17 / 0.13, K(eps) 1.4 %
    / 10 %). The
    same curves without the whole-body data (``body_data = "none"``): the cross-validation
    keeps the global fit nearly (smoothness weight 1000), held-out at 0.82 / 0.80 of it,
    K(eps) 9 % / 51 %, the arms 1-7 %. Asserted with ~1.5-2x margins."""
    scene = replace(_box(tmp_path, n_calibration=4),
                    experiments=["indentation", "relaxation", "body"],
                    calibration={"body_data": "+".join(BODY_KINDS),
                                 "body_candidates": True, "static_max_evaluations": 40,
                                 "relaxation_max_evaluations": 60},
                    body={"modes": 3, "load_steps": 2})
    problem = build_problem(scene)
    truth = smooth_truth(problem)
    synthetic_reference(scene, truth, tmp_path / "reference.h5")
    assert read_reference(tmp_path / "reference.h5").body is not None
    result = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5",
                       progress=False)
    record = result.body
    assert record["status"] == "fitted" and record["weight"] > 0
    assert record["kinds"] == list(BODY_KINDS)
    assert max(record["variants"]["calibrated"]["item_errors"]) < 0.002
    assert min(record["variants"]["global"]["item_errors"]) > 0.001
    assert set(record["cv"]["round_1"]) == set(BODY_DATA_CHOICES)  # every set of kinds
    calibrated, held_out_ratio, spring, arms = _recovery(problem, truth, result)
    assert max(calibrated) < 0.002 and max(held_out_ratio) < 0.12
    assert np.median(spring) < 0.01 and spring.max() < 0.1
    assert max(arms.values()) < 0.05, arms


def test_a_reference_without_the_unsupported_bodys_modes_serves_the_other_kinds(tmp_path):
    """A ``reference.h5`` written before the unsupported body's modes existed reads back
    without them (None); a fit of the other kinds runs on it, and one asking for them is
    refused, naming what to recompute."""
    scene = replace(_box(tmp_path, n_calibration=4),
                    experiments=["indentation", "relaxation", "body"],
                    body={"modes": 2, "load_steps": 2})
    truth = smooth_truth(build_problem(scene))
    ref = synthetic_reference(scene, truth, tmp_path / "reference.h5")
    assert ref.body.free_frequencies.shape == (2, 2)
    old = dataclasses.replace(ref.body, free_frequencies=None, free_shapes=None)
    write_reference(tmp_path / "old.h5", dataclasses.replace(ref, body=old))
    back = read_reference(tmp_path / "old.h5")
    assert back.body.free_frequencies is None and back.body.free_shapes is None
    data = BodyData.of(back, ("modes",), truth, 2)
    assert not any(name.startswith("free") for name in data.items)
    np.testing.assert_allclose(data.residuals(truth), 0.0, atol=1e-8)  # its own data
    with pytest.raises(ParameterError, match="free_modes.*recompute"):
        BodyData.of(back, ("modes", "free_modes"), truth, 2)


def test_a_reference_whose_body_loads_failed_fits_the_modes_and_says_why(tmp_path):
    """The FE could not hold the body under its weight sideways (``load_failure``, no loads
    and no modes about them): ``reference.h5`` keeps the reason; a fit asking for the loads
    and the modes fits the modes, and its ``body`` record names the kinds the FE could not
    give and why (the run ends in a report instead of an error). Loads together with a
    load failure are refused when written."""
    from forcecal.errors import DataFileError
    from particle.body import available_kinds

    scene = replace(_box(tmp_path, n_calibration=4),
                    experiments=["indentation", "relaxation", "body"],
                    calibration={"body_data": "loads+modes", "static_max_evaluations": 20,
                                 "relaxation_max_evaluations": 20,
                                 "gradient_max_iterations": 4},
                    body={"modes": 2, "load_steps": 2})
    truth = smooth_truth(build_problem(scene))
    ref = synthetic_reference(scene, truth, tmp_path / "synthetic.h5")
    why = "the weight along [1.0, 0.0, 0.0] (static): the support does not hold the body"
    n = ref.problem.mesh.n_vertices
    failed = dataclasses.replace(ref.body, load_directions=np.zeros((0, 3)),
                                 load_displacement=np.zeros((0, n, 3)),
                                 loaded_frequencies=np.zeros((0, 2)),
                                 loaded_shapes=np.zeros((0, 2, n, 3)), load_failure=why)
    with pytest.raises(DataFileError, match="a load failure with loads"):
        write_reference(tmp_path / "bad.h5", dataclasses.replace(
            ref, body=dataclasses.replace(ref.body, load_failure=why)))
    write_reference(tmp_path / "reference.h5", dataclasses.replace(ref, body=failed))
    back = read_reference(tmp_path / "reference.h5")
    assert back.body.load_failure == why and back.body.load_directions.shape == (0, 3)
    assert available_kinds(back.body) == ("modes", "free_modes")
    assert read_reference(tmp_path / "synthetic.h5").body.load_failure is None
    result = calibrate(scene, tmp_path / "reference.h5", tmp_path / "params.h5",
                       progress=False)
    record = result.body
    assert record["status"] == "fitted" and record["kinds"] == ["modes"]
    assert record["failure"] == f"the FE has no loads data: {why}"
    assert not any(item.startswith("load") for item in record["items"])


def test_the_kinds_a_model_has_no_response_to_are_named():
    """:meth:`BodyData.carried` tells, kind by kind, whether a model has a response: the soft
    box under 5 g sideways has its rest modes but no equilibrium under the loads, so neither
    the loads nor the modes about them (what a fit then starts without, adding them once it
    carries them)."""
    model = _box_model(False)
    body = dataclasses.replace(synthetic_body(model, np.array([0.0, 0.0, -9.81]), 2, 2),
                               load_acceleration=5 * 9.81)
    data = BodyData(model, body, BODY_KINDS, 4)
    soft = dataclasses.replace(model.params, b=-20.0 * model.params.K0)
    carried = data.carried(soft)
    assert carried["modes"] is None
    assert "ConvergenceError" in carried["loads"] and "ConvergenceError" in carried["loaded_modes"]
    assert not any(data.carried(model.params).values())
    only = data.with_kinds(("modes",))
    assert only.kinds == ("modes",) and len(only.residuals(soft)) == 2 * 2 * (1 + 2)
    assert only.items == data.items  # every item is still reported
