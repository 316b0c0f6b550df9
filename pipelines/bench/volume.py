"""Bench study "volume term": haptic step time with the volume term vs springs only.

``study(scene, cache_folder, quick)`` returns the bench.json key ``volume_haptic``:
for the scene's liver (its mesh and fixed base) and the large liver of the
particle-engine item (``pipelines.bench.particle_engine.LARGE_MESH_LENGTH``, ~12k
connectors), the latency of :meth:`particle.haptics.HapticSession.step` (1 ms per
call, median and p99 over the calls,
:func:`pipelines.bench.particle_engine.haptic_latency`; and the CPU time per call,
:func:`cpu_per_call`, which a busy machine disturbs less) with the uniform
benchmark springs alone and with the volume term added at ``kv`` = the spring
network's bulk modulus (:func:`particle.volume.network_bulk_modulus`, the paper
fit's starting value; ``kv_ratio`` says how many times that). Each session takes
its own largest stable step (``pipelines.bench.particle_engine.DT_SAFETY`` x the stability limit
over the default strain range +-0.5), so the ratio includes both the extra work
per substep and the extra substeps the volume term's stiffness needs. Goal: <= 1.5.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.scene import Scene

KV_RATIO = 1.0
GOAL_RATIO = 1.5


def with_volume(model, kv_ratio: float = KV_RATIO):
    """The model with kv = ``kv_ratio`` x its spring network's bulk modulus on every tet."""
    from particle.volume import network_bulk_modulus

    kv = kv_ratio * network_bulk_modulus(model, float(np.mean(model.params.K0)))
    return model.with_params(dataclasses.replace(model.params, kv=np.full(model.n_tets, kv))), kv


def cpu_per_call(model, node: int, normal: np.ndarray, calls: int) -> dict[str, Any]:
    """CPU time [us] per :meth:`HapticSession.step` over ``calls`` calls (process time: on a
    shared machine it counts this process's work only, not the time it waited for a core),
    the step and substeps as :func:`pipelines.bench.particle_engine.haptic_latency` takes them."""
    import time

    from pipelines.bench import particle_engine as pb
    from particle.haptics import HapticSession
    from particle.stability import critical_time_step

    session = HapticSession(model, pb.DT_SAFETY * critical_time_step(model))
    start = model.rest_positions[node]
    session.step(node, start)  # compile outside the clock
    cpu = time.process_time()
    for k in range(calls):
        session.step(node, start + 0.005 * min(1.0, k / (calls / 4)) * normal)
    return {"substeps": session.substeps,
            "cpu_us_per_call": 1e6 * (time.process_time() - cpu) / calls}


def study(scene: Scene, cache_folder: Path, quick: bool) -> dict[str, Any]:
    import numba

    from forcecal.liver_mesh import generate_liver
    from forcecal.problem import build_problem
    from pipelines.bench import particle_engine as pb

    numba.set_num_threads(1)
    problem = build_problem(scene)
    large_mesh = generate_liver(0.012 if quick else pb.LARGE_MESH_LENGTH)
    cases = {"liver": (pb.scene_model(scene, problem.mesh, problem.fixed),
                       int(problem.test_points[0]), problem.normals[0], 500 if quick else 2000),
             "large": (pb.scene_model(scene, large_mesh), int(np.argmax(large_mesh.vertices[:, 2])),
                       np.array([0.0, 0.0, -1.0]), 200 if quick else 1000)}
    out: dict[str, Any] = {"load_average_start": os.getloadavg()[0], "goal_ratio": GOAL_RATIO,
                           "kv_ratio": KV_RATIO}
    for name, (model, node, normal, calls) in cases.items():
        volume, kv = with_volume(model)
        springs = pb.haptic_latency(model, node, normal, calls=calls)
        both = pb.haptic_latency(volume, node, normal, calls=calls)
        cpu_springs = cpu_per_call(model, node, normal, calls)
        cpu_both = cpu_per_call(volume, node, normal, calls)
        out[name] = {"connectors": model.n_connectors, "tets": model.n_tets, "kv_pa": kv,
                     "springs": {**springs, **cpu_springs}, "volume": {**both, **cpu_both},
                     "ratio_median": both["median_us"] / springs["median_us"],
                     "ratio_cpu": cpu_both["cpu_us_per_call"] / cpu_springs["cpu_us_per_call"],
                     "ratio_cpu_per_substep": (cpu_both["cpu_us_per_call"] / cpu_both["substeps"])
                     / (cpu_springs["cpu_us_per_call"] / cpu_springs["substeps"])}
    out["load_average_end"] = os.getloadavg()[0]
    return {"volume_haptic": out}
