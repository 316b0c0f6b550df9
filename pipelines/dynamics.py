"""Dynamics metrics of the gravity release at the tracked vertex: period, first peak, decay.

The RMS error of the tracked vertex's history (``gravity_dynamic`` in
``report.json``) mixes every way two oscillations can differ. These metrics
separate them. The history ``u(t)`` (S, 3) [m] is projected on the direction
``e`` of the FE's static sag of that vertex, ``s(t) = u(t) . e``; released from
rest in the undeformed shape, ``s`` oscillates about the static sag ``s_eq``
(the model's own) with a decaying amplitude:

* ``period_s``: ``1/f`` (None if ``s`` does not oscillate) with ``f`` the dominant
  frequency of ``s - mean`` over
  the first :data:`WINDOW_S` seconds (Hann window, zero-padded FFT, parabolic
  interpolation of the log magnitude around the peak bin);
* ``first_peak_m``: the first local maximum of ``s`` (the deepest point of
  the first swing, about twice the static sag when the damping is light),
  parabolically interpolated between samples;
* ``decay_rate_1_per_s``: ``-slope`` of the least-squares line through
  ``log |s(t_k) - s_eq|`` at the extrema t_k of ``s`` (maxima and minima) over
  the whole record, i.e. the amplitude's exponential rate (zeta omega for a
  damped oscillator); None when fewer than two extrema rise above the noise.

The dominant period is a blend when two modes of similar frequency and amplitude carry the
swing (the default liver's overhanging lobe: 5.09 and 5.57 Hz, 9 mm each at its tip, 0.48 Hz
apart - closer than the 0.67 Hz resolution of a 1.5 s window): the blend can match while both
modes are 7-9 % off, and the RMS error then measures their beat. So :func:`release_modes` also
identifies the modes of the whole body's release (``modes``: frequency, decay rate and amplitude
at the tracked vertex of the :data:`N_MODES` modes that carry most of its motion) and the errors
of their frequencies (``mode_frequency_errors``, paired in order of frequency).

Errors are signed relative differences ``particle/FE - 1``.
"""

from __future__ import annotations

import math

import numpy as np

WINDOW_S = 1.5  # the period is measured on the first 1.5 s, before the two modes' beat blurs it
PAD = 16  # zero padding factor of the FFT (finer bins for the parabolic interpolation)
NOISE = 1e-3  # extrema closer to the equilibrium than this fraction of the first swing are dropped
N_MODES = 2  # modes reported per history: the ones with the largest amplitude at the tracked vertex
# release_modes: principal components of the body's history the poles are fitted to, and poles
# fitted (complex pairs count twice); on the liver releases 8 to 16 poles gave the same two
# leading modes to 0.1 %, 20 began to split them
CHANNELS = 8
MODEL_ORDER = 12


def dominant_period(time: np.ndarray, signal: np.ndarray, window: float = WINDOW_S) -> float:
    """Period [s] of the dominant frequency of ``signal`` (S,) over ``time <= window`` [s]
    (uniformly sampled from the first time); inf if the signal does not oscillate."""
    keep = time <= time[0] + window + 1e-12
    s = signal[keep] - signal[keep].mean()
    if len(s) < 4 or not np.any(s):
        return math.inf
    dt = float(np.mean(np.diff(time[keep])))
    n = PAD * len(s)
    spectrum = np.abs(np.fft.rfft(s * np.hanning(len(s)), n))
    k = int(np.argmax(spectrum[1:])) + 1  # skip the mean
    if k + 1 >= len(spectrum):
        return 2.0 * dt
    a, b, c = np.log(spectrum[k - 1:k + 2] + 1e-300)
    shift = 0.5 * (a - c) / (a - 2.0 * b + c) if (a - 2.0 * b + c) < 0 else 0.0
    frequency = (k + shift) / (n * dt)
    return 1.0 / frequency if frequency > 0 else math.inf


