"""Where the gradient calibration spends its time, and what bounds its largest kernel.

On a scene of the punch + gradient method (the liver punch's calibration has a goal of 120 s
on 2 cores), the workers spend the fit in point Jacobians (the adjoint pass of
:mod:`particle.sensitivity` through each point's recorded path), the parent in the whole-body
rows and the Levenberg-Marquardt algebra. This study times, on a finished run's reference:

* **one point Jacobian per kind**, kernel by kernel: the first ``points`` calibration points'
  Jacobians at the global fit's start (the outputs the scene fits: the force vector's three
  components or the normal force), their forward paths solved first so that only the adjoint
  pass is timed; each compiled kernel of :mod:`particle.sensitivity_kernels`, the tangent's
  assembly and factorisation and the factorisation's solves, per point [ms];
* **the largest streaming kernel against memory**: :func:`particle.sensitivity_kernels.
  add_partials` on arrays of the relaxation Jacobian's shape (every output live, as at the
  hold's last steps), the bytes it reads and writes per call and their rate [GB/s], against
  a plain read-modify-write pass over as many bytes (``memory``): a rate near the pass's says
  the kernel waits on memory, not on its arithmetic;
* **the factorisation's solve against its number of right-hand sides**: one tangent of the
  first point's path (its last step, factorised as the adjoint pass factorises it), solved
  for 1 to all of the outputs at once [us], and what taking the outputs back through the
  path in blocks of :data:`BLOCK` would cost in solves against all at once (``blocked_ratio``):
  a block's rows of the Jacobian would stay in cache from step to step, but each step would
  solve once per block;
* **a point's rows compressed**: what a worker does with a point's Jacobian after the
  adjoint pass, :func:`calibration.gradient_solver.compress` on rows of its shape (every
  kind's outputs x the fit's coordinates) [ms], and the projection ``U^T J`` it does with
  ``U`` a reversed view of eigh's columns instead (a negative stride: numpy's own matmul
  loop, not BLAS; the layout :func:`calibration.gradient_solver.leading_vectors` avoids);
* **the parent's whole-body rows** (with the scene's whole-body data): one
  :meth:`calibration.body.BodyData.responses` with Jacobians at the same parameters [s], what
  each linearisation computes while the workers compute theirs.

``python -m studies.calibration_time --scene scenes/liver_punch.toml [--run DIR] [--out
runs/studies/calibration_time_<scene>.json]`` (reads ``<run>/reference.h5``; about 15 s).
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from numba import njit

from studies._finished_run import run_folder, study_main

POINTS = 6  # calibration points timed per kind
REPEATS = 3  # timed repetitions of the whole-body rows and of the streaming kernels
BLOCK = 16  # outputs per block of the blocked adjoint pass the solve's cost prices


@contextlib.contextmanager
def kernel_clock() -> Iterator[dict[str, float]]:
    """Inside the block, the seconds spent in each compiled adjoint kernel, in the tangent's
    assembly (``tangent_data``) and factorisation (``ldl_factor``) and in the factorisation's
    solves (``Factor.solve``), accumulated by name (the module attributes the adjoint pass
    calls through are wrapped, and restored on leaving)."""
    import particle.sensitivity as sensitivity
    import particle.sensitivity_kernels as kernels
    from particle.sparse_ldl import Factor

    seconds: dict[str, float] = {}
    patched: list[tuple[Any, str, Any]] = []

    def clocked(name: str, fn):
        def call(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t
        return call

    names = [n for n in vars(kernels) if hasattr(getattr(kernels, n), "py_func")]
    for owner, name in ([(kernels, n) for n in names]
                        + [(sensitivity, "tangent_data"), (sensitivity, "ldl_factor"),
                           (Factor, "solve")]):
        original = getattr(owner, name)
        patched.append((owner, name, original))
        setattr(owner, name, clocked(name if owner is not Factor else "Factor.solve",
                                     original))
    try:
        yield seconds
    finally:
        for owner, name, original in patched:
            setattr(owner, name, original)


def point_jacobian_times(evaluator, params, points: list[int],
                         directions: np.ndarray | None) -> dict[str, Any]:
    """One kind's adjoint pass at ``params`` over ``points`` (local indices): its wall time
    and each kernel's, per point [ms] (the forward paths solved before the clock starts)."""
    evaluator.jacobian(params, points, directions)  # forward paths, compiled kernels
    with kernel_clock() as seconds:
        t = time.perf_counter()
        evaluator.jacobian(params, points, directions)
        total = time.perf_counter() - t
    per_point = 1e3 / len(points)
    kernels = dict(sorted(((k, v * per_point) for k, v in seconds.items()),
                          key=lambda kv: -kv[1]))
    return {"samples": len(evaluator.depths), "points": len(points),
            "point_jacobian_ms": total * per_point, "kernels_ms": kernels,
            "other_ms": total * per_point - sum(kernels.values())}


