"""The calibration time study (studies/calibration_time.py): its kernel clock and its rates."""
from types import SimpleNamespace

import numpy as np
import pytest

import particle.sensitivity as sensitivity
import particle.sensitivity_kernels as kernels
from particle.sparse_ldl import Factor
from studies.calibration_time import (add_partials_rate, compression_cost, fit_size,
                                      point_jacobian_times, solve_cost)
from tests.test_calibration_gradient import _box, _sensitivity_evaluators


def _compiled(module) -> dict:
    return {name: f for name, f in vars(module).items() if hasattr(f, "py_func")}


def test_the_kernel_clock_times_the_adjoint_pass_and_leaves_it_as_it_was(tmp_path):
    """On the box (relaxing volume term, two points, the force vector's three components):
    the relaxation's adjoint pass is timed kernel by kernel (the connectors', the volume
    arms', the factorisation and its solves), the kernels within the pass's time; the
    Jacobian is the one the pass gives without the clock, bit for bit, and the module
    attributes the clock wrapped are the originals afterwards."""
    before = (_compiled(kernels), sensitivity.tangent_data, sensitivity.ldl_factor,
              Factor.solve)
    params, evaluators = _sensitivity_evaluators(_box(tmp_path), "viscoelastic", False)
    evaluator, directions = evaluators["relaxation"], np.eye(3)
    plain = evaluator.jacobian(params, [0, 1], directions)
    times = point_jacobian_times(evaluator, params, [0, 1], directions)
    assert {"add_partials", "elongation_adjoint", "add_volume_arm_partials",
            "add_volume_pattern_product", "Factor.solve", "ldl_factor",
            "tangent_data"} <= set(times["kernels_ms"])
    assert times["points"] == 2 and times["samples"] == len(evaluator.depths)
    assert 0 < sum(times["kernels_ms"].values()) <= times["point_jacobian_ms"]
    assert times["other_ms"] == times["point_jacobian_ms"] - sum(times["kernels_ms"].values())
    assert list(times["kernels_ms"].values()) == sorted(times["kernels_ms"].values(),
                                                        reverse=True)
    after = (_compiled(kernels), sensitivity.tangent_data, sensitivity.ldl_factor,
             Factor.solve)
    assert after[0] == before[0] and after[1:] == before[1:]
    clocked = evaluator.jacobian(params, [0, 1], directions)
    for name in ("forces", "connectors", "kv", "volume_arms"):
        np.testing.assert_array_equal(getattr(clocked, name), getattr(plain, name))


def test_the_streaming_rate_counts_the_bytes_add_partials_moves():
    """Per (output, connector): the Jacobian's 7 rows, the two arm histories and the
    elongation history read and written, the tension adjoint read: 21 doubles; the rates
    are those bytes over the times."""
    rate = add_partials_rate(4, 50, repeats=2)
    assert rate["bytes"] == 8 * 4 * 50 * 21
    assert rate["gb_per_s"] == pytest.approx(rate["bytes"] / (rate["ms"] * 1e-3) / 1e9)
    assert rate["gb_per_s"] > 0 and rate["memory_gb_per_s"] > 0


def test_the_solve_cost_prices_the_blocked_pass_from_the_solves_it_times(tmp_path):
    """On the box's relaxation (force vector, 3 directions): the factor is the constrained
    tangent of the model's dofs, every count of right-hand sides up to all the outputs is
    timed, and the blocked ratio is the blocks' solves (a remainder block's included) over
    the one solve of all outputs."""
    params, evaluators = _sensitivity_evaluators(_box(tmp_path), "viscoelastic", False)
    evaluator = evaluators["relaxation"]
    evaluator.jacobian(params, [0], np.eye(3))  # the forward path the study starts from
    outputs = 3 * len(evaluator.depths)
    cost = solve_cost(evaluator, params, outputs, repeats=2)
    assert set(cost["microseconds"]) == {"1", "3", "16", str(outputs // 2), str(outputs)}
    assert all(t > 0 for t in cost["microseconds"].values())
    assert cost["dofs"] == evaluator.pattern_for(evaluator._solvers[0]).n_dofs
    assert cost["l_entries"] > cost["dofs"]
    blocks, rest = divmod(outputs, 16)
    assert rest == 0 or cost["blocked_ratio"] > blocks * cost["microseconds"]["16"] / \
        cost["microseconds"][str(outputs)]
    if rest == 0:
        assert cost["blocked_ratio"] == pytest.approx(
            blocks * cost["microseconds"]["16"] / cost["microseconds"][str(outputs)])


def test_the_compression_is_timed_on_a_points_rows_and_coordinates(tmp_path):
    """The fit's coordinates: seven per connector, and per tet log kv, log kv1, log kv2 when
    each tet's relaxing kv is fitted (the box: 3 per tet), none per tet otherwise; the
    compression of rows of that shape is timed both ways."""
    params, evaluators = _sensitivity_evaluators(_box(tmp_path), "viscoelastic", False)
    model = evaluators["relaxation"].model
    e, t = model.n_connectors, model.n_tets
    mesh = SimpleNamespace(edges=model.edges, tets=model.tets)

    def setup(kv_per_tet: bool) -> SimpleNamespace:
        return SimpleNamespace(problem=SimpleNamespace(mesh=mesh),
                               settings=SimpleNamespace(kv_per_tet=kv_per_tet))

    assert params.kv is not None and params.has_volume_arms
    assert fit_size(setup(True), params) == 7 * e + 3 * t
    assert fit_size(setup(False), params) == 7 * e
    cost = compression_cost(30, fit_size(setup(True), params), 5, repeats=2)
    assert (cost["rows"], cost["size"], cost["keep"]) == (30, 7 * e + 3 * t, 5)
    assert cost["compress_ms"] > 0 and cost["reversed_view_projection_ms"] > 0
