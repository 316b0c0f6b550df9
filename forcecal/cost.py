"""What a scene will cost, estimated before any expensive work; absurd work is refused.

The unit of the FE side is a *vertex-step* (one load or time step of one
experiment, times the mesh's vertices: a Newton solve costs about that much);
the particle side's is a *connector-step* (one explicit step of one connector).
The default liver's whole reference is about 7e5 vertex-steps (5 min on 2
cores); its gravity release with ``particle.dt = "auto"`` about 1e8
connector-steps. The limits below are some thousand times that: a scene above
them would run for days, which is a typo (``indentation.steps = 10000000``,
``particle.dt = 1e-9``) far more often than an intention. The message gives
the estimate and the key to change.
"""
from __future__ import annotations

import math

from forcecal.errors import SceneError
from forcecal.scene import Scene

#: largest FE reference accepted [vertex-steps] (~ a day on one core at the measured rate)
FE_LIMIT = 2e8
#: largest particle gravity release accepted [connector-steps] (both models together)
PARTICLE_LIMIT = 1e11
#: core-seconds per FE vertex-step measured on the default liver (P2, 2 cores: 5 min)
FE_SECONDS_PER_VERTEX_STEP = 8e-4


def n_test_points(scene: Scene) -> int:
    """Calibration + held-out points the scene asks for."""
    tp = scene.test_points
    n_cal = tp.n_calibration if isinstance(tp.calibration, str) else len(tp.calibration)
    n_held = tp.n_held_out if isinstance(tp.held_out, str) else len(tp.held_out)
    return n_cal + n_held


def fe_work(scene: Scene, n_vertices: int) -> dict[str, float]:
    """Vertex-steps of each FE experiment the scene runs (``experiments``), keyed by the
    scene key that sets its step count."""
    points = n_test_points(scene)
    r, g = scene.relaxation, scene.gravity
    work = {"indentation": ("indentation.steps", scene.indentation.steps * points),
            "relaxation": ("relaxation.hold_steps", (r.ramp_steps + r.hold_steps) * points),
            "gravity_dynamic": ("gravity.fe_dt", math.ceil(g.duration / g.fe_dt)),
            "gravity_static": ("gravity.static_load_steps", g.static_load_steps)}
    return {key: steps * n_vertices for experiment, (key, steps) in work.items()
            if experiment in scene.experiments}


def particle_work(scene: Scene, n_connectors: int) -> dict[str, float]:
    """Connector-steps of the particle gravity release (calibrated + baseline models) when
    ``particle.dt`` is a number (``"auto"`` is the stability limit: bounded by construction)."""
    dt = scene.particle.dt
    if isinstance(dt, str) or "gravity_dynamic" not in scene.experiments:
        return {}
    return {"particle.dt": 2.0 * scene.gravity.duration / dt * n_connectors}


def check_cost(scene: Scene, n_vertices: int, n_connectors: int) -> None:
    """Refuse a scene whose estimated work exceeds :data:`FE_LIMIT` or :data:`PARTICLE_LIMIT`.

    Raises:
        SceneError: with the estimate, its largest term and the key that sets it.
    """
    for side, work, limit, unit in (("FE reference", fe_work(scene, n_vertices), FE_LIMIT,
                                     "vertex-steps"),
                                    ("particle gravity release",
                                     particle_work(scene, n_connectors), PARTICLE_LIMIT,
                                     "connector-steps")):
        total = sum(work.values())
        if total <= limit:
            continue
        key = max(work, key=work.get)
        hours = (f" (about {total * FE_SECONDS_PER_VERTEX_STEP / 3600:.3g} core-hours)"
                 if side == "FE reference" else "")
        raise SceneError(f"{scene.path or 'scene'}: the {side} would take about {total:.3g} "
                         f"{unit}{hours}, above the limit of {limit:.3g}; most of it comes "
                         f"from {key} = {_value(scene, key)}: change {key}")


def _value(scene: Scene, key: str):
    section, _, name = key.partition(".")
    return getattr(getattr(scene, section), name)