def _parabolic_peak(time: np.ndarray, s: np.ndarray, i: int) -> tuple[float, float]:
    """(time, value) of the parabola through samples i-1, i, i+1 at its vertex."""
    a, b, c = s[i - 1], s[i], s[i + 1]
    curvature = a - 2.0 * b + c
    shift = 0.5 * (a - c) / curvature if curvature != 0.0 else 0.0
    dt = time[i + 1] - time[i]
    return float(time[i] + shift * dt), float(b - 0.25 * (a - c) * shift)


def extrema(time: np.ndarray, s: np.ndarray) -> list[tuple[float, float]]:
    """(time, value) of every interior local extremum of ``s`` (S,), parabolically refined."""
    d = np.diff(s)
    idx = np.nonzero(np.sign(d[:-1]) * np.sign(d[1:]) < 0)[0] + 1
    return [_parabolic_peak(time, s, int(i)) for i in idx]


def first_peak(time: np.ndarray, s: np.ndarray) -> float:
    """The first local maximum of ``s`` [m] (the last sample's value if it never turns)."""
    d = np.diff(s)
    turns = np.nonzero((d[:-1] > 0) & (d[1:] <= 0))[0] + 1
    if not len(turns):
        return float(s[-1])
    return _parabolic_peak(time, s, int(turns[0]))[1]


def decay_rate(time: np.ndarray, s: np.ndarray, equilibrium: float) -> float | None:
    """Exponential decay rate [1/s] of the excursions of ``s`` from ``equilibrium`` at its
    extrema (least squares in log), None with fewer than two extrema above :data:`NOISE`."""
    points = extrema(time, s)
    if not points:
        return None
    t = np.array([p[0] for p in points])
    amp = np.abs(np.array([p[1] for p in points]) - equilibrium)
    keep = amp > NOISE * amp.max()
    if keep.sum() < 2:
        return None
    slope = np.polyfit(t[keep], np.log(amp[keep]), 1)[0]
    return float(-slope)


def signal_metrics(time: np.ndarray, history: np.ndarray, direction: np.ndarray,
                   static: np.ndarray) -> dict[str, float | None]:
    """Period, first peak and decay rate of one history (S, 3) [m] along ``direction`` (3,),
    about the static displacement ``static`` (3,) [m]."""
    s = history @ direction
    period = dominant_period(time, s)
    return {"period_s": period if math.isfinite(period) else None,  # None: no oscillation
            "first_peak_m": first_peak(time, s),
            "decay_rate_1_per_s": decay_rate(time, s, float(static @ direction))}