@njit(cache=True)
def _read_modify_write(buffer: np.ndarray) -> None:
    for k in range(buffer.shape[0]):
        buffer[k] = buffer[k] * 0.5 + 1.0


def _best_seconds(fn, repeats: int) -> float:
    fn()
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def add_partials_rate(outputs: int, connectors: int, repeats: int = 20) -> dict[str, Any]:
    """:func:`~particle.sensitivity_kernels.add_partials` with arms on every one of
    ``outputs`` live outputs over ``connectors`` connectors: its best time per call [ms],
    the bytes it moves (the Jacobian's 7 rows and the arm history read and written, the
    tension adjoints read) and their rate [GB/s], against a read-modify-write pass over as
    many bytes."""
    from particle.sensitivity_kernels import add_partials

    rng = np.random.default_rng(0)
    s, e = outputs, connectors
    cols = np.arange(s)
    tau = rng.standard_normal((s, e))
    dx = 1e-3 * rng.standard_normal(e)
    rest = 0.01 + 0.01 * rng.random(e)
    r, c = rng.random((e, 2)), rng.random((e, 2))
    dk, db = rng.standard_normal((e, 2)), rng.standard_normal((e, 2))
    jac, abar, dbar = np.zeros((s, 7, e)), rng.standard_normal((s, 2, e)), np.zeros((s, e))
    seconds = _best_seconds(lambda: add_partials(cols, tau, dx, rest, jac, True, r, c, dk, db,
                                                 abar, dbar), repeats)
    moved = 8 * s * e * (2 * (7 + 2 + 1) + 1)  # bytes: jac, abar, dbar both ways; tau read
    buffer = np.zeros(moved // 16)  # read and written: as many bytes moved
    memory = _best_seconds(lambda: _read_modify_write(buffer), repeats)
    return {"outputs": s, "connectors": e, "ms": 1e3 * seconds, "bytes": moved,
            "gb_per_s": moved / seconds / 1e9, "memory_gb_per_s": moved / memory / 1e9}


def solve_cost(evaluator, params, outputs: int, repeats: int = 20) -> dict[str, Any]:
    """The factorisation's solve on the tangent at the last step of ``evaluator``'s first
    point's path (its forward path solved): best time [us] for 1, 3, :data:`BLOCK`, half of
    and all ``outputs`` right-hand sides, the factor's size, and ``blocked_ratio``: the
    solves of ``outputs`` right-hand sides in blocks of :data:`BLOCK` over one solve of all
    of them."""
    solver = evaluator._solvers[0]
    arms, eq = evaluator._steps(0)[0][-1]
    model = evaluator.model.with_params(params)
    pattern = evaluator.pattern_for(solver)
    factor = evaluator._constrained_factor(
        solver, pattern, evaluator._tangent(solver, model, pattern, eq, arms))
    rhs = np.asfortranarray(np.random.default_rng(0).standard_normal((factor.shape[0],
                                                                      outputs)))
    counts = sorted({1, 3, min(BLOCK, outputs), max(1, outputs // 2), outputs})
    us = {r: 1e6 * _best_seconds(lambda: factor.solve(rhs[:, :r]), repeats) for r in counts}
    blocks, rest = divmod(outputs, BLOCK)
    blocked = blocks * us[min(BLOCK, outputs)] + (_best_seconds(
        lambda: factor.solve(rhs[:, :rest]), repeats) * 1e6 if rest else 0.0)
    return {"dofs": factor.shape[0], "l_entries": int(factor.symbolic.x_ptr[-1]),
            "microseconds": {str(r): t for r, t in us.items()}, "block": BLOCK,
            "blocked_ratio": blocked / us[outputs]}


def fit_size(setup, params) -> int:
    """The gradient fit's number of coordinates at the start ``params`` of the scene's
    ``setup`` (:func:`calibration.gradient.fit_coordinates`)."""
    from calibration.gradient import fit_coordinates
    mesh = setup.problem.mesh
    tets = len(mesh.tets) if params.kv is not None else None
    return fit_coordinates(params, 1.0, len(mesh.edges), tets,
                           setup.settings.kv_per_tet)[1].size


def compression_cost(rows: int, size: int, keep: int, repeats: int = REPEATS
                     ) -> dict[str, Any]:
    """:func:`calibration.gradient_solver.compress` of one point's (rows, size) Jacobian
    (random values: the cost does not depend on them) to ``keep`` rows, and the projection
    through a reversed view of the Gram matrix's eigenvectors [ms]."""
    from calibration.gradient_solver import compress
    rng = np.random.default_rng(0)
    J, r = rng.standard_normal((rows, size)), rng.standard_normal(rows)
    _, vectors = np.linalg.eigh(J @ J.T)
    reversed_view = vectors[:, ::-1][:, :keep]
    return {"rows": rows, "size": size, "keep": keep,
            "compress_ms": 1e3 * _best_seconds(lambda: compress(r, J, rows, keep), repeats),
            "reversed_view_projection_ms": 1e3 * _best_seconds(lambda: reversed_view.T @ J,
                                                               repeats)}


def study(scene_path: str | Path, run: str | Path | None = None, *, points: int = POINTS
          ) -> dict[str, Any]:
    """The timings of the module docstring on the finished run of ``scene_path``."""
    from calibration.core import prepare_fit, whole_body_data
    from calibration.gradient import gradient_backend
    from calibration.gradient_solver import ROWS_KEPT
    from forcecal.scene import load_scene
    from pipelines.runners.common import REFERENCE

    scene = load_scene(scene_path)
    setup = prepare_fit(scene, run_folder(scene, run) / REFERENCE)
    params = setup.connector_params(setup.initial)
    chosen = np.arange(min(points, setup.n_calibration))  # the calibration points lead
    evaluators = gradient_backend(setup.experiments, chosen, params)
    directions = np.eye(3) if setup.settings.force_components == "vector" else None
    kinds = {kind: point_jacobian_times(ev, params, list(range(len(chosen))), directions)
             for kind, ev in evaluators.items()}
    model = evaluators[next(iter(evaluators))].model
    components = 1 if directions is None else len(directions)  # outputs per sample
    outputs = max(k["samples"] for k in kinds.values()) * components
    result = {"scene": scene.name, "connectors": model.n_connectors, "tets": model.n_tets,
              "particles": model.n_particles, "directions": components,
              "kinds": kinds, "add_partials": add_partials_rate(outputs, model.n_connectors)}
    if "relaxation" in evaluators:  # the kind whose outputs ride through many steps
        result["solve_cost"] = solve_cost(evaluators["relaxation"], params, outputs)
    rows = sum(k["samples"] for k in kinds.values()) * components
    result["compression"] = compression_cost(rows, fit_size(setup, params), ROWS_KEPT)
    body = whole_body_data(setup, setup.initial).every
    if body is not None:
        result["body_rows_s"] = _best_seconds(lambda: body.responses(params), REPEATS)
    return result


def main(argv: list[str] | None = None) -> int:
    return study_main("studies.calibration_time", __doc__, study, argv)


if __name__ == "__main__":
    raise SystemExit(main())
