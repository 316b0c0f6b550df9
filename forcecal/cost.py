"""What a scene will cost, estimated before any expensive work; absurd work is refused.

The unit of the FE side is a *vertex-step* (one load or time step of one
experiment, times the mesh's vertices: a Newton solve costs about that much);
the particle side's is a *connector-step* (one explicit step of one connector).
The default liver's whole reference is about 7e5 vertex-steps (about 2 core-minutes;
a vertex-step costs more on bigger meshes: :func:`fe_core_seconds`); its gravity
release with ``particle.dt = "auto"`` about 1e8 connector-steps. The limits below are
some thousand times that: a scene above them would run for days, which is a typo
(``indentation.steps = 10000000``, ``particle.dt = 1e-9``) far more often than an
intention. The message gives the estimate and the key to change.
"""
from __future__ import annotations

import math

from forcecal.errors import SceneError
from forcecal.h5io import FLOOR_ELEMENTS
from forcecal.scene import Scene

#: largest FE reference accepted [vertex-steps] (~ 10 core-hours at the default liver's rate,
#: a day on one core on a 1,000-vertex mesh: :func:`fe_core_seconds`)
FE_LIMIT = 2e8
#: largest particle gravity release accepted [connector-steps] (both models together)
PARTICLE_LIMIT = 1e11
#: core-seconds per FE vertex-step on the default liver (282 vertices, P2): its reference,
#: 7.2e5 vertex-steps, took 75 s on 2 idle cores (1.65 x the throughput of one) before the
#: Anderson-mixed chord steps made it cheaper, an upper bound
FE_SECONDS_PER_VERTEX_STEP = 1.7e-4
#: the cost of a vertex-step grows as (FE vertices / 282)^FE_RATE_GROWTH: every item's cost
#: per step grew 3.7-4.1 x from 282 to 2,936 vertices (P2, measured in one session, so at one
#: load; ``fe_<kind>_profile`` of the scale study): factorisations and back-solves grow
#: faster than the vertices
FE_RATE_GROWTH = 0.6
#: a vertex-dof element's step on the particle mesh (the ``floor`` experiment), against one of
#: the reference's: measured on the default liver, ANP's gravity test took 8.1 s against P2's
#: 78 s and its held-out curves 3.5 s against 29 s (0.10 and 0.12)
FLOOR_SOLVE_FRACTION = 0.12


def n_test_points(scene: Scene) -> int:
    """Calibration + held-out points the scene asks for."""
    tp = scene.test_points
    n_cal = tp.n_calibration if isinstance(tp.calibration, str) else len(tp.calibration)
    return n_cal + n_held_out(scene)


#: connectors (edges) per vertex of a generated liver, for an estimate before meshing
#: (5.0 at the default 0.0182 m, 6.5 at 0.004 m)
EDGES_PER_VERTEX = 6.5


def refined_vertices(n_vertices: int, n_edges: int, levels: int) -> float:
    """Vertices of a tet mesh after ``levels`` uniform refinements (``fe.refine``: each adds a
    vertex per edge and splits every tet into 8), from its vertices and edges alone: the tets
    from Euler's formula of a solid ball (t ~ e - v + 1, faces ~ 2 t), so exact after one
    level and a few % high after more (the exact count: ``reference_fe.refine.refined_counts``)."""
    v, e = float(n_vertices), float(n_edges)
    t = max(e - v + 1.0, 0.0)
    f = 2.0 * t
    for _ in range(levels):
        v, e, f, t = v + e, 2 * e + 3 * f + t, 4 * f + 8 * t, 8 * t
    return v


def local_refine_factor(scene: Scene) -> float:
    """Factor on a punch's FE mesh of ``fe.local_refine`` rim refinements: at most 2 per
    level (the estimate of :func:`reference_fe.refine.check_memory`, measured 1.5-2.0)."""
    return 2.0 ** scene.fe.local_refine if scene.indentation.indenter == "punch" else 1.0


def n_held_out(scene: Scene) -> int:
    """How many held-out test points the scene has."""
    tp = scene.test_points
    return tp.n_held_out if isinstance(tp.held_out, str) else len(tp.held_out)


