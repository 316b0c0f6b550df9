"""Dynamics metrics of the gravity release (pipelines/dynamics.py) on closed-form oscillations."""
import math

import numpy as np
import pytest

from pipelines.dynamics import dynamic_metrics, signal_metrics


def release(time, static, omega, zeta):
    """Damped oscillator released from rest at 0 towards ``static``: s = static (1 - e^{-zeta
    omega t} (cos(w_d t) + zeta omega/w_d sin(w_d t))), w_d = omega sqrt(1 - zeta^2)."""
    wd = omega * math.sqrt(1 - zeta ** 2)
    a = zeta * omega
    return static * (1 - np.exp(-a * time) * (np.cos(wd * time) + a / wd * np.sin(wd * time)))


def test_period_first_peak_and_decay_of_a_damped_release_are_recovered():
    """Sampled every 5 ms over 3 s as the FE records: period 2 pi/w_d within 0.5 % (FFT of
    a 1.5 s window holding ~5 periods, zero-padded, parabolic peak: measured 0.1 %), first
    peak static (1 + e^{-a pi/w_d}) within 1e-3 (parabola through samples 5 ms apart),
    decay rate zeta omega within 1 % (exact for the extrema of this form up to sampling)."""
    time = np.arange(0, 3.0 + 1e-9, 0.005)
    omega, zeta, static = 2 * math.pi * 3.3, 0.08, 0.02
    s = release(time, static, omega, zeta)
    history = np.column_stack([0.1 * s, 0 * s, -s])  # along the static sag direction
    direction = np.array([0.1, 0.0, -1.0]) / math.sqrt(1.01)
    m = signal_metrics(time, history, direction, np.array([0.1, 0.0, -1.0]) * static)
    wd = omega * math.sqrt(1 - zeta ** 2)
    scale = math.sqrt(1.01)
    assert m["period_s"] == pytest.approx(2 * math.pi / wd, rel=5e-3)
    assert m["first_peak_m"] == pytest.approx(scale * static * (1 + math.exp(-zeta * omega *
                                                                             math.pi / wd)),
                                              rel=1e-3)
    assert m["decay_rate_1_per_s"] == pytest.approx(zeta * omega, rel=1e-2)


def test_errors_are_signed_relative_differences_against_the_fe():
    time = np.arange(0, 3.0 + 1e-9, 0.005)
    fe = release(time, 0.02, 2 * math.pi * 3.0, 0.05)
    slow = release(time, 0.022, 2 * math.pi * 2.7, 0.10)
    as3 = lambda s: np.column_stack([0 * s, 0 * s, -s])  # noqa: E731
    out = dynamic_metrics(time, as3(fe), np.array([0, 0, -0.02]),
                          {"calibrated": (as3(slow), np.array([0, 0, -0.022]))},
                          {"calibrated": 0.3})
    m = out["calibrated"]
    assert m["period_error"] == pytest.approx(3.0 / 2.7 * math.sqrt((1 - 0.05 ** 2) /
                                                                    (1 - 0.1 ** 2)) - 1,
                                              abs=5e-3)
    assert m["decay_rate_error"] == pytest.approx(0.1 * 2.7 / (0.05 * 3.0) - 1, rel=2e-2)
    assert m["first_peak_error"] > 0.0  # a larger static sag swings deeper despite more damping
    assert m["rms_error"] == 0.3
    assert out["direction"] == [0.0, 0.0, -1.0]


def test_the_fe_p2_consistent_mass_condensed_onto_the_vertices_is_the_lumped_mass():
    """Why there is no FE-like mass option: the P2 consistent mass's row sums are -1/20 of the
    tet's mass at each vertex and 1/5 at each mid-edge node (exact, from the closed form
    int l1^a l2^b l3^c l4^d = a! b! c! d! 3! V/(a+b+c+d+3)!); split between its two ends,
    a vertex gets -1/20 + 3 x 1/10 = 1/4: the lumped masses the particle model already
    uses. (P1 row sums are 1/4 too.)"""
    from math import factorial

    def integral(powers):  # of prod l_i^p_i over a tet, per unit volume
        return (np.prod([factorial(p) for p in powers]) * factorial(3)
                / factorial(sum(powers) + 3))
    # row sum of node i = int phi_i (sum_j phi_j = 1): vertex l(2l - 1), edge 4 l_a l_b
    vertex = 2 * integral([2, 0, 0, 0]) - integral([1, 0, 0, 0])
    edge = 4 * integral([1, 1, 0, 0])
    assert vertex == pytest.approx(-1 / 20, rel=1e-14)
    assert edge == pytest.approx(1 / 5, rel=1e-14)
    assert 4 * vertex + 6 * edge == pytest.approx(1.0, rel=1e-14)
    assert vertex + 3 * edge / 2 == pytest.approx(1 / 4, rel=1e-14)  # = the lumped share