def release_modes(time: np.ndarray, history: np.ndarray, node: int,
                  n_modes: int = N_MODES) -> list[dict[str, float]]:
    """The ``n_modes`` oscillation modes of a whole body's release that carry most of the motion
    of vertex ``node``, in order of frequency.

    Matrix pencil (ESPRIT) on the body's history: its :data:`CHANNELS` leading principal
    components, stacked in a Hankel matrix of ``S/4`` time lags, give :data:`MODEL_ORDER`
    poles ``z = exp((-d + i 2 pi f) dt)``; their complex amplitudes in the vertex's (S, 3)
    history (least squares, with a constant for the equilibrium) rank them.

    Args:
        time: (S,) uniformly spaced sample times [s].
        history: (S, N, 3) displacement of every vertex [m] (or (S, C) channels).
        node: the vertex whose motion ranks the modes.
    Returns:
        Up to ``n_modes`` of {"frequency_hz", "decay_rate_1_per_s", "amplitude_m"} (amplitude:
        the mode's peak displacement at ``node`` at t = 0, ``2 |a|``); only modes with more
        than one cycle in the record count, so fewer when the body barely oscillates.
    """
    if len(time) < 8 * MODEL_ORDER:
        return []
    dt = float(time[1] - time[0])
    if not np.allclose(np.diff(time), dt, rtol=1e-6, atol=0.0):
        raise ValueError("release_modes needs uniformly spaced samples")
    channels = history.reshape(len(time), -1)
    at_node = history[:, node].reshape(len(time), -1)
    centred = channels - channels.mean(axis=0)
    u, sv, _ = np.linalg.svd(centred, full_matrices=False)
    rank = int(np.sum(sv > 1e-12 * sv[0])) if len(sv) and sv[0] > 0 else 0
    lags = len(time) // 4
    if rank == 0:
        return []
    r = min(CHANNELS, rank)
    z = u[:, :r] * sv[:r]
    width = len(time) - lags + 1
    hankel = np.concatenate([z[i:i + width].T for i in range(lags)], axis=0)
    basis = np.linalg.svd(hankel, full_matrices=False)[0][:, :min(MODEL_ORDER, r * lags)]
    shift = np.linalg.lstsq(basis[:-r], basis[r:], rcond=None)[0]
    poles = np.linalg.eigvals(shift)
    poles = poles[np.abs(poles) > 0]
    rates = np.log(poles.astype(complex)) / dt
    frequency, decay = rates.imag / (2 * math.pi), -rates.real
    # a pole and its conjugate are one mode; fewer than one cycle in the record is no mode
    fit = np.column_stack([np.ones(len(time)), np.power.outer(poles, np.arange(len(time))).T])
    amplitude = np.linalg.norm(np.linalg.lstsq(fit, at_node.astype(complex), rcond=None)[0][1:],
                               axis=1)
    modes = np.nonzero(frequency > 1.0 / (time[-1] - time[0]))[0]
    modes = modes[np.argsort(-amplitude[modes])][:n_modes]
    return [{"frequency_hz": float(frequency[k]), "decay_rate_1_per_s": float(decay[k]),
             "amplitude_m": float(2 * amplitude[k])}
            for k in modes[np.argsort(frequency[modes])]]


def _relative(got: float | None, want: float | None) -> float | None:
    if got is None or want is None or want == 0 or not (math.isfinite(got)
                                                         and math.isfinite(want)):
        return None
    return float(got / want - 1.0)


def dynamic_metrics(time: np.ndarray, fe: np.ndarray, fe_static: np.ndarray,
                    models: dict[str, tuple[np.ndarray, np.ndarray]],
                    rms: dict[str, float] | None = None,
                    modes: dict[str, list[dict[str, float]]] | None = None) -> dict[str, dict]:
    """``gravity.dynamic_metrics`` of report.json for the tracked vertex.

    Args:
        time: (S,) sample times [s] from the release at 0.
        fe: (S, 3) FE displacement history [m]; fe_static: (3,) its static sag [m].
        models: name -> (history (S, 3) [m], static sag (3,) [m]) of each particle model.
        rms: name -> the RMS error (``gravity_dynamic``), repeated next to the others.
        modes: "fe" and each name -> its :func:`release_modes`, added as ``modes`` with, for
            the particle models, ``mode_frequency_errors`` (paired in order of frequency).
    Returns:
        {"fe": metrics, name: metrics + ``period_error``, ``first_peak_error``,
        ``decay_rate_error`` (signed, particle/FE - 1) and ``rms_error``}.
    """
    norm = float(np.linalg.norm(fe_static))
    direction = fe_static / norm if norm > 0 else np.array([0.0, 0.0, -1.0])
    out = {"direction": direction.tolist(), "window_s": WINDOW_S,
           "fe": signal_metrics(time, fe, direction, fe_static)}
    if modes is not None:
        out["fe"]["modes"] = modes["fe"]
    for name, (history, static) in models.items():
        m = signal_metrics(time, history, direction, static)
        for key, err in (("period_s", "period_error"), ("first_peak_m", "first_peak_error"),
                         ("decay_rate_1_per_s", "decay_rate_error")):
            m[err] = _relative(m[key], out["fe"][key])
        if rms is not None:
            m["rms_error"] = rms.get(name)
        if modes is not None:
            m["modes"] = modes[name]
            m["mode_frequency_errors"] = [_relative(a["frequency_hz"], b["frequency_hz"])
                                          for a, b in zip(modes[name], modes["fe"])]
        out[name] = m
    return out
