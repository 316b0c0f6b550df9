"""Haptic session: the settled reaction force, one dispatch per call, and its refusals."""
import numpy as np
import pytest

from forcecal.errors import MeshError, ParameterError, StabilityError
from particle import haptics
from particle.evaluators import IndentationEvaluator
from particle.haptics import HapticSession
from particle.stability import critical_time_step
from particle.testing import box_model, top_centre

DOWN = np.array([0.0, 0.0, -1.0])  # inward normal of the top face


def test_haptic_session_settles_to_the_static_indentation_force():
    model = box_model(tau=(0.01, 0.05))
    node = top_centre(model)
    target = model.rest_positions[node] + 0.002 * DOWN
    session = HapticSession(model, 0.5 * critical_time_step(model, damping=40.0), damping=40.0)
    for k in range(3000):  # 3 s of device time, tool pressed in over the first 50 ms
        force = session.step(node, model.rest_positions[node] + min(1.0, k / 50) * 0.002 * DOWN)
    np.testing.assert_allclose(session.state.x[node], target, rtol=1e-15)
    static = IndentationEvaluator(model, [node], [DOWN], [0.002]).force_vectors(model.params)
    # the tissue pushes the tool back: minus the indenter force, once settled
    np.testing.assert_allclose(force, -static[0, 0], rtol=1e-6, atol=1e-9)
    # the force computed in the run's kernel call is the run's force_on, bitwise
    run, _ = session._run(node)
    np.testing.assert_array_equal(force, run.force_on(session.state, node))


def test_the_tool_run_cache_is_bounded(monkeypatch):
    """Each tool particle gets a prepared run; the least recently used is dropped beyond the
    cache size, and coming back to it prepares it again with the same result."""
    monkeypatch.setattr(haptics, "TOOL_RUN_CACHE", 2)
    model = box_model()
    top = np.nonzero(np.isclose(model.rest_positions[:, 2], model.rest_positions[:, 2].max()))[0]
    session = HapticSession(model, 0.5 * critical_time_step(model))
    first = session._run(int(top[0]))
    for node in top[:4]:
        session.step(int(node), model.rest_positions[node])
    assert list(session._runs) == [int(top[2]), int(top[3])]
    again = session._run(int(top[0]))
    assert again[0] is not first[0] and again[1] == first[1]


@pytest.mark.parametrize("dt", [0.0, -1e-4, np.nan, np.inf])
def test_a_step_that_is_not_a_positive_number_is_refused(dt):
    with pytest.raises(StabilityError, match=r"time step dt = .* s must be a finite number > 0"):
        HapticSession(box_model(), dt)


def test_bad_tool_nodes_and_positions_are_refused():
    model = box_model()
    node = top_centre(model)
    session = HapticSession(model, 0.5 * critical_time_step(model))
    x0 = model.rest_positions[node]
    with pytest.raises(MeshError, match="unknown particle"):
        session.step(model.n_particles, x0)
    with pytest.raises(MeshError, match="unknown particle"):
        session.step(-1, x0)
    with pytest.raises(MeshError, match="are fixed"):
        session.step(int(np.nonzero(model.fixed)[0][0]), x0)
    with pytest.raises(MeshError, match=r"tool node 4\.5 must be an integer particle id"):
        session.step(4.5, x0)  # was truncated to particle 4
    with pytest.raises(ParameterError, match="not finite"):
        session.step(node, [np.nan, 0.0, 0.0])
    for bad in ([0.0, 0.0], np.zeros((1, 3)), "top", None):
        with pytest.raises(ParameterError, match="must be 3 coordinates"):
            session.step(node, bad)
    # nothing was advanced by the refused calls
    assert session.state.t == 0.0
    session.step(np.int64(node), x0)  # numpy integers are integers
    assert session.state.t == pytest.approx(session.period)

