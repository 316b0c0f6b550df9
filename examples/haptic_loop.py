"""A 1 kHz haptic loop on a calibrated organ: push, hold, print the force and the step time.

A haptic device calls the simulation every millisecond with the tool's position and renders
the force it gets back. Here the tool holds one particle of the calibrated model (the first
held-out test point: a vertex the calibration never fitted) and pushes it ``--depth`` along
its inward normal over the first quarter of the calls, then holds it there. Each call is
one :meth:`particle.HapticSession.step` (1 ms of simulated time in a few explicit
substeps); its wall time is what a device loop must fit in 1 ms.

The force follows the model's own ramp-and-hold (relaxation) curve on the same schedule,
and while the tool is held the Maxwell arms relax towards the model's static indentation
force at that depth (the long-term curve the calibration fitted): the last lines compare.

    python examples/haptic_loop.py --params runs/liver/params.h5
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import forcecal
from particle import (HapticSession, IndentationEvaluator, RelaxationEvaluator,
                      critical_time_step)
from pipelines.realtime import session_strain_range

PERIOD = 1e-3  # s: the device's period


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--params", required=True, help="params.h5 of a calibration")
    parser.add_argument("--calls", type=int, default=2000, help="device periods (1 ms each)")
    parser.add_argument("--depth", type=float, default=0.002, help="push depth [m]")
    args = parser.parse_args(argv)

    calibrated = forcecal.load_calibrated(args.params)
    model, problem = calibrated.model, calibrated.problem
    k = len(problem.calibration) if len(problem.held_out) else 0
    tool, normal = int(problem.test_points[k]), problem.normals[k]

    # the explicit step: 0.9 x the rigorous stability limit over the strains the session
    # allows (+-0.5, cut short of where a calibrated spring would lose its stiffness)
    strain_range = session_strain_range(model.params)
    dt = 0.9 * critical_time_step(model, strain_range=strain_range)
    session = HapticSession(model, dt, period=PERIOD, strain_range=strain_range)
    print(f"{model.n_particles} particles, {model.n_connectors} connectors, volume term "
          f"{calibrated.volume or 'off'}; {session.substeps} substeps of "
          f"{session.dt * 1e6:.1f} us per {PERIOD * 1e3:g} ms call; tool: particle {tool}")

    start = model.rest_positions[tool]
    session.step(tool, start)  # the first call compiles the kernels: not timed
    forces = np.empty((args.calls, 3))
    step_us = np.empty(args.calls)
    ramp = args.calls // 4
    for call in range(args.calls):
        depth = args.depth * min(1.0, (call + 1) / ramp)
        t0 = time.perf_counter()
        forces[call] = session.step(tool, start + depth * normal)
        step_us[call] = 1e6 * (time.perf_counter() - t0)
        if (call + 1) % (args.calls // 8) == 0:
            print(f"t = {(call + 1) * PERIOD:5.3f} s  depth {depth * 1e3:4.2f} mm  "
                  f"force on the tool {forces[call] @ normal:+8.4f} N along the normal  "
                  f"step {step_us[call]:6.1f} us")
    print(f"step time per call: median {np.median(step_us):.1f} us, "
          f"p99 {np.percentile(step_us, 99):.1f} us, max {step_us.max():.1f} us")

    # what the force must be: the model's quasi-static ramp-and-hold curve on the same
    # schedule (inertia dropped: it differs from the dynamic loop by the tissue's ringing),
    # and, once every arm has relaxed, its static indentation curve at the held depth
    ramp_s, end_s = ramp * PERIOD, args.calls * PERIOD
    times = np.concatenate([np.linspace(ramp_s / 8, ramp_s, 8),
                            ramp_s + (end_s - ramp_s) * np.geomspace(1e-2, 1.0, 12)])
    calls = np.unique(np.rint(times / PERIOD).astype(int) - 1)  # the calls ending then
    times = (calls + 1) * PERIOD
    depths = args.depth * np.minimum(1.0, times / ramp_s)
    nodes, normals = np.array([tool]), normal[None]
    curve = RelaxationEvaluator(model, nodes, normals, times, depths,
                                strain_range=calibrated.strain_range)(model.params)[0]
    static = IndentationEvaluator(model, nodes, normals, np.array([args.depth]),
                                  strain_range=calibrated.strain_range)(model.params)[0, -1]
    pushed = -forces[calls] @ normal  # the tissue pushes back: the indenter's force
    print("   t [s]  loop [N]  ramp-and-hold curve [N]")
    for t, f, c in zip(times[::2], pushed[::2], curve[::2]):
        print(f"  {t:6.3f}  {f:8.5f}  {c:8.5f} ({100 * (f / c - 1):+.2f} %)")
    print(f"held at {args.depth * 1e3:g} mm: {pushed[-1]:.5f} N; the static indentation curve "
          f"(every arm relaxed): {static:.5f} N")
    return {"forces": forces, "step_us": step_us, "normal": normal, "tool": tool,
            "times": times, "loop_force": pushed, "curve_force": curve,
            "static_force": float(static), "substeps": session.substeps, "dt": session.dt}


if __name__ == "__main__":
    main(sys.argv[1:])
