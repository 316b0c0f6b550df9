"""Evaluate test points in parallel: persistent workers, each owning a fixed set of points.

Every test point belongs to one worker (round robin over the point index), which
builds the particle evaluators for its points once and keeps them, so warm starts
and factorisations stay where they are used. The master sends *calls*: a
module-level function and its arguments, run as ``fn(worker, *args)`` on the
worker; the calls calibration needs are :func:`point_curves` (curves of some
points for one parameter set), :func:`point_curves_and_forces` (with their whole force,
for the validation) and the local fit of one point (:func:`calibration.local.fit_point`).

One code path, three transports:

* ``workers = 1``: the worker lives in the calling process (:class:`InlineTransport`);
* ``workers > 1``: worker processes, fresh interpreters talking over sockets
  (:class:`ProcessTransport`);
* under ``mpirun`` with more than one rank: ranks 1..n-1 are the workers
  (:class:`MpiTransport`, :func:`serve_mpi`), rank 0 runs the optimisers.

A worker error travels back to the master, which lets every other call in
flight finish and then raises it (ForcecalError subclasses keep their type).

(At the project's 450-line guideline: the three transports are one protocol with one
error path, kept in one module so that a change of the protocol is one change.)
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import socket
import subprocess
import sys
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence

import numpy as np

from calibration.metrics import point_costs
from forcecal.failures import die_with_parent
from forcecal.logs import configure_logging
from forcecal.problem import Problem
from particle.evaluators import normal_force
from particle.params import ConnectorParams

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Experiments:
    """The experiments every worker reproduces (picklable).

    Attributes:
        problem: mesh, fixed nodes and test points (curves are ordered like
            ``problem.test_points``).
        density: mass density [kg/m^3] (the evaluators' model needs masses).
        depths: (Si,) float64, indentation depths [m].
        times: (Sr,) float64, relaxation sample times [s].
        relaxation_depths: (Sr,) float64, prescribed depth at those times [m].
        strain_range: (low, high) strains over which the spring K(eps) must stay
            positive (the evaluators refuse parameters that violate it).
        footprints: per test point, the particles the indenter holds (a flat punch,
            :func:`forcecal.indenter.indenter_footprints`); None: the test point alone.
        volume_element: the volume term's element (:attr:`particle.model.Model.volume_element`,
            scene key ``particle.volume_element``): the evaluators' models use it.
    """
    problem: Problem
    density: float
    depths: np.ndarray
    times: np.ndarray
    relaxation_depths: np.ndarray
    strain_range: tuple[float, float]
    footprints: tuple[np.ndarray, ...] | None = None
    volume_element: str = "tet"

    def held(self, points: np.ndarray) -> list[np.ndarray] | None:
        """The footprints of ``points`` (indices into the test points), None for the vertex
        indenter: what every backend hands its evaluators, so all indent alike."""
        return None if self.footprints is None else [self.footprints[int(k)] for k in points]


class PointEvaluator(Protocol):
    """A backend's evaluator of one experiment: called with parameters and test point
    indices, it returns their (P', S) normal-force curves [N]. Optional, used when present:
    ``force_vectors`` (same arguments, the (P', S, 3) forces: needed by the force-vector
    fit, stored by the validation), ``forget`` and ``set_tolerance`` (see the calls
    below); the particle engine's evaluators have all three."""

    def __call__(self, params: ConnectorParams, points: Sequence[int] | None = None
                 ) -> np.ndarray: ...


Backend = Callable[[Experiments, np.ndarray, ConnectorParams], dict[str, PointEvaluator]]


def particle_backend(experiments: Experiments, points: np.ndarray,
                     params: ConnectorParams) -> dict[str, PointEvaluator]:
    """The particle engine's evaluators for test points ``points`` (indices into test_points)."""
    from particle.evaluators import IndentationEvaluator, RelaxationEvaluator
    from particle.model import build_model

    p = experiments.problem
    model = build_model(p, experiments.density, params,
                        volume_element=experiments.volume_element)
    nodes, normals = p.test_points[points], p.normals[points]
    strain = experiments.strain_range
    held = experiments.held(points)
    return {"indentation": IndentationEvaluator(model, nodes, normals, experiments.depths,
                                                strain_range=strain, footprints=held),
            "relaxation": RelaxationEvaluator(model, nodes, normals, experiments.times,
                                              experiments.relaxation_depths,
                                              strain_range=strain, footprints=held)}


@dataclass(frozen=True, eq=False)
class WorkerSpec:
    """What a worker is built from (picklable: sent to forkserver children and MPI ranks)."""
    experiments: Experiments
    points: np.ndarray
    backend: Backend
    params: ConnectorParams
    log_level: int = logging.WARNING


class PointWorker:
    """Owns the evaluators of a fixed set of test points."""

    def __init__(self, spec: WorkerSpec):
        self.experiments = spec.experiments
        self.points = np.asarray(spec.points, dtype=np.int64)
        self._local = {int(p): i for i, p in enumerate(self.points)}
        self.evaluators = spec.backend(spec.experiments, self.points, spec.params)
        self.evaluations = 0  # point-curves computed by this worker

    def curves(self, kind: str, params: ConnectorParams, points: Sequence[int]) -> np.ndarray:
        """(len(points), S) normal-force curves [N] of owned test points (global indices)."""
        local = [self._local[int(p)] for p in points]
        out = np.asarray(self.evaluators[kind](params, local), dtype=np.float64)
        self.evaluations += len(local)
        return out

    def force_vectors(self, kind: str, params: ConnectorParams, points: Sequence[int]
                      ) -> np.ndarray:
        """(len(points), S, 3) indenter force vectors [N] of owned test points (global
        indices): the curves' whole force, not only its normal component."""
        local = [self._local[int(p)] for p in points]
        out = np.asarray(self.evaluators[kind].force_vectors(params, local), dtype=np.float64)
        self.evaluations += len(local)
        return out

    def curves_and_forces(self, kind: str, params: ConnectorParams, points: Sequence[int]
                          ) -> tuple[np.ndarray, np.ndarray | None]:
        """The :meth:`curves` of owned test points and, from one evaluation, the
        :meth:`force_vectors` they are the inward-normal components of; a backend whose
        evaluators have no ``force_vectors`` (a plain :class:`PointEvaluator`) gives the
        curves and None."""
        if not hasattr(self.evaluators[kind], "force_vectors"):
            return self.curves(kind, params, points), None
        forces = self.force_vectors(kind, params, points)
        normals = self.experiments.problem.normals[np.asarray(points, dtype=np.int64)]
        return normal_force(forces, normals), forces

    def strain_extremes(self, kind: str, points: Sequence[int]) -> np.ndarray | None:
        """(len(points), 2) the smallest and largest connector strain [1] of owned test
        points' last ``kind`` curves (their evaluators' ``strain_extremes``), or None if the
        backend's evaluators do not give them."""
        evaluator = self.evaluators[kind]
        if not hasattr(evaluator, "strain_extremes"):
            return None
        return evaluator.strain_extremes([self._local[int(p)] for p in points])


def point_curves(worker: PointWorker, kind: str, params: ConnectorParams,
                 points: Sequence[int]) -> np.ndarray:
    """Call run on a worker: its curves of ``points`` (see :meth:`PointWorker.curves`)."""
    return worker.curves(kind, params, points)


def point_curves_and_forces(worker: PointWorker, kind: str, params: ConnectorParams,
                            points: Sequence[int]) -> tuple[np.ndarray, np.ndarray | None]:
    """Call run on a worker: its curves and force vectors of ``points`` (see
    :meth:`PointWorker.curves_and_forces`)."""
    return worker.curves_and_forces(kind, params, points)


def forget_warm_starts(worker: PointWorker) -> None:
    """Call run on a worker: its evaluators start cold at their next call (see
    :meth:`particle.evaluators._PointEvaluator.forget`; a backend without ``forget`` has no
    warm starts)."""
    for evaluator in worker.evaluators.values():
        forget = getattr(evaluator, "forget", None)
        if forget is not None:
            forget()


def set_newton_tolerance(worker: PointWorker, rtol: float | None) -> None:
    """Call run on a worker: its evaluators' Newton tolerance (see
    :meth:`particle.evaluators._PointEvaluator.set_tolerance`; a backend without
    ``set_tolerance`` solves nothing iteratively)."""
    for evaluator in worker.evaluators.values():
        set_tolerance = getattr(evaluator, "set_tolerance", None)
        if set_tolerance is not None:
            set_tolerance(rtol)


def evaluation_count(worker: PointWorker) -> int:
    """Call run on a worker: point-curves it has computed so far."""
    return worker.evaluations


def _run(worker: PointWorker, message: tuple) -> tuple[str, Any]:
    fn, args = message
    try:
        return "ok", fn(worker, *args)
    except Exception as exc:  # sent back and re-raised by the master
        exc.add_note(f"(in calibration worker {os.getpid()})\n{traceback.format_exc()}")
        return "error", exc


def serve(receive: Callable[[], Any], send: Callable[[Any], None]) -> None:
    """Worker loop: first message is a WorkerSpec, then calls until None.

    A None first message releases a worker the pool has no points for (an MPI
    rank beyond the number of test points).
    """
    spec = receive()
    if spec is None:
        return
    import numba
    numba.set_num_threads(1)  # one core per worker; the pool is the parallelism
    if not logging.getLogger().handlers:  # a fresh worker process: the master's set-up
        configure_logging(spec.log_level, prefix=f"[worker {os.getpid()}] ")
    try:
        worker = PointWorker(spec)
    except Exception as exc:
        exc.add_note(traceback.format_exc())
        send(("error", exc))
        return
    send(("ok", None))
    while (message := receive()) is not None:
        send(_run(worker, message))


class InlineTransport:
    """One worker in the calling process."""

    def __init__(self, specs: list[WorkerSpec]):
        self.worker = PointWorker(specs[0])
        self._replies: collections.deque = collections.deque()

    def send(self, w: int, message: tuple) -> None:
        self._replies.append((w, _run(self.worker, message)))

    def receive(self) -> tuple[int, tuple[str, Any]]:
        return self._replies.popleft()

    def close(self) -> None:
        pass


class ProcessTransport:
    """Worker processes (fresh interpreters, ``python -m calibration.worker``) over sockets.

    Fresh interpreters rather than ``fork``: a parent that has started numba or
    OpenMP threads cannot hand a broken runtime to its children, and unlike
    ``spawn``/``forkserver`` the caller's ``__main__`` is not re-imported, so
    scripts need no ``if __name__ == "__main__"`` guard.
    """

    def __init__(self, specs: list[WorkerSpec]):
        from multiprocessing.connection import Connection
        self._conns, self._procs = [], []
        for spec in specs:
            parent, child = socket.socketpair()
            # a worker dies with its master, even a SIGKILLed one (mid-fit it would not
            # notice the closed socket until its call ends)
            proc = subprocess.Popen([sys.executable, "-m", "calibration.worker",
                                     str(child.fileno())], pass_fds=(child.fileno(),),
                                    preexec_fn=die_with_parent)
            child.close()
            conn = Connection(parent.detach())
            conn.send(spec)
            self._conns.append(conn)
            self._procs.append(proc)
        for w, conn in enumerate(self._conns):
            _check_reply(self._recv(w, conn))

    def _recv(self, w: int, conn) -> tuple[str, Any]:
        try:
            return conn.recv()
        except (EOFError, ConnectionError):
            raise RuntimeError(f"calibration worker {w} (pid {self._procs[w].pid}) died "
                               f"(exit code {self._procs[w].poll()})") from None

    def send(self, w: int, message: tuple) -> None:
        self._conns[w].send(message)

    def receive(self) -> tuple[int, tuple[str, Any]]:
        from multiprocessing.connection import wait
        ready = wait(self._conns)
        w = self._conns.index(ready[0])
        return w, self._recv(w, ready[0])

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(None)
            except OSError:
                pass
        for proc in self._procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for conn in self._conns:
            conn.close()


def serve_socket(fd: int) -> None:
    """Body of a worker process: serve the master over the socket ``fd`` until it closes."""
    from multiprocessing.connection import Connection
    conn = Connection(fd)
    try:
        serve(conn.recv, conn.send)
    except (EOFError, ConnectionError, KeyboardInterrupt):  # the master went away or Ctrl-C
        pass


def mpi_world():
    """The MPI world communicator when running under mpirun with > 1 rank, else None.

    mpi4py is imported only then (importing it initialises MPI).
    """
    size = int(os.environ.get("OMPI_COMM_WORLD_SIZE", os.environ.get("PMI_SIZE", "1")))
    if size <= 1:
        return None
    from mpi4py import MPI
    return MPI.COMM_WORLD


class MpiTransport:
    """Ranks 1..len(specs) of ``comm`` are the workers; this rank (0) is the master.

    Ranks beyond them (more ranks than test points) are released at once with
    the stop message, instead of waiting (and spinning) until the pool closes.
    """

    def __init__(self, specs: list[WorkerSpec], comm):
        self.comm = comm
        self.n_workers = len(specs)
        for w, spec in enumerate(specs):
            comm.send(spec, dest=w + 1)
        for rank in range(self.n_workers + 1, comm.Get_size()):
            comm.send(None, dest=rank)
        for _ in specs:
            _check_reply(self.receive()[1])

    def send(self, w: int, message: tuple) -> None:
        self.comm.send(message, dest=w + 1)

    def receive(self) -> tuple[int, tuple[str, Any]]:
        from mpi4py import MPI
        status = MPI.Status()
        reply = self.comm.recv(source=MPI.ANY_SOURCE, status=status)
        return status.Get_source() - 1, reply

    def close(self) -> None:
        for w in range(self.n_workers):
            self.comm.send(None, dest=w + 1)


def serve_mpi(comm) -> None:
    """Body of an MPI worker rank: serve the master (rank 0) until it closes the pool."""
    serve(lambda: comm.recv(source=0), lambda obj: comm.send(obj, dest=0))


def _check_reply(reply: tuple[str, Any]) -> Any:
    status, value = reply
    if status == "error":
        raise value
    return value


class Pool:
    """Persistent workers evaluating test points; use as a context manager.

    Args:
        experiments: the experiments to reproduce.
        backend: builds a worker's evaluators (default: the particle engine).
        params: any valid parameter set to build the evaluators' model with.
        workers: number of workers (ignored under mpirun: the ranks other than 0).
    """

    def __init__(self, experiments: Experiments, params: ConnectorParams, *,
                 backend: Backend = particle_backend, workers: int = 2):
        n_points = len(experiments.problem.test_points)
        comm = mpi_world()
        asked = comm.Get_size() - 1 if comm is not None else workers
        n = max(1, min(asked, n_points))
        if n < asked:
            log.info("evaluation pool: %d workers asked for, %d used (one per test point at "
                     "most)%s", asked, n, "; the other MPI ranks are released"
                     if comm is not None else "")
        self.owner = np.arange(n_points) % n
        # the project's level (configure_logging keeps the root logger at WARNING)
        level = logging.getLogger("calibration").getEffectiveLevel()
        specs = [WorkerSpec(experiments, np.nonzero(self.owner == w)[0], backend, params, level)
                 for w in range(n)]
        if comm is not None:
            self.transport = MpiTransport(specs, comm)
        elif n == 1:
            self.transport = InlineTransport(specs)
        else:
            self.transport = ProcessTransport(specs)
        self.n_workers = len(specs)
        log.info("evaluation pool: %d worker(s) via %s", self.n_workers,
                 type(self.transport).__name__)

    def __enter__(self) -> "Pool":
        return self

    def __exit__(self, *exc) -> None:
        self.transport.close()

    def map(self, fn: Callable, items: Iterable[tuple[int, tuple]], *,
            meanwhile: Callable[[], None] | None = None) -> Iterator[tuple[int, Any]]:
        """Run ``fn(worker, *args)`` for each ``(point, args)`` on the point's owner.

        Yields ``(item index, result)`` as calls complete; each worker runs its
        calls in the given order, one at a time. On a worker error, the calls
        already running finish, the items before the failed one still run, and the error of
        the first item (in ``items``' order) that failed is raised: which one that is does
        not depend on which worker answered first.

        ``meanwhile``: work of the calling process run while the workers run their first
        calls (the whole-body data next to the points' curves: the master would otherwise
        wait idle). Its error is raised after every call has answered, unless a worker's
        error comes first (as if it had run after the calls).
        """
        queues: dict[int, collections.deque] = collections.defaultdict(collections.deque)
        for i, (point, args) in enumerate(items):
            queues[int(self.owner[point])].append((i, args))
        running: dict[int, int] = {}

        def start(w: int) -> None:
            if queues[w]:
                i, args = queues[w].popleft()
                running[w] = i
                self.transport.send(w, (fn, args))

        for w in list(queues):
            start(w)
        own_error = None
        if meanwhile is not None:
            try:
                meanwhile()
            except BaseException as exc:  # noqa: BLE001 - raised once the workers answered
                own_error = exc
        errors: dict[int, BaseException] = {}
        while running:
            w, (status, value) = self.transport.receive()
            i = running.pop(w)
            if status == "error":
                errors[i] = value
            if not errors:
                start(w)
                yield i, value
            elif queues[w] and queues[w][0][0] < min(errors):
                start(w)  # an earlier item might fail too: its error is the one raised
        if errors:
            raise errors[min(errors)]
        if own_error is not None:
            raise own_error

    def by_owner(self, fn: Callable, points: Sequence[int], *args,
                 meanwhile: Callable[[], None] | None = None) -> tuple[list, np.ndarray]:
        """``fn(worker, *args, owned)`` on every worker owning some of ``points``, ``owned``
        its share of them (in their order). Returns the results, one per such worker, and
        where each entry of their concatenated shares sits in ``points``. ``meanwhile``: as
        :meth:`map`'s."""
        points = np.asarray(points, dtype=np.int64)
        groups = [g for g in (points[self.owner[points] == w] for w in range(self.n_workers))
                  if len(g)]
        out: list[Any] = [None] * len(groups)
        for i, value in self.map(fn, [(int(g[0]), args + (g,)) for g in groups],
                                 meanwhile=meanwhile):
            out[i] = value
        return out, _positions(np.concatenate(groups), points)

    def curves(self, kind: str, params: ConnectorParams, points: Sequence[int]) -> np.ndarray:
        """(len(points), S) normal-force curves [N] of test points ``points`` (indices)."""
        out, positions = self.by_owner(point_curves, points, kind, params)
        return in_point_order(out, positions)

    def curves_and_forces(self, kind: str, params: ConnectorParams, points: Sequence[int]
                          ) -> tuple[np.ndarray, np.ndarray | None]:
        """The (len(points), S) normal-force curves [N] of test points ``points`` (indices)
        and the (len(points), S, 3) force vectors [N] they are the inward-normal components
        of, None if the backend's evaluators do not give them (see
        :meth:`PointWorker.curves_and_forces`)."""
        out, positions = self.by_owner(point_curves_and_forces, points, kind, params)
        curves = in_point_order([c for c, _ in out], positions)
        if any(f is None for _, f in out):
            return curves, None
        return curves, in_point_order([f for _, f in out], positions)

    def total_cost(self, kind: str, params: ConnectorParams, points: Sequence[int],
                   reference: np.ndarray) -> float:
        """Sum of the points' costs ``G_j`` against ``reference`` (len(points), S) [N^2]."""
        return float(np.sum(point_costs(self.curves(kind, params, points), reference)))

    def forget_warm_starts(self) -> None:
        """Every worker's evaluators start cold at their next call.

        Called wherever calibration checkpoints (before each fit, sweep-start cost,
        damped update and the validation), so what follows a checkpoint does not depend
        on the evaluations before it and a resumed run repeats an uninterrupted one
        exactly, not to the Newton tolerance.
        """
        self._each_worker(forget_warm_starts)

    @contextlib.contextmanager
    def newton_tolerance(self, rtol: float | None) -> Iterator[None]:
        """Inside the block every evaluator solves to Newton tolerance ``rtol`` (relative to
        the indenter force; None: their own, nothing changes). Entering and leaving starts
        them cold, so no curve after the block depends on an equilibrium of looser tolerance.
        """
        if rtol is None:
            yield
            return
        self._each_worker(set_newton_tolerance, rtol)
        try:
            yield
        finally:
            self._each_worker(set_newton_tolerance, None)

    def _each_worker(self, fn: Callable, *args) -> list:
        """``fn(worker, *args)`` once on every worker; the results in worker order."""
        calls = [(int(np.nonzero(self.owner == w)[0][0]), args) for w in range(self.n_workers)]
        out: list = [None] * self.n_workers
        for i, value in self.map(fn, calls):
            out[i] = value
        return out

    def evaluations(self) -> int:
        """Point-curves computed by all workers so far."""
        return sum(self._each_worker(evaluation_count))


def in_point_order(parts: Sequence[np.ndarray], positions: np.ndarray,
                   per_point: tuple[int, ...] | None = None) -> np.ndarray:
    """The workers' point-major results of :meth:`Pool.by_owner` concatenated and put in the
    order of the points asked for: (P, *per_point) (default per point: the parts' rows)."""
    rows = np.concatenate(parts)
    if per_point is not None:
        rows = rows.reshape((len(positions),) + tuple(per_point))
    out = np.empty_like(rows)
    out[positions] = rows
    return out


def _positions(order: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Where each entry of ``order`` sits in ``points`` (both permutations of the same ids)."""
    where = {int(p): i for i, p in enumerate(points)}
    return np.array([where[int(p)] for p in order], dtype=np.int64)
