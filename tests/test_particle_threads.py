"""The multi-threaded explicit step: the serial step's results to round-off, the same checks
and stops, scheduling-independent results, and its refusals."""
import numba
import numpy as np
import pytest

from forcecal.errors import ParameterError, StabilityError
from particle.haptics import HapticSession
from particle.integrator import VerletIntegrator
from particle.model import Prescribed
from particle.stability import critical_time_step
from tests.particle_models import box_model, top_centre

GRAVITY = np.array([0.0, 0.0, -9.81])
DOWN = np.array([0.0, 0.0, -1.0])
POOL = numba.config.NUMBA_NUM_THREADS
pytestmark = pytest.mark.skipif(POOL < 2, reason="numba's thread pool has a single thread")


def _close(parallel: np.ndarray, serial: np.ndarray, relative: float = 1e-12) -> None:
    """Equal up to the summation order of the force reduction: ``relative`` of the largest
    value."""
    np.testing.assert_allclose(parallel, serial, rtol=0,
                               atol=relative * np.abs(serial).max())


def test_the_threaded_run_matches_the_serial_run_to_round_off():
    """Every term (nonlinear springs, arms, gravity, damping, prescribed motion) over 2000
    steps in 100 calls: two connector and node blocks vs the serial loop."""
    model = box_model((4, 4, 3), a=-20.0, b=300.0)
    dt = 0.5 * critical_time_step(model, damping=3.0)
    node = top_centre(model)
    start = model.rest_positions[node]
    motion = Prescribed([node], [0.0, 200 * dt], [[start], [start + 2e-3 * DOWN]])
    integrator = VerletIntegrator(3.0)
    serial, parallel = model.state(), model.state()
    for _ in range(100):
        for state, threads in ((serial, 1), (parallel, 2)):
            integrator.simulate(model, state, dt, 20, gravity=GRAVITY, prescribed=motion,
                                threads=threads)
        _close(parallel.x - model.rest_positions, serial.x - model.rest_positions)
    # the arm forces sum 2000 steps of elongation increments, differences of nearly equal
    # numbers: their round-off, relative to their largest value, is the largest here
    # (measured 7.9e-13 with the reference BLAS's time step, 1.03e-12 with OpenBLAS's, which
    # differs in the last bit; positions 3.9e-13)
    _close(parallel.arm_force, serial.arm_force, relative=1e-11)
    _close(parallel.dx_prev, serial.dx_prev)
    assert parallel.t == serial.t
    assert not np.array_equal(parallel.x, serial.x)  # really another summation order


def test_the_threaded_haptic_session_matches_the_serial_one_over_many_calls():
    model = box_model((4, 4, 3), tau=(0.01, 0.05))
    node = top_centre(model)
    dt = 0.5 * critical_time_step(model)
    sessions = [HapticSession(model, dt, gravity=GRAVITY, threads=t) for t in (1, 2)]
    assert sessions[0]._run(node)[0]._blocks is None  # threads=1 is the serial loop
    forces = np.array([[s.step(node, model.rest_positions[node] + min(1.0, k / 100) * 2e-3
                               * DOWN) for s in sessions] for k in range(500)])
    _close(forces[:, 1], forces[:, 0])
    _close(sessions[1].state.x - model.rest_positions,
           sessions[0].state.x - model.rest_positions)


def test_the_threaded_mass_scaled_session_matches_the_serial_one():
    """Mass scaling (one substep per period) on two threads: the inertia reaches the node
    blocks' position update as in the serial loop."""
    from particle.mass_scaling import scaled_inertia

    model = box_model((4, 4, 3), tau=(0.01, 0.05))
    node = top_centre(model)
    period = 2.0 * critical_time_step(model)
    inertia = scaled_inertia(model, period)
    sessions = [HapticSession(model, period, period=period, gravity=GRAVITY, threads=t,
                              inertia=inertia) for t in (1, 2)]
    assert sessions[0].substeps == 1
    forces = np.array([[s.step(node, model.rest_positions[node] + min(1.0, k / 50) * 2e-3
                               * DOWN) for s in sessions] for k in range(200)])
    _close(forces[:, 1], forces[:, 0])
    _close(sessions[1].state.x - model.rest_positions,
           sessions[0].state.x - model.rest_positions)


def test_the_threaded_result_does_not_depend_on_the_scheduling_and_the_pool_is_restored():
    """The blocks' forces are summed in block order: run on one pool thread (both blocks in
    turn) or two, the result is bitwise the same; each call sets numba's thread count to the
    run's and restores the caller's."""
    model = box_model((4, 4, 3))
    dt = 0.5 * critical_time_step(model)
    states = []
    previous = numba.get_num_threads()
    try:
        for pool in (1, 2):
            numba.set_num_threads(pool)
            state = model.state()
            VerletIntegrator().simulate(model, state, dt, 300, gravity=GRAVITY, threads=2)
            assert numba.get_num_threads() == pool
            states.append(state)
    finally:
        numba.set_num_threads(previous)
    np.testing.assert_array_equal(states[0].x, states[1].x)
    np.testing.assert_array_equal(states[0].arm_force, states[1].arm_force)


def _error(run) -> str:
    with pytest.raises(StabilityError) as info:
        run()
    return str(info.value)


def test_the_threaded_run_stops_where_and_when_the_serial_run_does():
    """A connector leaving the verified strain range (in the second block only, or in both:
    the first in connector order is named), a non-finite position and an energy beyond the
    bound: the same StabilityError, word for word."""
    model = box_model((3, 3, 2))
    dt = 0.5 * critical_time_step(model)
    last = model.n_connectors - 1
    lo, hi = np.full(model.n_connectors, -0.5), np.full(model.n_connectors, 0.5)
    for narrow in ([last], slice(None)):
        lo[narrow], hi[narrow] = -1e-6, 1e-6
        integrator = VerletIntegrator(strain_range=(lo.copy(), hi.copy()))
        messages = [_error(lambda: integrator.simulate(model, model.state(), dt, 200,
                                                       gravity=GRAVITY, threads=t))
                    for t in (1, 2)]
        named = last if isinstance(narrow, list) else 0
        assert messages[0].startswith(f"connector {named} ") and messages[1] == messages[0]
    for check_every, bound, what in ((1, np.inf, "non-finite"), (4, 1e-30, "fastest")):
        messages = []
        for threads in (1, 2):
            state = model.state()
            state.x[int(model.free_nodes[-1]), 1] = np.nan if what == "non-finite" else 1e-3
            run = VerletIntegrator(check_every=check_every).prepare(model, dt, threads=threads)
            messages.append(_error(lambda: run(state, 10, None, bound)))
        assert what in messages[0] and messages[1] == messages[0]


@pytest.mark.parametrize("threads", [0, -1, 1.5, "2", None, POOL + 1])
def test_a_thread_count_outside_the_pool_is_refused(threads):
    model = box_model()
    dt = 0.5 * critical_time_step(model)
    message = rf"threads = .* must be an integer in 1\.\.{POOL} \(numba's thread pool"
    for make in (lambda: HapticSession(model, dt, threads=threads),
                 lambda: VerletIntegrator().prepare(model, dt, threads=threads),
                 lambda: VerletIntegrator().simulate(model, model.state(), dt, 1,
                                                     threads=threads)):
        with pytest.raises(ParameterError, match=message):
            make()
