"""The calibration's evaluation pool with more workers than test points: the extra MPI ranks
are released at once, the clamp is logged."""
import logging
import sys
import types

import numpy as np
import pytest

from calibration.pool import Experiments, MpiTransport, Pool, serve
from calibration.synthetic import box_scene
from forcecal.problem import Problem, build_problem
from particle.params import ConnectorParams


def test_an_idle_worker_is_released_by_its_first_message():
    sent = []
    serve(iter([None]).__next__, sent.append)  # no spec: return before building anything
    assert sent == []


class FakeComm:
    """Rank 0's view of an MPI world of ``size`` ranks whose workers accept any spec."""

    def __init__(self, size: int):
        self.size, self.sent, self.replies = size, [], []

    def Get_size(self) -> int:
        return self.size

    def send(self, obj, dest: int) -> None:
        self.sent.append((dest, obj))
        if obj is not None:
            self.replies.append((dest, ("ok", None)))

    def recv(self, source, status):
        status.source, reply = self.replies.pop(0)
        return reply


class FakeStatus:
    source = -1

    def Get_source(self) -> int:
        return self.source


def test_mpi_ranks_beyond_the_workers_are_released_at_once(monkeypatch):
    monkeypatch.setitem(sys.modules, "mpi4py",
                        types.SimpleNamespace(MPI=types.SimpleNamespace(Status=FakeStatus,
                                                                        ANY_SOURCE=-1)))
    comm = FakeComm(size=5)  # 4 worker ranks for 2 workers' worth of points
    transport = MpiTransport(["spec 0", "spec 1"], comm)
    assert comm.sent == [(1, "spec 0"), (2, "spec 1"), (3, None), (4, None)]
    transport.close()
    assert comm.sent[4:] == [(1, None), (2, None)]  # the released ranks get nothing more


def test_pool_uses_at_most_one_worker_per_test_point(tmp_path, caplog):
    p = build_problem(box_scene(tmp_path, test_points={"n_calibration": 4, "n_held_out": 8}))
    one = Problem(p.mesh, p.fixed, p.calibration[:1], p.held_out[:0], p.tracked_node)
    experiments = Experiments(one, 1000.0, np.array([1e-3]), np.array([0.0]), np.array([0.0]),
                              (-0.5, 0.5))

    def backend(experiments, points, params):
        return {"indentation": lambda params, pts=None: np.ones((len(pts), 1))}

    params = ConnectorParams.uniform(len(p.mesh.edges), K0=1.0, k1=1.0, b1=1.0, k2=1.0, b2=10.0)
    caplog.set_level(logging.INFO, logger="calibration.pool")
    with Pool(experiments, params, backend=backend, workers=3) as pool:
        assert pool.n_workers == 1
        np.testing.assert_array_equal(pool.curves("indentation", params, [0]), [[1.0]])
    assert "3 workers asked for, 1 used (one per test point at most)" in caplog.text


class _ToleranceEcho:
    """An evaluator whose curve is its Newton tolerance (what the pool set, per worker)."""

    def __init__(self):
        self.rtol = 1e-8

    def set_tolerance(self, rtol):
        self.rtol = 1e-8 if rtol is None else rtol

    def __call__(self, params, points=None):
        return np.full((len(points), 1), self.rtol)


def _echo_backend(experiments, points, params):
    return {"indentation": _ToleranceEcho()}


def test_newton_tolerance_reaches_every_worker_for_the_block_only(tmp_path):
    """Pool.newton_tolerance sets every worker's evaluators (worker processes included) and
    gives them their own back when the block ends, also when it ends by an error."""
    p = build_problem(box_scene(tmp_path, test_points={"n_calibration": 4, "n_held_out": 8}))
    experiments = Experiments(p, 1000.0, np.array([1e-3]), np.array([0.1]), np.array([1e-3]),
                              (-0.5, 0.5))
    params = ConnectorParams.uniform(len(p.mesh.edges), K0=1.0, k1=1.0, b1=1.0, k2=1.0, b2=10.0)
    points = np.arange(4)
    with Pool(experiments, params, backend=_echo_backend, workers=2) as pool:
        assert pool.n_workers == 2
        with pool.newton_tolerance(1e-6):
            np.testing.assert_array_equal(pool.curves("indentation", params, points), 1e-6)
        np.testing.assert_array_equal(pool.curves("indentation", params, points), 1e-8)
        with pool.newton_tolerance(None):  # nothing changes
            np.testing.assert_array_equal(pool.curves("indentation", params, points), 1e-8)
        with pytest.raises(KeyError), pool.newton_tolerance(1e-5):
            raise KeyError("a fit failed")
        np.testing.assert_array_equal(pool.curves("indentation", params, points), 1e-8)


class _LateTransport:
    """Runs each call at once but delivers the replies of worker 0 after those of worker 1
    (the other worker answering first, as a loaded machine may order them)."""

    def __init__(self):
        self.pending = []

    def send(self, w, message):
        fn, args = message
        try:
            reply = ("ok", fn(None, *args))
        except Exception as exc:  # noqa: BLE001 - returned as a worker returns it
            reply = ("error", exc)
        self.pending.append((w, reply))

    def receive(self):
        self.pending.sort(key=lambda item: item[0] == 0)  # worker 1's replies first
        return self.pending.pop(0)


def _fails(_worker, name):
    if name.startswith("fail"):
        raise ValueError(name)
    return name


def test_a_worker_error_raised_is_the_first_items_whatever_the_reply_order():
    """The error a map raises is the first failing item's in the items' order, not the first
    to arrive (which varies from run to run): items before it still run, items after it are
    not started."""
    pool = Pool.__new__(Pool)  # the map only: a fake transport, two workers
    pool.owner = np.array([0, 0, 1, 0])
    pool.transport = _LateTransport()
    items = [(0, ("ok 0",)), (1, ("fail 1",)), (2, ("fail 2",)), (3, ("fail 3",))]
    with pytest.raises(ValueError, match="fail 1"):  # worker 1's "fail 2" arrives first
        list(pool.map(_fails, items))
    pool.transport = _LateTransport()
    assert sorted(pool.map(_fails, [(0, ("ok 0",)), (2, ("ok 2",))])) == [(0, "ok 0"),
                                                                         (1, "ok 2")]


def test_the_masters_own_work_runs_while_the_workers_run_and_its_error_comes_last():
    """``meanwhile`` runs after the first calls are sent and before any reply is read; its
    error is raised once every call has answered (the next map starts clean), and a worker's
    error takes precedence over it (as if the master's work had run after the calls)."""
    pool = Pool.__new__(Pool)
    pool.owner = np.array([0, 1])
    pool.transport = _LateTransport()
    seen = []

    def meanwhile():
        seen.append(len(pool.transport.pending))  # both calls sent, none received

    assert sorted(pool.map(_fails, [(0, ("ok 0",)), (1, ("ok 1",))], meanwhile=meanwhile)) \
        == [(0, "ok 0"), (1, "ok 1")]
    assert seen == [2]

    def broken():
        raise KeyError("master")

    with pytest.raises(KeyError, match="master"):
        list(pool.map(_fails, [(0, ("ok 0",)), (1, ("ok 1",))], meanwhile=broken))
    assert not pool.transport.pending  # every reply was read
    with pytest.raises(ValueError, match="fail 1"):
        list(pool.map(_fails, [(0, ("ok 0",)), (1, ("fail 1",))], meanwhile=broken))
