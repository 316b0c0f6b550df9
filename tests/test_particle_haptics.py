"""Haptic session: the settled reaction force, one dispatch per call, and its refusals."""
import numpy as np
import pytest

from forcecal.errors import MeshError, ParameterError, StabilityError
from particle import haptics
from particle.evaluators import IndentationEvaluator
from particle.haptics import HapticSession
from particle.stability import critical_time_step
from tests.particle_models import box_model, top_centre

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



def _strains(model, x):
    d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
    return np.linalg.norm(d, axis=1) / model.rest_lengths - 1.0


@pytest.mark.parametrize("jump", [0.8, 30.0])  # x the mean connector length
def test_a_step_ending_outside_the_strain_range_is_refused_by_that_call(jump):
    """The strain checks ride on each substep's force pass, which sees the positions the
    substep starts from; the state a call ends in is checked too, so a tool jump that takes a
    connector out of the session's range is refused by the call that made it (no force
    returned), naming a connector that is out of range in that state. One substep per call
    (period = dt): only the final check can see it."""
    model = box_model()
    node = top_centre(model)
    dt = 0.5 * critical_time_step(model)
    session = HapticSession(model, dt, period=dt)
    assert session.substeps == 1
    x0 = model.rest_positions[node]
    session.step(node, x0)  # a valid call first: compiled, state at rest
    move = jump * float(model.rest_lengths.mean())
    with pytest.raises(StabilityError, match=rf"haptic step moving tool particle {node} by "
                       rf".* m in {dt:g} s .*: connector \d+ \(particles \d+-\d+\) reached "
                       rf"strain .* at the end of the run, t = {2 * dt:.6g} s, outside "
                       r"\[-0\.5, 0\.5\]") as err:
        session.step(node, x0 + move * DOWN)
    e = int(str(err.value).split("connector ")[1].split()[0])
    strain = _strains(model, session.state.x)[e]
    assert not -0.5 <= strain <= 0.5
    assert f"reached strain {strain:.4g}" in str(err.value)


def test_a_jump_out_of_range_in_a_call_of_several_substeps_is_refused_by_that_call():
    model = box_model()
    node = top_centre(model)
    session = HapticSession(model, 0.5 * critical_time_step(model))
    assert session.substeps > 1
    x0 = model.rest_positions[node]
    session.step(node, x0)
    with pytest.raises(StabilityError, match=r"connector \d+ \(particles \d+-\d+\) reached "
                       r"strain .* outside \[-0\.5, 0\.5\]"):
        session.step(node, x0 + 0.8 * float(model.rest_lengths.mean()) * DOWN)


def test_the_final_state_check_leaves_valid_calls_unchanged():
    """Calls that stay in range return bitwise the forces of an unmonitored run (the check
    only reads the state), and a drag close to the range's edge passes."""
    model = box_model()
    node = top_centre(model)
    dt = 0.5 * critical_time_step(model)
    session = HapticSession(model, dt)
    free = session.integrator.prepare(model, session.dt, prescribed_nodes=[node],
                                      _check_dt=False)
    assert free.monitored is None
    state = model.state()
    x0 = model.rest_positions[node]
    reached = 0.0
    for k in range(40):
        target = x0 + 0.005 * np.sin(k / 6.0) * DOWN
        force = session.step(node, target)
        times, positions = session._keyframes
        expected = free(state, session.substeps, (times.copy(), positions.copy()), 1e30,
                        probe=node)
        np.testing.assert_array_equal(force, expected)
        np.testing.assert_array_equal(session.state.x, state.x)
        reached = max(reached, float(np.abs(_strains(model, state.x)).max()))
    assert 0.25 < reached < 0.5


def test_the_final_strain_check_matches_numpy_on_both_of_its_paths():
    """step_kernels.final_strain_check (the displacement bound, else the exact pass) names
    the first connector outside the range, as the plain numpy check does."""
    from particle import kernels, step_kernels
    model = box_model()
    edges = kernels.index_view(model.edges)
    lo, hi = -0.2 * model.rest_lengths, 0.2 * model.rest_lengths
    rng = np.random.default_rng(3)
    seen = set()
    for amplitude in (1e-5, 1e-4, 5e-4, 1e-3, 2e-3):
        for _ in range(20):
            x_prev = model.rest_positions + amplitude * rng.standard_normal((model.n_particles, 3))
            x = x_prev + 0.3 * amplitude * rng.standard_normal(x_prev.shape)
            d = x_prev[model.edges[:, 1]] - x_prev[model.edges[:, 0]]
            dx_prev = np.linalg.norm(d, axis=1) - model.rest_lengths
            dx = _strains(model, x) * model.rest_lengths
            outside = np.nonzero(~((lo <= dx) & (dx <= hi)))[0]
            got = step_kernels.final_strain_check(x, x_prev, edges, model.rest_lengths,
                                                  dx_prev, lo, hi)
            assert got == (outside[0] if len(outside) else -1)
            seen.add(got >= 0)
            assert step_kernels.first_length_outside(x, edges, model.rest_lengths, lo,
                                                     hi) == got
    assert seen == {False, True}
    x[3, 0] = np.nan  # a non-finite position is never inside
    assert step_kernels.final_strain_check(x, x_prev, edges, model.rest_lengths, dx_prev,
                                           lo, hi) >= 0


def test_a_session_gravity_that_is_not_three_finite_numbers_is_refused():
    model = box_model()
    dt = 0.5 * critical_time_step(model)
    with pytest.raises(ParameterError, match=r"gravity = \[0\.0, -9\.81\] must be 3 "
                       r"components \(x, y, z\) in m/s\^2"):
        HapticSession(model, dt, gravity=np.array([0.0, -9.81]))
    with pytest.raises(ParameterError, match=r"gravity \[0\.0, 0\.0, nan\] m/s\^2 is not finite"):
        HapticSession(model, dt, gravity=[0.0, 0.0, np.nan])


def test_repeated_calls_through_the_compiled_entry_point_equal_numba_dispatch():
    """After its first call a session's run calls run_verlet's compiled entry point (its
    keyframes and probe kind unchanged): forces and states bit for bit those of calls
    through numba's dispatcher (the cache emptied before every call)."""
    model = box_model()
    node = top_centre(model)
    dt = 0.5 * critical_time_step(model)
    fast, slow = HapticSession(model, dt), HapticSession(model, dt)
    x0 = model.rest_positions[node]
    for k in range(30):
        target = x0 + [0.0, 0.0, -2e-4 * min(k, 10)]
        slow._run(node)[0]._entries.clear()
        np.testing.assert_array_equal(fast.step(node, target), slow.step(node, target))
    assert len(fast._run(node)[0]._entries) == 1
    np.testing.assert_array_equal(fast.state.x, slow.state.x)
    np.testing.assert_array_equal(fast.state.arm_force, slow.state.arm_force)