def fe_work(scene: Scene, n_vertices: int, n_edges: int | None = None) -> dict[str, float]:
    """Vertex-steps of each FE experiment the scene runs (``experiments``), keyed by the
    scene key that sets its step count, on the FE mesh: ``n_vertices`` refined ``fe.refine``
    times (:func:`refined_vertices`, ``n_edges`` the particle mesh's edges, estimated from
    :data:`EDGES_PER_VERTEX` if None), the indentation and relaxation on each punch's mesh
    refined ``fe.local_refine`` times near its rim (:func:`local_refine_factor`).

    The opt-in experiments: ``second_support`` runs the gravity test again (its steps added to
    the gravity keys'); ``body`` two static loads of ``body.load_steps`` and two eigen-solves
    (counted a step each); ``floor`` (key ``experiments``) runs, for each of
    :data:`~forcecal.h5io.FLOOR_ELEMENTS` on the particle mesh's ``n_vertices``, the gravity
    test, the second support's when asked for and the held-out points' indentation and
    relaxation curves, each step :data:`FLOOR_SOLVE_FRACTION` of a reference one (its
    core-seconds at the FE mesh's rate, :func:`fe_core_seconds`: an upper bound with
    ``fe.refine``)."""
    n_edges = EDGES_PER_VERTEX * n_vertices if n_edges is None else n_edges
    fe_vertices = refined_vertices(n_vertices, n_edges, scene.fe.refine)
    local = local_refine_factor(scene)
    points = n_test_points(scene)
    ind, r, g = scene.indentation.steps, scene.relaxation, scene.gravity
    curves = {"indentation": ind, "relaxation": r.ramp_steps + r.hold_steps}
    gravity = {"gravity_dynamic": ("gravity.fe_dt", math.ceil(g.duration / g.fe_dt)),
               "gravity_static": ("gravity.static_load_steps", g.static_load_steps)}
    work: dict[str, float] = {}

    def add(key: str, steps: float, vertices: float) -> None:
        work[key] = work.get(key, 0.0) + steps * vertices

    curve_keys = {"indentation": "indentation.steps", "relaxation": "relaxation.hold_steps"}
    for experiment, key in curve_keys.items():
        if experiment in scene.experiments:
            add(key, curves[experiment] * points, fe_vertices * local)
    second = "second_support" in scene.experiments  # the gravity test's both parts again
    for experiment, (key, steps) in gravity.items():
        runs = (experiment in scene.experiments) + second
        if runs:
            add(key, steps * runs, fe_vertices)
    if "body" in scene.experiments:
        add("body.load_steps", 2 * scene.body.load_steps + 2, fe_vertices)
    if "floor" in scene.experiments:
        test = sum(steps for _, steps in gravity.values())
        held = n_held_out(scene) * sum(steps for kind, steps in curves.items()
                                       if kind in scene.experiments)
        add("experiments",
            len(FLOOR_ELEMENTS) * FLOOR_SOLVE_FRACTION * ((1 + second) * test + held), n_vertices)
    return work


def fe_core_seconds(scene: Scene, work: float, n_vertices: int,
                    n_edges: int | None = None) -> float:
    """Estimated core-seconds of ``work`` FE vertex-steps of ``scene`` on the particle mesh of
    ``n_vertices`` (``n_edges`` as :func:`fe_work`): :data:`FE_SECONDS_PER_VERTEX_STEP` at the
    default liver's size, growing as :data:`FE_RATE_GROWTH` with the FE mesh's vertices."""
    n_edges = EDGES_PER_VERTEX * n_vertices if n_edges is None else n_edges
    fe_vertices = refined_vertices(n_vertices, n_edges, scene.fe.refine)
    return (work * FE_SECONDS_PER_VERTEX_STEP
            * (fe_vertices / DEFAULT_LIVER_VERTICES) ** FE_RATE_GROWTH)


def particle_work(scene: Scene, n_connectors: int) -> dict[str, float]:
    """Connector-steps of the particle gravity release (calibrated + baseline models) when
    ``particle.dt`` is a number (``"auto"`` is the stability limit: bounded by construction)."""
    dt = scene.particle.dt
    if isinstance(dt, str) or "gravity_dynamic" not in scene.experiments:
        return {}
    return {"particle.dt": 2.0 * scene.gravity.duration / dt * n_connectors}