def test_the_gravity_stage_runs_a_model_with_the_volume_term(tmp_path):
    """The gravity stage's run of a model with kv: the static sag and the release complete
    (the step chosen and verified for the release's strain and volume ranges), the volume
    term stiffens the sag, and the metrics of the release are finite."""
    import dataclasses

    from calibration.synthetic import box_scene
    from forcecal.problem import build_problem
    from calibration.gravity_check import gravity_outcome
    from tests.test_calibration_fit import TRUE_GLOBAL

    scene = box_scene(tmp_path, particle={"volume": True},
                      test_points={"n_calibration": 4, "n_held_out": 8})
    problem = build_problem(scene)
    times = np.arange(0.0, 1.0 + 1e-9, 0.01)
    n = len(problem.mesh.edges)
    runs = {}
    for kv in (0.0, 20000.0):
        params = dataclasses.replace(TRUE_GLOBAL, kv=kv).connector_params(n)
        runs[kv], failure = gravity_outcome(scene, problem, params, times, (-0.3, 0.3),
                                            "calibrated")
        assert failure is None
    sag = {kv: np.abs(r.static_displacement).max() for kv, r in runs.items()}
    assert 0 < sag[20000.0] < sag[0.0]
    assert runs[20000.0].dt < runs[0.0].dt  # a stiffer model takes a smaller stable step
    node = int(np.argmax(np.abs(runs[0.0].static_displacement[:, 2])))
    metrics = signal_metrics(times, runs[20000.0].displacement[:, node], np.array([0, 0, -1.0]),
                             runs[20000.0].static_displacement[node])
    assert np.isfinite(metrics["period_s"]) and metrics["first_peak_m"] > 0


def two_mode_release(time, rng, noise=0.0):
    """(S, 40, 3) release of a body whose 40 vertices swing in two modes 5.0 / 5.5 Hz apart by
    10 % (decay 0.5 / 0.3 1/s, random shapes, 8 and 6 mm at vertex 0) about a static sag, plus
    a weak 14 Hz mode (1 mm) and ``noise`` x 10 mm of white noise."""
    shapes = rng.standard_normal((3, 40, 3))
    shapes /= np.linalg.norm(shapes[:, 0], axis=1)[:, None, None]  # unit motion at vertex 0
    out = np.broadcast_to(rng.standard_normal((40, 3)) * 0.02, (len(time), 40, 3)).copy()
    for shape, f, d, a in zip(shapes, (5.0, 5.5, 14.0), (0.5, 0.3, 1.0), (0.008, 0.006, 0.001)):
        out -= a * np.exp(-d * time)[:, None, None] * np.cos(2 * math.pi * f * time)[:, None,
                                                                                    None] * shape
    return out + noise * 0.01 * rng.standard_normal(out.shape)


def test_release_modes_separates_two_close_modes_the_dominant_period_blends():
    """Two modes 0.5 Hz apart in a 3 s record sampled every 5 ms (as the FE records): the
    matrix pencil recovers frequencies, decay rates and amplitudes to round-off noise-free
    (the signal is exactly a sum of damped modes: measured 1e-13, asserted 1e-8), and with
    0.1 mm of white noise (1 % of the swing) the frequencies within 1e-3 (measured 2e-6:
    3,600 channel samples average the noise out); the dominant period of the first 1.5 s
    (0.67 Hz resolution) sees one blended peak between them (4.95 Hz)."""
    from pipelines.dynamics import dominant_period, release_modes
    time = np.arange(0, 3.0 + 1e-9, 0.005)
    rng = np.random.default_rng(7)
    history = two_mode_release(time, rng)
    modes = release_modes(time, history, 0)
    assert [m["frequency_hz"] for m in modes] == pytest.approx([5.0, 5.5], rel=1e-8)
    assert [m["decay_rate_1_per_s"] for m in modes] == pytest.approx([0.5, 0.3], rel=1e-8)
    assert [m["amplitude_m"] for m in modes] == pytest.approx([0.008, 0.006], rel=1e-8)
    noisy = release_modes(time, two_mode_release(time, np.random.default_rng(7), 0.01), 0)
    assert [m["frequency_hz"] for m in noisy] == pytest.approx([5.0, 5.5], rel=1e-3)
    blend = 1.0 / dominant_period(time, history[:, 0, 2])
    assert 5.0 - 0.2 < blend < 5.5 + 0.2  # one peak, not two


def test_mode_frequency_errors_pair_the_modes_in_order_of_frequency():
    time = np.arange(0, 3.0 + 1e-9, 0.005)
    fe = [{"frequency_hz": 5.0}, {"frequency_hz": 5.5}]
    model = [{"frequency_hz": 4.5}, {"frequency_hz": 5.5 * 1.1}]
    s = release(time, 0.02, 2 * math.pi * 5.0, 0.05)
    h = np.column_stack([0 * s, 0 * s, -s])
    out = dynamic_metrics(time, h, np.array([0, 0, -0.02]), {"calibrated": (h, h[-1])},
                          modes={"fe": fe, "calibrated": model})
    assert out["fe"]["modes"] == fe
    assert out["calibrated"]["mode_frequency_errors"] == pytest.approx([-0.1, 0.1], rel=1e-12)


def test_a_body_at_rest_has_no_modes():
    from pipelines.dynamics import release_modes
    time = np.arange(0, 3.0 + 1e-9, 0.005)
    assert release_modes(time, np.zeros((len(time), 5, 3)), 0) == []
