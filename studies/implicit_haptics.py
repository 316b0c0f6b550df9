"""Would a linearised implicit haptic step beat the exact explicit one, within the error rules?

The question: one implicit step per 1 ms device period on the tangent factorised once at the
rest state, as SOFA-style haptics run (:mod:`studies._implicit_step`: Newmark's average
acceleration, HHT-alpha, backward Euler), instead of the explicit session's substeps
(:class:`particle.haptics.HapticSession`), if it is faster at large sizes. A variant may
replace the default only within 1e-3 of the float64 explicit force on the drag and within
1 % RMS on the release (the bench's ``error_drag`` and ``error_release``,
:mod:`pipelines.bench.haptic`).

**The floor** (:func:`floor`). An implicit step costs at least one forward and backward
substitution with the factor plus one force evaluation; where the substitution alone takes
longer than the explicit step's p99, no implicit step can win (``floor_exceeds``). Timed on
the bench's meshes (:data:`pipelines.bench.haptic.MESHES`: 1.4k, 12k and 54k connectors),
springs + arms and with the relaxing volume term (the volume term adds no entry to the
pattern: a tet's vertex pairs are connectors, so the substitution costs the same).

**The steps** (:func:`mesh_rows`). Per mesh and terms, the explicit float64 session (the
bench's reference: ``particle.dt_safety`` x the rigorous stable step) and each scheme of
:data:`SCHEMES` on the bench's drag (the top vertex 5 mm down over 0.25 s, then held, every
call timed) and release (3 s from rest under a quarter of the scene's gravity, the tracked
vertex every 5 ms), with the bench's errors against the explicit run (``error_drag`` over the
drag's first second, ``error_release``), the same error over the drag's last second
(``error_drag_end``: the tool held 9.75 s, where a growing mode shows), the time a release
diverged at (``release_diverged_s``) and the spread of its last second over the explicit
one's (``release_amplitude_ratio``: below 1, damped). ``newmark, converged`` iterates each
step to convergence on the same factor (not a haptic candidate: it tells the time
discretisation's error from the linearisation's). The implicit drags are run where the floor
puts one under :data:`MAX_DRAG_S`. The release's lowest natural frequency gives the analytic
damping of backward Euler there and Newmark's period error (:func:`analytic_damping`), and
:func:`frozen_amplification` what a step frozen at the rest tangent does to a mode whose
stiffness has moved away from it (``frozen_tangent``).

**The answer** (``runs/studies/implicit_haptics.json``): no implicit variant is both faster
than the explicit step and within the error rules, at any size. The substitution alone is
above the explicit p99 on the 12k and 54k livers with springs + arms (1.07 and 21 ms against
0.21 and 1.2 ms); with the relaxing volume term one substitution and one force pass (1.2 and
22 ms) are above it too (1.17 and 7.9 ms). The factor (9.5 and 115 MB) is read twice per
substitution, so its time follows its size. On the default liver the whole step's p99 is
above the explicit one's as well (89 against 25 us; 109 against 98 with the relaxing term).
Nor is a step frozen at the rest tangent accurate enough: a mode the deformed state
stiffens grows by the step's amplification (1.016 a step at omega h = 1 and 5 % stiffer),
one it softens is damped. Under Newmark the 12k liver's held drag diverges after 4.1 s and
its release after 1.5 s; HHT-alpha at -0.3 stays stable but is 1.1-1.9 % off on the 12k
releases (within both rules only on the default liver's springs, at 4x the explicit p99);
backward Euler damps every release by 7-9 % RMS (a 5 Hz swing keeps 23 % of its amplitude
after 3 s of 1 ms steps). Converged (four solves a step), Newmark meets both rules but for
the default liver's drag with the relaxing volume term (1.5e-3: the 1 ms step itself), so the
linearisation is what costs the accuracy.

``python -m studies.implicit_haptics --out runs/studies/implicit_haptics.json [--calls 10000]
[--mesh NAME ...] [--lock FILE]``: ``--lock`` holds FILE while timing (created with this
process's name, waited for while another holds it), so that other jobs on a shared machine
can pause meanwhile.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import time
from pathlib import Path
from typing import Any, Iterator

import numba
import numpy as np

from forcecal.errors import StabilityError
from particle.model import Model
from particle.sparse_ldl import _solve_one
from particle.statics import TangentPattern
from studies._implicit_step import NEWMARK, PERIOD, ImplicitSession, Scheme, rest_tangent

SCENE = Path("scenes/liver.toml")  # the bench's scene
CALLS = 10_000  # timed calls per drag (the haptic goals' p99 is of at least this many)
FLOOR_CALLS = 1_000  # timed substitutions and force evaluations per model
MAX_DRAG_S = 60.0  # the implicit drags are run where the floor puts one under this [s]
ERROR_RULES = {"drag": 1e-3, "release": 1e-2}  # a variant's allowed errors against float64
RECORD_S = 0.005  # s: the release's record interval (the bench's)
SCHEMES = (NEWMARK, Scheme("hht -0.05", alpha=-0.05), Scheme("hht -0.3", alpha=-0.3),
           Scheme("backward euler", euler=True),
           Scheme("newmark, converged", iterations=4))


@contextlib.contextmanager
def holding(lock: Path | None) -> Iterator[None]:
    """Hold ``lock`` (a file naming this process) while timing, after waiting for any other
    holder to let go; nothing with None."""
    if lock is None:
        yield
        return
    me = f"implicit_haptics {os.getpid()}"
    while True:
        try:
            with open(lock, "x") as f:
                f.write(me)
            break
        except FileExistsError:
            time.sleep(2.0)
    try:
        yield
    finally:
        if lock.is_file() and lock.read_text() == me:
            lock.unlink()


def timings(us: np.ndarray) -> dict[str, float]:
    """Median, p99 and max of per-call times [us]."""
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)),
            "max_us": float(us.max())}


def floor(model: Model, calls: int = FLOOR_CALLS, lock: Path | None = None
          ) -> dict[str, Any]:
    """The least an implicit step costs on ``model``: one substitution with the factor of
    the step matrix (Newmark's, no tool) and one force evaluation of the explicit step's own
    force pass (:func:`particle.kernels.internal_forces`, the volume term's
    :func:`particle.volume.add_volume_forces_grouped`), each timed ``calls`` times (holding
    ``lock``); with the factor's size (entries of ``L``, megabytes of its supernodal
    storage), the time of the pattern's analysis and of one factorisation [s]."""
    from particle import kernels
    from particle.volume import add_volume_forces_grouped

    session = ImplicitSession(model)
    pattern = session.pattern
    t0 = time.perf_counter()
    pattern.ldl  # the ordering and symbolic analysis, once per pattern
    analyse_s = time.perf_counter() - t0
    factor, _ = session._constraint(-1)
    factorise_s = time.perf_counter() - t0 - analyse_s
    rng = np.random.default_rng(0)
    rhs, out = rng.standard_normal(pattern.n_dofs), np.empty(pattern.n_dofs)
    p = model.params
    x = model.rest_positions + 1e-4 * rng.standard_normal(model.rest_positions.shape)
    r, c = p.arm_recursion(PERIOD)
    e = model.n_connectors
    forces, arm_out, dx = np.empty((model.n_particles, 3)), np.empty((e, 2)), np.empty(e)
    arm_prev, dx_prev = np.zeros((e, 2)), np.zeros(e)
    edges = kernels.index_view(model.edges)
    a, b = (None, None) if p.is_linear else (p.a, p.b)
    volume = None
    if p.kv is not None:
        t = model.n_tets
        arms = None
        if p.has_volume_arms:
            vr, vc = p.volume_arm_recursion(PERIOD)
            arms = (vr, vc, np.zeros((t, 2)), np.zeros(t))
        volume = (kernels.index_view(model.tets), model.rest_volumes,
                  np.broadcast_to(p.kv, (t,)).copy(), np.zeros(t), np.full(t, np.inf), arms,
                  None if arms is None else (np.empty((t, 2)), np.empty(t)), np.empty(t))

    def evaluate():
        kernels.internal_forces(x, edges, model.rest_lengths, p.K0, a, b, r, c, arm_prev,
                                dx_prev, forces, None, arm_out, dx)
        if volume is not None:
            add_volume_forces_grouped(x, volume[0], volume[1], volume[2], volume[3],
                                      volume[4], forces, volume[5], volume[6], volume[7])

    def solve():
        _solve_one(*factor, rhs, out)

    times = {}
    with holding(lock):
        for name, call in (("solve", solve), ("force", evaluate)):
            call()  # compiled outside the clock
            us = np.empty(calls)
            for k in range(calls):
                t0 = time.perf_counter()
                call()
                us[k] = time.perf_counter() - t0
            times[name] = timings(1e6 * us)
    nc, nr = np.diff(factor[0]), np.diff(factor[1])  # supernodes' columns and rows
    return {"dofs": pattern.n_dofs, "matrix_entries": len(pattern.indices),
            "factor_entries": int(np.sum(nc * nr - nc * (nc + 1) // 2)),
            "factor_mb": 8e-6 * len(factor[4]), "analyse_s": analyse_s,
            "factorise_s": factorise_s, "calls": calls, **times}


def implicit_drag(model: Model, scheme: Scheme, tool: int, *, calls: int, ramp_calls: int,
                  depth: float, direction: np.ndarray) -> dict[str, Any]:
    """The bench's drag (:func:`pipelines.bench.particle_engine.haptic_drag`: one untimed
    call at rest, then ``calls`` timed ones moving ``tool`` ``depth`` [m] along
    ``direction`` over ``ramp_calls``, then held) with :class:`ImplicitSession`."""
    session = ImplicitSession(model, scheme)
    start = model.rest_positions[tool].copy()
    session.step(tool, start)  # compile and factorise outside the clock
    latencies, forces = np.empty(calls), np.full((calls, 3), np.nan)
    diverged = None
    for k in range(calls):
        target = start + depth * min(1.0, k / ramp_calls) * direction
        t0 = time.perf_counter()
        try:
            forces[k] = session.step(tool, target)
        except StabilityError as exc:
            diverged = {"call": k, "error": str(exc)}
            latencies = latencies[:k]
            break
        latencies[k] = time.perf_counter() - t0
    return {"latencies_us": 1e6 * latencies, "forces": forces, "diverged": diverged}


def implicit_release(model: Model, scheme: Scheme, gravity: np.ndarray, node: int, *,
                     duration: float = 3.0, record_interval: float = 0.005) -> np.ndarray:
    """(S, 3) displacement [m] of ``node`` every ``record_interval`` over ``duration`` s of
    release from rest under ``gravity`` (:func:`pipelines.bench.particle_engine.
    release_history`'s record) with :class:`ImplicitSession`; NaN after a divergence."""
    session = ImplicitSession(model, scheme, gravity=gravity)
    per_record = int(round(record_interval / session.h))
    samples = int(round(duration / record_interval))
    out = np.full((samples + 1, 3), np.nan)
    out[0] = 0.0
    try:
        for s in range(1, samples + 1):
            session.advance(per_record)
            out[s] = session.x[node] - model.rest_positions[node]
    except StabilityError:
        pass
    return out


def lowest_frequency(model: Model, h: float = PERIOD) -> float:
    """The lowest natural frequency [Hz] of the rest tangent (the arms' step coefficients at
    ``h`` included) with the lumped masses, by shift-invert Lanczos."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import eigsh

    pattern = TangentPattern.of(model)
    data = rest_tangent(model, h, pattern)
    n = pattern.n_dofs
    k = sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=(n, n))
    m = sp.diags(np.repeat(model.masses[model.free_nodes], 3))
    value = eigsh(k, k=1, M=m, sigma=0.0, which="LM", return_eigenvectors=False)[0]
    return float(math.sqrt(value) / (2.0 * math.pi))


def analytic_damping(frequency: float, h: float = PERIOD, duration: float = 3.0
                     ) -> dict[str, float]:
    """Undamped oscillator at ``frequency`` [Hz], steps ``h`` [s] for ``duration`` [s]: the
    amplitude backward Euler leaves, ``(1 + (omega h)^2)^(-n/2)``, and Newmark's period
    error ``2 / (omega h) atan(omega h / 2)`` - 1 (it keeps the amplitude)."""
    wh = 2.0 * math.pi * frequency * h
    steps = duration / h
    return {"frequency_hz": frequency, "omega_h": wh,
            "euler_amplitude_left": (1.0 + wh * wh) ** (-0.5 * steps),
            "newmark_period_error": wh / (2.0 * math.atan(0.5 * wh)) - 1.0}


def frozen_amplification(scheme: Scheme, ratio: float, omega_h: float) -> float:
    """Spectral radius of one linearised step (:mod:`studies._implicit_step`) of an undamped
    one-dof oscillator whose stiffness is ``ratio`` x the frozen one the step's matrix holds
    (``omega_h``: the frozen stiffness' omega x h): 1 for Newmark at ``ratio`` 1 (exact
    step), above 1 where the state is stiffer than the factorised tangent (the mode grows),
    below where it is softer (damped)."""
    h, k0 = 1.0, omega_h ** 2  # unit mass and step: only omega h matters
    k = ratio * k0
    mass_coef, stiff_coef = scheme.coefficients(h)
    beta, gamma, alpha = scheme.beta, scheme.gamma, scheme.alpha
    columns = []
    for x, v, a in np.eye(3):  # the map of (x, v, a); HHT's f(x_n) = -k x_n exactly
        if scheme.euler:
            d = (-k * x + v / h) / (mass_coef + stiff_coef * k0)
            columns.append((x + d, d / h, 0.0))
            continue
        inertia = -(h * v + h * h * (0.5 - beta) * a) / (beta * h * h)
        d = (-k * x - inertia) / (mass_coef + stiff_coef * k0)
        a_new = (d - h * v - h * h * (0.5 - beta) * a) / (beta * h * h)
        columns.append((x + d, v + h * ((1.0 - gamma) * a + gamma * a_new), a_new))
    return float(np.max(np.abs(np.linalg.eigvals(np.array(columns).T))))


def mesh_rows(name: str, model: Model, tool: int, tracked: int, gravity: np.ndarray, *,
              calls: int, lock: Path | None, schemes: tuple[Scheme, ...] = SCHEMES
              ) -> dict[str, Any]:
    """One mesh and terms: the explicit float64 reference (drag timed, release), the floor
    and, where the floor puts an implicit drag under :data:`MAX_DRAG_S`, every scheme's drag
    (timed, but for a converged scheme's: the error window only) and release with their
    errors against the reference; ``lock`` held while timing."""
    from pipelines.bench import haptic as bh
    from pipelines.bench import particle_engine as pb
    from particle.stability import DEFAULT_STRAIN_RANGE, critical_time_step

    dt = pb.DT_SAFETY * critical_time_step(model)
    release_gravity = bh.RELEASE_GRAVITY * gravity
    with holding(lock):
        reference = pb.haptic_drag(model, tool, bh.DOWN, dt, calls=calls,
                                   ramp_calls=bh.RAMP_CALLS)
    bottom = floor(model, lock=lock)
    explicit = {"substeps": reference["substeps"], "dt_s": reference["dt_s"], "calls": calls,
                **timings(reference["latencies_us"])}
    least = bottom["solve"]["median_us"] + bottom["force"]["median_us"]
    row = {"mesh": name, "connectors": model.n_connectors, "particles": model.n_particles,
           "tets": model.n_tets if model.params.kv is not None else 0,
           "explicit": explicit, "floor": bottom,
           "floor_exceeds": bottom["solve"]["median_us"] > explicit["p99_us"],
           "floor_us": least, "implicit": []}
    if least * 1e-6 * calls > MAX_DRAG_S:
        return row
    ref_release = pb.release_history(model, release_gravity, dt, tracked,
                                     strain_range=DEFAULT_STRAIN_RANGE)
    row["release_frequency"] = analytic_damping(lowest_frequency(model))
    spread = np.std(ref_release[-200:], axis=0)
    window = bh.ERROR_CALLS
    for scheme in schemes:
        timed = scheme.iterations == 1  # a converged step is a diagnostic, not a candidate
        with holding(lock if timed else None):
            drag = implicit_drag(model, scheme, tool, calls=calls if timed else window,
                                 ramp_calls=bh.RAMP_CALLS, depth=0.005, direction=bh.DOWN)
        release = implicit_release(model, scheme, release_gravity, tracked,
                                   record_interval=RECORD_S)
        done = drag["diverged"] is None and np.all(np.isfinite(release))
        drag_error = (pb.relative_history_error(drag["forces"][:window],
                                                reference["forces"][:window])
                      if drag["diverged"] is None or drag["diverged"]["call"] >= window
                      else None)
        release_error = amplitude = release_diverged_s = None
        if np.all(np.isfinite(release)):
            release_error = pb.relative_history_error(release, ref_release)
            amplitude = float(np.linalg.norm(np.std(release[-200:], axis=0))
                              / np.linalg.norm(spread))
        else:
            release_diverged_s = RECORD_S * int(np.argmax(~np.isfinite(release[:, 0])))
        # the held tool's force over the drag's last second: where an instability shows
        end = len(drag["forces"]) if drag["diverged"] is None else 0
        end_error = (pb.relative_history_error(drag["forces"][end - window:end],
                                               reference["forces"][end - window:end])
                     if end >= 2 * window else None)
        entry = {"scheme": scheme.name, "alpha": scheme.alpha, "euler": scheme.euler,
                 "iterations": scheme.iterations, "calls": len(drag["latencies_us"]),
                 "diverged": drag["diverged"],
                 **(timings(drag["latencies_us"]) if timed and len(drag["latencies_us"])
                    else {}),
                 "error_drag": drag_error, "error_drag_end": end_error,
                 "error_release": release_error, "release_diverged_s": release_diverged_s,
                 "release_amplitude_ratio": amplitude}
        entry["within_rules"] = bool(done and drag_error <= ERROR_RULES["drag"]
                                     and release_error <= ERROR_RULES["release"])
        entry["faster"] = bool(done and timed and entry["p99_us"] < explicit["p99_us"])
        row["implicit"].append(entry)
    return row


def measure(calls: int = CALLS, lock: Path | None = None,
            meshes: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Every mesh of the bench (or those named ``meshes``) x terms (springs + arms, with the
    relaxing volume term): :func:`mesh_rows`."""
    from forcecal.problem import tracked_node_by_rule
    from forcecal.scene import load_scene
    from pipelines.bench import haptic as bh

    numba.set_num_threads(1)
    scene = load_scene(SCENE)
    gravity = np.asarray(scene.gravity.acceleration, dtype=float)
    load = [os.getloadavg()[0]]
    rows = []
    for name, length in bh.MESHES[False]:
        if meshes is not None and name not in meshes:
            continue
        springs, mesh, fixed = bh._mesh_model(scene, length)
        tool = int(np.argmax(np.where(springs.fixed, -np.inf, springs.rest_positions[:, 2])))
        tracked = tracked_node_by_rule(mesh, fixed, "farthest_from_support")
        relaxing = bh.volume_model(springs, bh.VOLUME_KV, (scene.material.prony_g,
                                                           scene.material.prony_tau))
        for terms, model in ((bh.SPRINGS, springs), (bh.RELAXING, relaxing)):
            row = mesh_rows(name, model, tool, tracked, gravity, calls=calls, lock=lock)
            rows.append({"terms": terms, **row})
            print(summary_line(rows[-1]), flush=True)
        load.append(os.getloadavg()[0])
    euler_5hz = analytic_damping(5.0)
    frozen = [{"scheme": scheme.name, "ratio": ratio, "omega_h": wh,
               "amplification": frozen_amplification(scheme, ratio, wh)}
              for scheme in SCHEMES if scheme.iterations == 1
              for ratio in (0.8, 0.95, 1.05, 1.2) for wh in (0.03, 1.0, 3.0)]
    return {"scene": str(SCENE), "period_s": PERIOD, "calls": calls,
            "error_rules": ERROR_RULES, "rows": rows, "euler_5hz": euler_5hz,
            "frozen_tangent": frozen,
            "wins": [f"{r['mesh']}, {r['terms']}, {i['scheme']}" for r in rows
                     for i in r["implicit"] if i["within_rules"] and i["faster"]],
            "load_average": load, "cpus": os.cpu_count()}


def summary_line(row: dict[str, Any]) -> str:
    """One row in a line of text."""
    e, f = row["explicit"], row["floor"]
    text = (f"{row['mesh']:9s} {row['terms']:33s} explicit p99 {e['p99_us']:7.0f} us "
            f"({e['substeps']} substeps); floor: solve {f['solve']['median_us']:7.0f} us + "
            f"force {f['force']['median_us']:5.0f} us")
    for i in row["implicit"]:
        def err(key, i=i):
            return "-" if i[key] is None else f"{i[key]:.1e}"
        timed = (f"p99 {i['p99_us']:7.0f} us, median {i['median_us']:7.0f} us" if "p99_us" in i
                 else "(not timed)")
        text += (f"\n    {i['scheme']:18s} {timed}; drag {err('error_drag')} (last second "
                 f"{err('error_drag_end')}), release {err('error_release')}"
                 + (f"; drag diverged at call {i['diverged']['call']}" if i["diverged"] else "")
                 + (f"; release diverged at {i['release_diverged_s']:.2f} s"
                    if i["release_diverged_s"] is not None else ""))
    return text


def main(argv: list[str] | None = None) -> None:
    from studies.viscoelastic_volume import write_json

    parser = argparse.ArgumentParser(prog="python -m studies.implicit_haptics",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/studies/implicit_haptics.json"))
    parser.add_argument("--calls", type=int, default=CALLS, help="timed calls per drag")
    parser.add_argument("--mesh", action="append", help="only these of the bench's meshes")
    parser.add_argument("--lock", type=Path, help="file held while timing (see the docstring)")
    args = parser.parse_args(argv)
    from pipelines.bench.haptic import ERROR_CALLS
    if args.calls < ERROR_CALLS:
        raise SystemExit(f"error: --calls {args.calls} is below the drag error's window "
                         f"({ERROR_CALLS} calls)")
    result = measure(args.calls, args.lock, None if args.mesh is None else tuple(args.mesh))
    result["command"] = ("python -m studies.implicit_haptics --out "
                         f"{args.out.as_posix()}"
                         + ("" if args.calls == CALLS else f" --calls {args.calls}")
                         + "".join(f" --mesh '{m}'" for m in args.mesh or ()))
    write_json(args.out, result)
    print(f"wrote {args.out}; implicit within the error rules and faster than explicit: "
          f"{', '.join(result['wins']) or 'none'}")


if __name__ == "__main__":
    main()