def check_cost(scene: Scene, n_vertices: int, n_connectors: int, *,
               estimated: bool = False) -> None:
    """Refuse a scene whose estimated work exceeds :data:`FE_LIMIT` or :data:`PARTICLE_LIMIT`.

    ``n_vertices`` and ``n_connectors`` are the particle mesh's (the FE mesh is derived from
    it: ``fe.refine``, ``fe.local_refine``); ``estimated``: they are the estimate of the
    generated liver before meshing (:func:`check_generated_cost`).

    Raises:
        SceneError: with the estimate, its largest term and the key that sets it: a
            refinement or the mesh length when the work without it would be within the limit
            (the largest such factor), else the step key of the largest term.
    """
    for side, work, limit, unit in (("FE reference", fe_work(scene, n_vertices, n_connectors),
                                     FE_LIMIT, "vertex-steps"),
                                    ("particle gravity release",
                                     particle_work(scene, n_connectors), PARTICLE_LIMIT,
                                     "connector-steps")):
        total = sum(work.values())
        if total <= limit:
            continue
        key = max(work, key=work.get)
        cause = f"{key} = {_value(scene, key)}: change {key}"
        if side == "FE reference":
            cause = _mesh_cause(scene, n_vertices, n_connectors, total, limit, estimated) or cause
        hours = (f" (about {fe_core_seconds(scene, total, n_vertices, n_connectors) / 3600:.3g}"
                 " core-hours)" if side == "FE reference" else "")
        raise SceneError(f"{scene.path or 'scene'}: the {side} would take about {total:.3g} "
                         f"{unit}{hours}, above the limit of {limit:.3g}; most of it comes "
                         f"from {cause}")


#: vertices of the default generated liver (mesh.characteristic_length = 0.0182 m)
DEFAULT_LIVER_VERTICES = 282


def _mesh_cause(scene: Scene, n_vertices: int, n_edges: int, total: float, limit: float,
                estimated: bool) -> str | None:
    """The mesh key to blame for FE work ``total`` above ``limit`` (None: the steps): of
    ``fe.refine``, ``fe.local_refine`` and, before meshing, ``mesh.characteristic_length``,
    the one multiplying the work most, if the work without it is within the limit."""
    fe_vertices = refined_vertices(n_vertices, n_edges, scene.fe.refine)
    factors = {"fe.refine": (fe_vertices / n_vertices,
                             f"the FE mesh would have about {fe_vertices:.3g} vertices, "
                             f"{fe_vertices / n_vertices:.3g} x the particle mesh's "
                             f"{n_vertices}; lower fe.refine"),
               "fe.local_refine": (local_refine_factor(scene),
                                   f"each punch's FE mesh up to {local_refine_factor(scene):g} x "
                                   "the uniform one; lower fe.local_refine")}
    if estimated:
        factors["mesh.characteristic_length"] = (
            n_vertices / DEFAULT_LIVER_VERTICES,
            f"the generated liver would have about {n_vertices} vertices, estimated from its "
            f"volume before meshing, {DEFAULT_LIVER_VERTICES} at the default 0.0182 m; raise "
            "mesh.characteristic_length")
    key = max(factors, key=lambda k: factors[k][0])
    factor, why = factors[key]
    if factor <= 1.0 or total / factor > limit:
        return None
    return f"{key} = {_value(scene, key)} ({why})"


def check_generated_cost(scene: Scene) -> None:
    """Before meshing: refuse a generated liver (``mesh.source = "generate"``) whose
    ``mesh.characteristic_length`` gives, by the vertex count estimated from the organ's
    volume and area
    (:func:`forcecal.liver_mesh.estimated_liver_vertices`), work above the limits of
    :func:`check_cost` (gmsh alone would run for minutes or hours on it).

    Raises:
        SceneError: naming ``mesh.characteristic_length`` (or the key that causes most work).
    """
    from forcecal.liver_mesh import estimated_liver_vertices
    if scene.mesh.source != "generate":
        return
    # a length not small against the organ never gets here: the scene refused it at load
    n = estimated_liver_vertices(scene.mesh.characteristic_length)
    check_cost(scene, n, int(EDGES_PER_VERTEX * n), estimated=True)


def _value(scene: Scene, key: str):
    section, _, name = key.partition(".")
    return getattr(getattr(scene, section), name) if name else getattr(scene, section)
