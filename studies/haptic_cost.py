"""The haptic step's time per call with springs only, the elastic and the viscoelastic volume term.

:meth:`particle.haptics.HapticSession.step` (1 ms of simulated time per call, one thread,
``dt_safety`` x the rigorous stable step) over the bench's 1000-call drag
(:func:`pipelines.bench.particle_engine.haptic_drag`: the top vertex pushed 5 mm down over
0.25 s, then held) on the default liver with the bench's uniform parameters
(:func:`pipelines.bench.particle_engine.scene_model`), ``--reps`` times per variant:

* ``springs``: springs + arms, no volume term;
* ``volume``: with the elastic volume term at the bench's kv
  (:data:`pipelines.bench.haptic.VOLUME_KV`);
* ``viscoelastic``: the same kv with Maxwell arms at the material's Prony ratios
  (``kv_i = g_i/g_inf kv``, the Prony times), only where the code has them.

Per variant: the substeps per call and, per repetition, the minimum, median and 99th
percentile of the wall time per call and the process CPU time per call [us], with the load
average before and after. The module imports only what every version of the haptic step
has, so the same measurement runs on another checkout first on ``PYTHONPATH`` (``--label``
names it); alternate the two, as timings on a shared machine drift.

``python -m studies.haptic_cost --label LABEL [--reps 5] [--out
runs/studies/haptic_cost_LABEL.json]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from studies.viscoelastic_volume import write_json

SCENE = Path("scenes/liver.toml")
DOWN = np.array([0.0, 0.0, -1.0])


def variants(scene) -> dict[str, Any]:
    """The models timed (module docstring), by name."""
    from pipelines.bench import particle_engine as pb
    from pipelines.bench.haptic import VOLUME_KV

    springs = pb.scene_model(scene)
    kv = np.array([VOLUME_KV])
    out = {"springs": springs,
           "volume": springs.with_params(dataclasses.replace(springs.params, kv=kv))}
    fields = {f.name for f in dataclasses.fields(springs.params)}
    if "kv1" in fields:  # a checkout with the viscoelastic volume term
        g, tau = scene.material.prony_g, scene.material.prony_tau
        ratio = [gi / (1.0 - sum(g)) for gi in g]
        arms = {"kv1": ratio[0] * kv, "bv1": tau[0] * ratio[0] * kv, "kv2": ratio[1] * kv,
                "bv2": tau[1] * ratio[1] * kv}
        out["viscoelastic"] = springs.with_params(dataclasses.replace(springs.params, kv=kv,
                                                                      **arms))
    return out


def measure(reps: int, calls: int = 1000) -> dict[str, Any]:
    """Every variant's timings (module docstring)."""
    import numba

    from forcecal.scene import load_scene
    from pipelines.bench import particle_engine as pb
    from particle.stability import critical_time_step

    numba.set_num_threads(1)
    scene = load_scene(SCENE)
    rows = {}
    load = [os.getloadavg()[0]]
    for name, model in variants(scene).items():
        tool = int(np.argmax(np.where(model.fixed, -np.inf, model.rest_positions[:, 2])))
        dt = pb.DT_SAFETY * critical_time_step(model)
        runs = []
        for _ in range(reps):
            drag = pb.haptic_drag(model, tool, DOWN, dt, calls=calls)
            us = drag["latencies_us"]
            runs.append({"min_us": float(us.min()), "median_us": float(np.median(us)),
                         "p99_us": float(np.percentile(us, 99)), "cpu_us": drag["cpu_us"]})
        rows[name] = {"substeps": drag["substeps"], "dt_s": drag["dt_s"], "runs": runs,
                      "median_of_medians_us": float(np.median([r["median_us"] for r in runs])),
                      "median_cpu_us": float(np.median([r["cpu_us"] for r in runs])),
                      "min_us": float(min(r["min_us"] for r in runs))}
        load.append(os.getloadavg()[0])
    return {"scene": str(SCENE), "calls": calls, "reps": reps, "variants": rows,
            "load_average": load, "cpus": os.cpu_count()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m studies.haptic_cost",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--label", required=True, help="names the code measured")
    parser.add_argument("--reps", type=int, default=5, help="drags per variant")
    parser.add_argument("--out", type=Path, help="JSON (default runs/studies/haptic_cost_"
                                                 "<label>.json)")
    args = parser.parse_args(argv)
    out = args.out or Path(f"runs/studies/haptic_cost_{args.label}.json")
    result = {"label": args.label, **measure(args.reps)}
    write_json(out, result)
    for name, row in result["variants"].items():
        print(f"{args.label:8s} {name:13s} substeps {row['substeps']}  median "
              f"{row['median_of_medians_us']:.1f} us  CPU {row['median_cpu_us']:.1f} us  "
              f"min {row['min_us']:.1f} us")
    print(f"load average {', '.join(f'{x:.2f}' for x in result['load_average'])}")


if __name__ == "__main__":
    main()
