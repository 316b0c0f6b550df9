"""How much of the haptic step's p99 is the machine's, and how much the step's?

The haptic goals are p99 call times of the exact step (``runs/bench/bench.json``
``haptic_scale``). A call that a periodic interruption of the core (the kernel's timer
tick, a hypervisor's exit) hits takes longer, by the interruption itself and by what the
step then reloads of its working set from further out in the cache hierarchy. The p99 of
calls that long therefore carries a part that no kernel change removes but a smaller or
faster step does.

Per mesh (the bench's haptic meshes, springs + arms, float64, the default session's
substeps), ``calls`` timed calls of the bench's drag (:func:`pipelines.bench.particle_engine
.haptic_drag`), against two compiled controls timed call by call the same way, each sized to
the step's median time:

* ``compute``: arithmetic on a few registers (no working set);
* ``memory``: read-modify-write passes over an array of the step's working set (the bytes of
  the arrays a substep touches).

For each: median, p99 and p99.9 [us], the share of calls more than 30 us over the median and
the median time between two such calls [ms] (a periodic interruption shows as a steady
spacing). The step's p99 over its median, against the controls', is what its working set
adds to the machine's own tail.

``python -m studies.haptic_tail [--meshes 2] [--calls 10000] [--out
runs/studies/haptic_tail.json]`` (about 1 min with two meshes; an idle machine: another
process on the core is another interruption).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numba import njit

SCENE = Path("scenes/liver.toml")
DEPTH = 0.005  # m: the bench's drag
SLOW_US = 30.0  # a call this much over the median counts as interrupted


@njit(cache=True)
def compute_work(n: int) -> float:
    """``n`` dependent multiply-adds on registers (no memory traffic); returns the result so
    the loop is not removed."""
    s = 0.5
    for _ in range(n):
        s = s * 0.999999 + 1e-7
    return s


@njit(cache=True)
def memory_work(buffer: np.ndarray, passes: int) -> float:
    """``passes`` read-modify-write sweeps over ``buffer`` (float64) [1]; returns a sum."""
    total = 0.0
    for _ in range(passes):
        for k in range(buffer.shape[0]):
            buffer[k] = buffer[k] * 0.5 + 1.0
        total += buffer[0]
    return total


def timed_calls(call: Callable[[], object], calls: int) -> np.ndarray:
    """(calls,) wall times [us] of ``call``, after one untimed call."""
    call()
    out = np.empty(calls)
    for k in range(calls):
        t0 = time.perf_counter()
        call()
        out[k] = time.perf_counter() - t0
    return 1e6 * out


def tail(latencies_us: np.ndarray) -> dict[str, float | None]:
    """Median, p99, p99.9 [us], the share of calls more than :data:`SLOW_US` over the median
    and the median spacing [ms] of those calls in elapsed time (None with fewer than two)."""
    median = float(np.median(latencies_us))
    slow = latencies_us > median + SLOW_US
    ends = np.cumsum(latencies_us) * 1e-3  # ms: when each call ended (calls back to back)
    spacing = np.diff(ends[slow])
    return {"median_us": median, "p99_us": float(np.percentile(latencies_us, 99)),
            "p999_us": float(np.percentile(latencies_us, 99.9)),
            "slow_share": float(slow.mean()),
            "slow_spacing_ms": float(np.median(spacing)) if len(spacing) else None}


def working_set_bytes(model) -> int:
    """Bytes of the arrays one substep of the haptic loop reads or writes: the connectors'
    ends, rest lengths, spring and arm coefficients, arm forces and elongations, and the
    particles' positions (two), forces, masses and inverse masses."""
    e, n = model.n_connectors, model.n_particles
    per_connector = 2 * 8 + 8 + 3 * 8 + 2 * 2 * 8 + 2 * 8 + 8
    per_particle = 3 * 3 * 8 + 2 * 8
    return e * per_connector + n * per_particle


def sized(run: Callable[[int], object], target_us: float, start: int) -> int:
    """The size argument of ``run`` whose median call time is ``target_us`` [us] (two
    rounds of proportional scaling from ``start``)."""
    size = start
    for _ in range(3):
        median = float(np.median(timed_calls(lambda: run(size), 200)))
        size = max(1, round(size * target_us / median))
    return size


def measure(meshes: int, calls: int) -> dict[str, Any]:
    """Every mesh's step and its controls (module docstring)."""
    from forcecal.scene import load_scene
    from pipelines.bench import haptic as bh
    from pipelines.bench import particle_engine as pb

    scene = load_scene(SCENE)
    rows = []
    for name, length in bh.MESHES[False][:meshes]:
        model, mesh, fixed = bh._mesh_model(scene, length)
        substeps = bh._default_substeps(model)
        tool = int(np.argmax(model.rest_positions[:, 2]))
        drag = pb.haptic_drag(model, tool, np.array([0.0, 0.0, -1.0]), 1e-3 / substeps,
                              calls=calls, depth=DEPTH)
        step = tail(drag["latencies_us"])
        target = step["median_us"]
        n = sized(compute_work, target, 10_000)
        compute = tail(timed_calls(lambda: compute_work(n), calls))
        nbytes = working_set_bytes(model)
        buffer = np.ones(nbytes // 8)
        passes = sized(lambda p: memory_work(buffer, p), target, substeps)
        memory = tail(timed_calls(lambda: memory_work(buffer, passes), calls))
        rows.append({"mesh": name, "connectors": model.n_connectors,
                     "particles": model.n_particles, "substeps": substeps,
                     "working_set_bytes": nbytes, "memory_passes": passes, "step": step,
                     "compute": compute, "memory": memory})
        for label, t in (("step", step), ("compute", compute), ("memory", memory)):
            spacing = t["slow_spacing_ms"]
            print(f"{name:10s} {label:8s} median {t['median_us']:7.1f} us, p99 "
                  f"{t['p99_us']:7.1f} us (+{t['p99_us'] - t['median_us']:5.1f}), p99.9 "
                  f"{t['p999_us']:7.1f} us; {100 * t['slow_share']:.2f} % of calls > median + "
                  f"{SLOW_US:g} us, every {'-' if spacing is None else f'{spacing:.2f}'} ms",
                  flush=True)
    return {"scene": SCENE.stem, "calls": calls, "depth_m": DEPTH, "slow_us": SLOW_US,
            "load_average": list(os.getloadavg()), "rows": rows}


def main(argv: list[str] | None = None) -> int:
    from studies.viscoelastic_volume import write_json

    ap = argparse.ArgumentParser(prog="python -m studies.haptic_tail",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", type=int, default=2, help="how many of the bench's haptic "
                    "meshes, smallest first (default 2: the liver and its 12k-connector mesh)")
    ap.add_argument("--calls", type=int, default=10_000, help="timed calls per row")
    ap.add_argument("--out", type=Path, default=Path("runs/studies/haptic_tail.json"))
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    result = measure(args.meshes, args.calls)
    result["command"] = (f"python -m studies.haptic_tail --meshes {args.meshes} --calls "
                         f"{args.calls}")
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
