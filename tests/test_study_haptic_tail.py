"""The haptic tail study (studies/haptic_tail.py): its tail statistics and its controls."""
import numpy as np
import pytest

from studies.haptic_tail import SLOW_US, compute_work, memory_work, sized, tail, timed_calls
from tests.particle_models import box_model


def test_tail_finds_the_share_and_the_spacing_of_interrupted_calls():
    """Calls of 100 us, every 40th (4 ms of calls back to back) 80 us longer: 2.5 % slow,
    spaced 4.08 ms (39 calls of 100 us and one of 180 us), the p99 in the slow ones."""
    latencies = np.full(4000, 100.0)
    latencies[39::40] = 180.0
    t = tail(latencies)
    assert t["median_us"] == 100.0 and t["p99_us"] == 180.0
    assert t["slow_share"] == pytest.approx(0.025)
    assert t["slow_spacing_ms"] == pytest.approx(4.08)
    assert tail(np.full(100, 50.0))["slow_spacing_ms"] is None
    assert SLOW_US == 30.0


def test_the_controls_are_sized_to_a_median_time_and_do_their_work():
    """Sized to 200 us, a control's median is within 30 % of it (three proportional rounds on
    a shared machine); the memory sweep changes every element it passes."""
    n = sized(compute_work, 200.0, 1000)
    assert np.median(timed_calls(lambda: compute_work(n), 50)) == pytest.approx(200.0, rel=0.3)
    buffer = np.zeros(1000)
    memory_work(buffer, 2)
    np.testing.assert_array_equal(buffer, 1.5)  # (0 * 0.5 + 1) * 0.5 + 1


def test_the_working_set_counts_every_array_a_substep_touches():
    """104 bytes per connector (ends, rest length, K0, a, b, two arms' r and c, two arm
    forces, the elongation) and 88 per particle (positions twice, forces, mass, 1/mass)."""
    from studies.haptic_tail import working_set_bytes
    model = box_model()
    assert working_set_bytes(model) == 104 * model.n_connectors + 88 * model.n_particles
