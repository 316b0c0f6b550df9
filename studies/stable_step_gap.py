"""How many haptic substeps could a tighter rigorous stability bound save?

The haptic loop advances 1 ms per call in ``ceil(1 ms / (dt_safety x dt_bound))`` substeps,
``dt_bound`` the rigorous stable step of :func:`particle.stability.critical_time_step` over
the strains the run verifies. A bound valid on a range of states that holds the rest state
is valid at rest, so it can never exceed the **exact** stable step at rest, ``2 /
omega_max``, ``omega_max^2`` the largest eigenvalue of ``M^-1/2 K M^-1/2`` with ``K`` the
instantaneous tangent at rest (springs ``K0 + k1 + k2``, volume term ``kv + kv1 + kv2``: an
arm's stiffness in a Verlet step, ``k b / (k dt + b)``, is below ``k``) and ``M`` the lumped
masses of the free particles. Its substeps are therefore the fewest any rigorous bound, however
tight, can give a session that starts at rest.

Per mesh (the bench's haptic meshes, :data:`pipelines.bench.haptic.MESHES`) and terms
(springs + arms, with the elastic and with the relaxing volume term at the bench's kv,
:func:`pipelines.bench.haptic.volume_model`): the bound over the default strain range
(+-0.5, the float64 default session), over a band of +-0.05 about rest (what the "state's
strains" session verifies at the start), and the exact step at rest, each with its substeps
per 1 ms at the scene's ``dt_safety``.

``python -m studies.stable_step_gap [--meshes 2] [--out runs/studies/stable_step_gap.json]``
(about 10 s with two meshes, 1 min with three).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

SCENE = Path("scenes/liver.toml")
PERIOD = 1e-3  # s: one haptic call
BAND = 0.05  # the "state's strains" session's half-width (pipelines.bench.haptic.BAND)


def exact_rest_step(model) -> float:
    """``2 / omega_max`` [s] of ``model`` at rest (module docstring): its instantaneous
    tangent's largest eigenvalue over the lumped masses of the free particles."""
    import scipy.sparse.linalg as sla

    from particle.body import RestOperators

    ops = RestOperators.of(model)
    stiffness = ops.stiffness(model, "instantaneous").tocsc()
    scale = 1.0 / np.sqrt(ops.mass)
    a = stiffness.multiply(scale[:, None]).multiply(scale[None, :]).tocsc()
    largest = float(sla.eigsh(a, k=1, which="LA", return_eigenvectors=False, tol=1e-10)[0])
    return 2.0 / math.sqrt(largest)


def substeps(dt: float, safety: float) -> int:
    """Substeps per haptic period at ``safety`` x the stable step ``dt`` [s]."""
    from particle.haptics import substeps_per_period

    return substeps_per_period(PERIOD, safety * dt)


def measure(meshes: int) -> dict[str, Any]:
    """Every mesh's and term's steps (module docstring)."""
    from forcecal.scene import load_scene
    from pipelines.bench import haptic as bh
    from particle.stability import critical_time_step

    scene = load_scene(SCENE)
    safety = scene.particle.dt_safety
    prony = (scene.material.prony_g, scene.material.prony_tau)
    rows = []
    for name, length in bh.MESHES[False][:meshes]:
        base, _, _ = bh._mesh_model(scene, length)
        for terms, model in ((bh.SPRINGS, base), (bh.VOLUME, bh.volume_model(base, bh.VOLUME_KV)),
                             (bh.RELAXING, bh.volume_model(base, bh.VOLUME_KV, prony))):
            steps = {"bound_default_s": critical_time_step(model),
                     "bound_band_s": critical_time_step(model, strain_range=(-BAND, BAND)),
                     "exact_rest_s": exact_rest_step(model)}
            row = {"mesh": name, "terms": terms, "connectors": model.n_connectors,
                   "particles": model.n_particles, **steps}
            for key, dt in steps.items():
                row[key.replace("_s", "_substeps")] = substeps(dt, safety)
            row["band_over_exact"] = steps["bound_band_s"] / steps["exact_rest_s"]
            rows.append(row)
            print(f"{name:10s} {terms:34s} bound +-0.5 {1e3 * steps['bound_default_s']:.3f} ms "
                  f"({row['bound_default_substeps']}), band +-{BAND} "
                  f"{1e3 * steps['bound_band_s']:.3f} ms ({row['bound_band_substeps']}), exact "
                  f"at rest {1e3 * steps['exact_rest_s']:.3f} ms ({row['exact_rest_substeps']})",
                  flush=True)
    return {"scene": SCENE.stem, "dt_safety": safety, "period_s": PERIOD, "band": BAND,
            "volume_kv_pa": bh.VOLUME_KV, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    from studies.viscoelastic_volume import write_json

    ap = argparse.ArgumentParser(prog="python -m studies.stable_step_gap",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", type=int, default=3, help="how many of the bench's haptic "
                    "meshes, smallest first (default: all three)")
    ap.add_argument("--out", type=Path, default=Path("runs/studies/stable_step_gap.json"))
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    result = measure(args.meshes)
    result["command"] = f"python -m studies.stable_step_gap --meshes {args.meshes}"
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
