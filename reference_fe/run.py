"""Compute a scene's whole FE reference and write ``reference.h5``: :func:`compute_reference`.

Work items are the indentation curve and the relaxation curve of every test
point, the static sag, the dynamic gravity run, the whole-body data, and the second support's
static sag and release (one item, ``second_support``), of the experiments the
scene asks for (``experiments``; the others are not computed). Under ``mpirun -n K`` every
rank builds one :class:`~reference_fe.model.FEModel` on ``MPI.COMM_SELF``
(forms compiled once per process) and claims items one at a time, largest
first, by creating ``<item>.claim`` exclusively in the checkpoint folder
``<out>.parts/`` (dynamic load balancing without messages). Each finished item
is written there atomically as ``<item>.npz``; an interrupted run resumes from
them. Rank 0 then gathers the parts, writes ``reference.h5`` atomically and
deletes the folder. Items never depend on the rank that computed them, so the
result equals the serial one. Ranks share the output folder's filesystem (one
machine, as ``mpirun`` is used here).

Failures (:mod:`forcecal.fe_failures`): the mesh preflight
(:func:`forcecal.preflight.run_preflight`) runs first and refuses a support that does not
hold the body; then the static sag runs before every other item and the dynamic gravity
run only after it converged. A test point whose indentation or relaxation fails is
recorded in the folder (``<item>.failed``) and does not stop the others; when every item of
a round is done, rank 0 replaces each failed point by the next candidate of the scene's
selection rule (or drops it from an explicit list) and the ranks compute the replacements'
items in the next round. The decisions are a function of the recorded failures, so a
resumed run decides the same. More than a quarter of the points failing stops the run
(every rank, at its next step). A failed gravity test leaves both gravity experiments out,
a failed second-support test ``second_support`` (a second support that does not hold the
body is refused before any FE work, :func:`forcecal.problem.check_second_support`);
``reference.h5`` records all of it (``fe_failures``). The whole-body data (experiment
``body``, asked for explicitly) failing stops the run, its error naming the item. The
discretisation floor (experiment ``floor``, :mod:`reference_fe.floor`) builds its own
vertex-dof models on the particle mesh and records a failed run in its arrays.

Parts and stored results are keyed per experiment (:mod:`reference_fe.keys`:
the scene sections it reads, the mesh, the FE code), not on the experiments
list. An experiment that ``<out>`` (the previous ``reference.h5``) already
holds with the same key is taken from it instead of being recomputed, and
is kept in the new file even if the scene no longer asks for it: the file is
a superset of what the scene needs (its ``experiments`` attribute lists what
it holds, ``reused`` what was taken over and ``items_computed`` the items
this run computed).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import os
import shutil
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO, TypeVar

import numpy as np
from mpi4py import MPI
from tqdm import tqdm

import dolfinx
from forcecal import errors
from forcecal.errors import (ConvergenceError, DataFileError, ForcecalError, SceneError,
                             StabilityError)
from forcecal.cost import check_cost
from forcecal.failures import collective
from forcecal.fe_failures import (FEFailures, PointFailure, common_features, punch_reach, replay,
                                  too_many_failures, with_point, with_preflight)
from forcecal.preflight import run_preflight, tet_quality
from forcecal.h5io import (GravityResult, IndentationCurves, Reference, RelaxationCurves,
                           SecondSupportResult, atomic_path, read_reference, write_reference)
from forcecal.indenter import indenter_footprints, punch_footprint
from forcecal.problem import (Problem, build_problem, check_second_support, replacement_point,
                              second_support)
from forcecal.scene import EXPERIMENTS, GRAVITY_EXPERIMENTS, SECOND_SUPPORT_PARTS, Scene
from forcecal.schedules import indentation_depths, relaxation_schedule
from forcecal.sections import REFERENCE_SECTIONS
from reference_fe import body, experiments, floor
from reference_fe.keys import experiment_keys
from reference_fe.model import FEModel
from reference_fe.refine import (FEProblem, check_memory, estimated_dofs, fe_clamp, fe_problem,
                                 patch_on_fe_mesh, rim_refined_problem)

log = logging.getLogger(__name__)

KINDS = ("indentation", "relaxation", "gravity_static", "gravity_dynamic", "body",
         "second_support", "floor")
#: the items that build their own FE models (not the reference's: :mod:`reference_fe.floor`)
OWN_MODEL_KINDS = ("floor",)
T = TypeVar("T")


@dataclass(frozen=True)
class WorkItem:
    """One independent piece of the reference.

    Attributes:
        kind: one of :data:`KINDS`.
        point: index into ``problem.test_points`` (-1 for the gravity runs): the slot.
        cost: estimated Newton solves (orders the items, largest first).
        replacement: 0 for the scene's own test point, k for the k-th vertex that replaced
            it after a failure (:mod:`forcecal.fe_failures`).
        vertex: the test vertex of a replacement (its part is keyed on it); -1 otherwise.
    """
    kind: str
    point: int
    cost: float
    replacement: int = 0
    vertex: int = -1

    @property
    def name(self) -> str:
        if self.point < 0:
            return self.kind
        name = f"{self.kind}-{self.point:04d}"
        return f"{name}-r{self.replacement}" if self.replacement else name


#: the items that can fail for the whole scene run first, cheapest first (fail fast)
FIRST = ("gravity_static",)
#: item -> the item that must have converged before it starts (the release needs a sag)
AFTER = {"gravity_dynamic": "gravity_static"}


def work_items(scene: Scene, n_points: int, kinds: tuple[str, ...] | None = None
               ) -> list[WorkItem]:
    """The items of the experiments ``kinds`` (default: the scene's ``experiments``):
    the static sag first (:data:`FIRST`), then largest estimated cost first (better load
    balance)."""
    kinds = scene.experiments if kinds is None else kinds
    g = scene.gravity
    # observed Newton iterations per step: ~2 quasi-static, ~3 dynamic, ~5 for the sag
    dynamic, static = 3.0 * g.duration / g.fe_dt, 5.0 * g.static_load_steps
    gravity_test = dynamic + static
    items = [WorkItem("gravity_dynamic", -1, dynamic),
             WorkItem("gravity_static", -1, static),
             # two static loads and two eigen-solves (each about a factorisation's cost)
             WorkItem("body", -1, 2 * 5.0 * scene.body.load_steps + 2.0),
             # the second support's sag and release, one item
             WorkItem("second_support", -1, gravity_test),
             # each floor element's gravity test, second-support test and held-out curves on
             # the particle mesh's vertex dofs (a Newton solve a fraction of the reference's)
             WorkItem("floor", -1, floor.item_cost(
                 scene, gravity_test, sum(it.cost for it in point_items(scene, 0))))]
    for p in range(n_points):
        items.extend(point_items(scene, p))
    return sorted((it for it in items if it.kind in kinds),
                  key=lambda it: (it.kind not in FIRST, -it.cost))


def point_items(scene: Scene, point: int, replacement: int = 0, vertex: int = -1
                ) -> list[WorkItem]:
    """The relaxation and indentation items of test point ``point`` (slot)."""
    n_rel = scene.relaxation.ramp_steps + scene.relaxation.hold_steps
    return [WorkItem("relaxation", point, 2.0 * n_rel, replacement, vertex),
            WorkItem("indentation", point, 2.0 * scene.indentation.steps, replacement, vertex)]


def run_keys(scene: Scene, problem: Problem) -> dict[str, str]:
    """Identity of each experiment's computation (:func:`reference_fe.keys.experiment_keys`):
    checkpoint parts and stored results with another key are ignored."""
    return experiment_keys(scene, problem.mesh.fingerprint())


def indenter_experiments(scene: Scene) -> tuple[Callable[..., np.ndarray],
                                                  Callable[..., np.ndarray]]:
    """The FE experiments of ``indentation.indenter``: (static curve, relaxation curve).

    Each takes ``(model, fixed, vertex, normal, depths)`` or ``(model, fixed, vertex,
    normal, times, depths)`` and returns the (S, 3) indenter force, like
    :func:`~reference_fe.experiments.indentation_curve` and
    :func:`~reference_fe.experiments.relaxation_curve` (``"vertex"``) or their punch
    versions with the scene's ``indentation.radius`` (``"punch"``: the footprint rule applied
    on the given FE mesh, for a model on the particle mesh or on a mesh fitted to the disc).
    The reference itself goes through :func:`indenter_dofs`, which on a refined FE mesh
    holds the particle footprint's patch instead (the same punch as the particle model's);
    at ``fe.refine = 0`` the two hold the same nodes.

    Raises:
        SceneError: an indenter with no FE experiment.
    """
    indenter = scene.indentation.indenter
    if indenter == "vertex":  # the test vertex itself is displaced along its inward normal
        return experiments.indentation_curve, experiments.relaxation_curve
    if indenter == "punch":  # every FE node of the footprint is held (forcecal.indenter)
        radius = scene.indentation.radius
        return (functools.partial(experiments.punch_indentation_curve, radius=radius),
                functools.partial(experiments.punch_relaxation_curve, radius=radius))
    raise SceneError(f"indentation.indenter = {indenter!r}: the FE reference has no experiment "
                     "for it (known: 'vertex', 'punch')")


def check_indenter(scene: Scene, problem: Problem) -> None:
    """Refuse, before any FE work, a punch whose footprint on the particle mesh holds fewer than
    3 particles or touches the clamp (SceneError naming ``indentation.radius``); warn when 3/4
    of the test points' footprints hold particles beyond the punch's reach
    (:func:`forcecal.fe_failures.punch_reach`, at the shallowest depth the scene indents)."""
    ind = scene.indentation
    held = indenter_footprints(problem.mesh, problem.fixed, problem.test_points,
                               problem.normals, ind.indenter, ind.radius)
    depths = [getattr(scene, kind).depth for kind in ("indentation", "relaxation")
              if kind in scene.experiments]
    if ind.indenter == "punch" and depths:
        points = {int(v): (n, min(depths)) for v, n in zip(problem.test_points, problem.normals)}
        said = punch_reach(problem.mesh, points, dict(zip(points, held)), ind.radius,
                           "test points")
        if said:
            log.warning("%s; the FE punch runs there may not converge (docs/punch.md)", said)


def indenter_dofs(model: FEModel, scene: Scene, problem: Problem, fe: FEProblem,
                  point: int) -> np.ndarray:
    """(K, 3) FE dofs the indenter of test point ``point`` (index into ``problem.test_points``)
    holds: the vertex (``"vertex"``), or every FE node of the particle footprint's surface
    patch (``"punch"``, :func:`~reference_fe.refine.patch_on_fe_mesh`: at ``fe.refine = 0``
    the footprint's vertices and the mid-edge nodes of the surface edges between them)."""
    indenter_experiments(scene)  # an indenter without FE experiment is refused here
    vertex = int(problem.test_points[point])
    if scene.indentation.indenter == "vertex":
        return model.vertex_dofs[[int(fe.vertex_map[vertex])]]
    held = punch_footprint(problem.mesh, vertex, problem.normals[point],
                           scene.indentation.radius, fixed=problem.fixed)
    return model.surface_patch_dofs(*patch_on_fe_mesh(fe, problem.mesh, held))


def punch_problem(scene: Scene, problem: Problem, fe: FEProblem, point: int) -> FEProblem:
    """The FE problem of the punch at test point ``point`` (index into
    ``problem.test_points``): ``fe``'s mesh refined ``fe.local_refine`` times near the rim of
    its footprint's patch (:func:`~reference_fe.refine.rim_refined_problem`)."""
    held = punch_footprint(problem.mesh, int(problem.test_points[point]),
                           problem.normals[point], scene.indentation.radius, fixed=problem.fixed)
    local = rim_refined_problem(fe, problem.mesh, held, scene.fe.local_refine)
    log.debug("punch at vertex %d: FE mesh %s", problem.test_points[point],
              local.problem.mesh.summary())
    return local


def punch_model(scene: Scene, problem: Problem, fe: FEProblem,
                point: int) -> tuple[FEProblem, FEModel]:
    """The FE problem (:func:`punch_problem`) and model of the punch at test point ``point``."""
    local = punch_problem(scene, problem, fe, point)
    return local, FEModel(local.problem.mesh, scene.material, scene.fe)


def largest_punch_dofs(scene: Scene, problem: Problem) -> int | None:
    """Length of the solution vector of the largest punch model of the test points (None
    without rim refinement), for :func:`~reference_fe.refine.check_memory`.

    Counted on every punch's refined mesh, not estimated: the dofs a rim refinement adds depend
    on the cells along that rim (x2.03 per level for the default liver's largest punch, x3.5
    on SOFA's coarse liver). The meshes alone, without models: 4.3 s for the default liver's
    31 points at ``local_refine = 3``."""
    if not (scene.indentation.indenter == "punch" and scene.fe.local_refine):
        return None
    fe = fe_problem(problem, scene.fe)
    return max(estimated_dofs(punch_problem(scene, problem, fe, point).problem.mesh,
                              scene.fe.element, 0)
               for point in range(len(problem.test_points)))


def compute_item(model: FEModel, scene: Scene, problem: Problem, item: WorkItem,
                 fe: FEProblem | None = None, after: dict | None = None) -> dict:
    """Arrays of one work item (keys as stored in its checkpoint part), at the particle
    vertices; ``fe`` is the FE mesh's problem ``model`` was built on (default: ``problem``
    itself, ``fe.refine = 0``); ``after`` the arrays of the item it waits for
    (:data:`AFTER`: the release checks its motion against the static sag), if known."""
    fe = FEProblem(problem, np.arange(problem.mesh.n_vertices), 0) if fe is None else fe
    fixed, at_particles = fe.problem.fixed, fe.vertex_map
    if item.kind in ("indentation", "relaxation"):
        indenter_experiments(scene)  # an indenter without FE experiment: refused before a solve
    model.forget_tangent()  # the item's result does not depend on the rank's earlier items
    g = scene.gravity
    if item.kind == "second_support":
        return second_support_runs(model, scene, problem, fe)
    if item.kind == "floor":
        return floor.floor_arrays(scene, problem)
    if item.kind == "gravity_static":
        disp = experiments.gravity_static(model, fixed, g.acceleration, g.static_load_steps)
        return {"displacement": disp[at_particles]}
    if item.kind == "gravity_dynamic":
        times, disp = experiments.gravity_dynamic(
            model, fixed, g.acceleration, g.duration, g.fe_dt, g.record_interval,
            static_sag=(None if after is None
                        else experiments.largest_displacement(after["displacement"])),
            watched=at_particles)
        return {"time": times, "displacement": disp[:, at_particles]}
    if item.kind == "body":
        return body.at_vertices(body.body_data(model, fixed, np.asarray(g.acceleration, float),
                                               scene.body.modes, scene.body.load_steps),
                                at_particles)
    if scene.indentation.indenter == "punch" and scene.fe.local_refine:
        fe, model = punch_model(scene, problem, fe, item.point)
        try:
            return indenter_item(model, scene, problem, item, fe)
        finally:
            model.destroy()  # its memory now, failed or not (FEModel.destroy)
    return indenter_item(model, scene, problem, item, fe)


def indenter_item(model: FEModel, scene: Scene, problem: Problem, item: WorkItem,
                  fe: FEProblem) -> dict:
    """The force curve of an indentation or relaxation item on ``model``, built on ``fe``'s
    mesh (:func:`compute_item`)."""
    fixed = fe.problem.fixed
    dofs = indenter_dofs(model, scene, problem, fe, item.point)
    normal = problem.normals[item.point]  # refinement keeps it (coplanar sub-faces)
    what = f"{scene.indentation.indenter} {item.kind} at vertex {problem.test_points[item.point]}"
    if item.kind == "indentation":
        force = experiments.held_indentation_curve(model, fixed, dofs, normal,
                                                   indentation_depths(scene.indentation), what)
    else:
        times, depths = relaxation_schedule(scene.relaxation)
        force = experiments.held_relaxation_curve(model, fixed, dofs, normal, times, depths,
                                                  what)
    return {"force": force}


def gravity_test(model: FEModel, scene: Scene, fixed: np.ndarray, at_particles: np.ndarray,
                 section: str = "fixed") -> dict:
    """The scene's gravity test on ``model`` with the FE vertices ``fixed`` clamped by the rule
    of scene section ``section`` (``fixed`` or ``second_support``): the static sag and the
    release (:func:`~reference_fe.experiments.gravity_static`,
    :func:`~reference_fe.experiments.gravity_dynamic`, the scene's ``[gravity]``) at the
    particle vertices ``at_particles`` (N,): ``static_displacement`` (N, 3) [m], ``time`` (S,)
    [s], ``displacement`` (S, N, 3) [m].

    A failure keeps its class (:data:`ITEM_FAILURES` are recorded) and says which part failed
    in its ``experiment`` attribute (``gravity_static`` / ``gravity_dynamic``, or
    ``second_support_static`` / ``second_support_dynamic``).
    """
    g = scene.gravity
    parts = SECOND_SUPPORT_PARTS if section == "second_support" else GRAVITY_EXPERIMENTS
    part = parts[0]
    try:
        static = experiments.gravity_static(model, fixed, g.acceleration, g.static_load_steps,
                                            section=section)
        part = parts[1]
        times, disp = experiments.gravity_dynamic(
            model, fixed, g.acceleration, g.duration, g.fe_dt, g.record_interval,
            section=section, static_sag=experiments.largest_displacement(static[at_particles]),
            watched=at_particles)
    except ITEM_FAILURES as exc:
        exc.experiment = part
        raise
    return {"static_displacement": static[at_particles], "time": times,
            "displacement": disp[:, at_particles]}


def second_support_runs(model: FEModel, scene: Scene, problem: Problem, fe: FEProblem) -> dict:
    """The arrays of the ``second_support`` item: :func:`gravity_test` with the second support's
    vertices clamped (:func:`forcecal.problem.second_support`; on a refined FE mesh its P2
    clamp, :func:`~reference_fe.refine.fe_clamp`)."""
    fixed = fe_clamp(problem, second_support(scene, problem).fixed, fe, scene.fe)
    return gravity_test(model, scene, fixed, fe.vertex_map, "second_support")


class _Parts:
    """The checkpoint folder ``<out>.parts/``: finished items, claims and a failure note.

    One ``.npz`` per work item, each holding its experiment's key, because the ranks
    write them concurrently (why the calibration's single-writer JSON checkpoint is
    another mechanism: :mod:`calibration.checkpoint`)."""

    def __init__(self, out_path: Path, key: str | dict[str, str]):
        self.folder = out_path.with_name(out_path.name + ".parts")
        self.key = key  # one key, or one per experiment (:func:`run_keys`)
        # item name -> the arrays of an item taken over from the previous reference instead of
        # computed (those another item waits for, :data:`AFTER`), on every rank
        self.reused: dict[str, dict] = {}

    def key_of(self, item: WorkItem) -> str:
        key = self.key[item.kind] if isinstance(self.key, dict) else self.key
        # a replacement's part is valid for its vertex only
        return f"{key} vertex {item.vertex}" if item.replacement else key

    def _path(self, item: WorkItem, suffix: str) -> Path:
        return self.folder / f"{item.name}.{suffix}"

    def path(self, item: WorkItem) -> Path:
        """The finished part of ``item`` (present once it is complete: written atomically)."""
        return self._path(item, "npz")

    def load(self, item: WorkItem) -> dict | None:
        """The stored arrays of ``item`` if present and computed for this run key."""
        path = self.path(item)
        if not path.is_file():
            return None
        try:
            with np.load(path) as data:
                if str(data["run_key"]) != self.key_of(item):
                    return None
                return {k: data[k] for k in data.files if k != "run_key"}
        except Exception as exc:  # noqa: BLE001 - truncated (BadZipFile, EOFError), damaged
            log.warning("discarding the unreadable checkpoint part %s (%s: %s); its work item "
                        "is computed again", path, type(exc).__name__, exc)
            path.unlink(missing_ok=True)
            return None

    def arrays(self, item: WorkItem) -> dict | None:
        """The arrays of ``item``: its finished part, or those taken over from the previous
        reference (:attr:`reused`); None when neither is there."""
        arrays = self.load(item)
        return self.reused.get(item.name) if arrays is None else arrays

    def save(self, item: WorkItem, arrays: dict) -> None:
        with atomic_path(self.path(item)) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, run_key=self.key_of(item), **arrays)

    def done(self, item: WorkItem) -> bool:
        """Whether ``item`` has a finished part of this run key (reads only the key)."""
        try:
            with np.load(self.path(item)) as data:
                return str(data["run_key"]) == self.key_of(item)
        except Exception:  # noqa: BLE001 - absent, truncated, damaged: not done (load says)
            return False

    def failure_path(self, item: WorkItem) -> Path:
        """The failure record of ``item`` (present once it failed: written atomically)."""
        return self._path(item, "failed")

    def save_failure(self, item: WorkItem, error: Exception, seconds: float,
                     vertex: int) -> None:
        """Record that ``item`` (of test vertex ``vertex``, -1 for gravity) failed: its error
        class, message and how far it got (the error's ``reached`` attribute, if any)."""
        record = {"run_key": self.key_of(item), "kind": item.kind, "point": item.point,
                  "replacement": item.replacement, "vertex": vertex,
                  # the part of an item of two experiments that failed (the second support)
                  "experiment": getattr(error, "experiment", item.kind),
                  "error": type(error).__name__, "reason": str(error),
                  "reached": getattr(error, "reached", None), "seconds": seconds}
        with atomic_path(self.failure_path(item)) as tmp:
            tmp.write_text(json.dumps(record))

    def failure(self, item: WorkItem) -> dict | None:
        """The failure record of ``item`` for this run key, or None."""
        try:
            record = json.loads(self.failure_path(item).read_text())
        except (OSError, ValueError):
            return None
        return record if record.get("run_key") == self.key_of(item) else None

    def point_failures(self) -> list[PointFailure]:
        """Every test point failure recorded for this run key, in slot order."""
        out = []
        for path in sorted(self.folder.glob("*.failed")):
            try:
                record = json.loads(path.read_text())
                item = WorkItem(record["kind"], int(record["point"]), 0.0,
                                int(record["replacement"]),
                                int(record["vertex"]) if record["replacement"] else -1)
            except (OSError, ValueError, KeyError, TypeError):
                continue
            if item.point < 0 or record.get("run_key") != self.key_of(item):
                continue
            reached = record.get("reached")
            unit = "depth_m" if item.kind == "indentation" else "time_s"
            out.append(PointFailure(item.point, int(record["vertex"]), item.kind,
                                    record["reason"], {} if reached is None else
                                    {unit: float(reached)}))
        return sorted(out, key=lambda f: (f.slot, f.vertex, f.experiment))

    def test_failure(self, items: list[WorkItem], kinds: tuple[str, ...]) -> dict | None:
        """The ``fe_failures`` record (``gravity``, ``second_support``) of the first failed
        item of ``items`` of ``kinds``, None when none failed: the experiment (the part of
        the item that failed), the reason and how far it got."""
        for item in items:
            if item.kind not in kinds:
                continue
            record = self.failure(item)
            if record is not None:
                experiment = record.get("experiment", item.kind)
                unit = "load_factor" if experiment.endswith("_static") else "time_s"
                reached = record.get("reached")
                return {"experiment": experiment, "reason": record["reason"],
                        "reached": {} if reached is None else {unit: float(reached)}}
        return None

    def claim(self, item: WorkItem) -> bool:
        """True if this process is the first to claim ``item``."""
        try:
            os.close(os.open(self._path(item, "claim"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return False
        return True

    def start(self) -> None:
        """Take the folder over for this run (rank 0).

        Claims and a failure note left by an interrupted run are cleared, but not
        while another live process computes the same output (its claims would be lost).

        Raises:
            DataFileError: the folder cannot be created, or another process uses it.
        """
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataFileError(f"cannot create the checkpoint folder {self.folder}: "
                                f"{exc}") from None
        owner = self.folder / "OWNER"
        if owner.is_file():
            host, _, pid = owner.read_text().partition(" ")
            if pid.strip().isdigit() and int(pid) != os.getpid() and _alive(host, int(pid)):
                raise DataFileError(f"{self.folder} is in use by process {pid.strip()} on "
                                    f"{host}, which computes the same reference; wait for it "
                                    "(or delete the folder if that process is gone)")
        owner.write_text(f"{socket.gethostname()} {os.getpid()}")
        for claim in self.folder.glob("*.claim"):
            claim.unlink()
        (self.folder / "FAILED").unlink(missing_ok=True)

    def fail(self, message: str) -> None:
        (self.folder / "FAILED").write_text(message)

    @property
    def failed(self) -> bool:
        return (self.folder / "FAILED").exists()


def progress_stream(progress: bool, rank: int) -> TextIO | None:
    """Where rank 0 draws the bar of finished items, or None for no bar.

    On stderr if it is a terminal, else on stdout if that is one (under ``mpirun``,
    OpenMPI hands its ranks a pseudo-terminal as stdout but a pipe as stderr), else on
    stderr if the environment sets ``FORCECAL_PROGRESS=1``. ``progress=False``
    (``--no-progress``) always wins.
    """
    if not progress or rank != 0:
        return None
    for stream in (sys.stderr, sys.stdout):
        if stream.isatty():
            return stream
    return sys.stderr if os.environ.get("FORCECAL_PROGRESS") == "1" else None


class _Progress:
    """A tqdm bar on ``stream`` that ticks once per finished (or failed) work item, with its
    name.

    It counts the items every rank finishes: a thread polls the checkpoint folder
    (every :attr:`POLL_S` seconds, and after each of this rank's items), so the bar moves
    while rank 0 computes a long item itself. Items already done when it starts are in
    its initial count; the items of a later round (replacement points) are added with
    :meth:`extend`. ``stream=None``: no bar, no thread.
    """

    POLL_S = 0.5

    def __init__(self, parts: _Parts, items: list[WorkItem], stream: TextIO | None):
        self._bar = None
        if stream is None:
            return
        self._parts = parts
        self._paths: dict[str, tuple[Path, Path]] = {}
        self._pending: dict[str, tuple] = {}
        self._lock = threading.Lock()
        # every tick is drawn (items take seconds, so this cannot flood the terminal)
        self._bar = tqdm(total=0, desc="FE reference", unit="item", file=stream,
                         mininterval=0, miniters=1)
        self.extend(items)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fe-progress", daemon=True)
        self._thread.start()

    def extend(self, items: list[WorkItem]) -> None:
        """Count ``items`` too (those already finished as done)."""
        if self._bar is None:
            return
        with self._lock:
            for it in items:
                self._paths[it.name] = (self._parts.path(it), self._parts.failure_path(it))
            # an item is pending until its part appears or changes (a stale part is replaced)
            pending = {it.name: self._stamp(it.name) for it in items
                       if not self._parts.done(it) and self._parts.failure(it) is None}
            self._pending.update(pending)
            self._bar.total += len(items)
            self._bar.update(len(items) - len(pending))

    def _stamp(self, name: str) -> tuple[int | None, ...]:
        out = []
        for path in self._paths[name]:
            try:
                out.append(path.stat().st_mtime_ns)
            except OSError:
                out.append(None)
        return tuple(out)

    def _run(self) -> None:
        while not self._stop.wait(self.POLL_S):
            self.poll()

    def poll(self) -> None:
        """Tick for every item whose part (or failure record) appeared since the last poll."""
        if self._bar is None:
            return
        with self._lock:
            for name, stamp in list(self._pending.items()):
                now = self._stamp(name)
                if any(t is not None and t != t0 for t, t0 in zip(now, stamp)):
                    del self._pending[name]
                    self._bar.set_postfix_str(name, refresh=False)
                    self._bar.update(1)

    def close(self) -> None:
        if self._bar is None:
            return
        self._stop.set()
        self._thread.join()
        self.poll()
        self._bar.close()


def _alive(host: str, pid: int) -> bool:
    """Whether process ``pid`` runs (a process on another host is assumed to)."""
    if host != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def compute_reference(scene: Scene, problem: Problem | None = None, *, out_path: str | Path,
                      progress: bool = True) -> Reference:
    """Compute the scene's experiments: every test point's indentation and relaxation curves,
    the gravity runs (those of ``scene.experiments``; an experiment ``out_path`` already
    holds with the same key is reused, see the module docstring).

    Serial, or under ``mpirun -n K`` (items distributed over the ranks of
    ``MPI.COMM_WORLD``, see the module docstring). Writes ``out_path``
    (``reference.h5``, atomically) on rank 0 and returns the
    :class:`~forcecal.h5io.Reference` on every rank. Failed test points are replaced or
    dropped and a failed gravity test is left out (module docstring), all recorded in the
    reference (:attr:`~forcecal.h5io.Reference.fe_failures`).

    Args:
        problem: the scene's geometry; built with :func:`forcecal.problem.build_problem`
            (on rank 0, then broadcast) when None.
        out_path: the ``reference.h5`` to write; checkpoints go to ``<out_path>.parts/``.
        progress: show a bar of finished items on rank 0 (:func:`progress_stream`).

    Raises:
        StabilityError: the support does not hold the body (mesh preflight, before any FE
            work).
        DataFileError: another live process is computing the same ``out_path``.
        ConvergenceError: more than a quarter of the test points failed (the message says
            what they share); raised on every rank. An error that is not a convergence
            failure of an experiment (a bug, memory) stops the run too, keeping its
            ForcecalError class (anything else is a RuntimeError).
    """
    comm = MPI.COMM_WORLD
    start = time.perf_counter()
    out_path = Path(out_path)
    indenter_experiments(scene)  # an unknown indenter fails here, before any work
    if problem is None:
        problem = _on_root(comm, lambda: build_problem(scene))
    try:  # before any FE work
        check_cost(scene, problem.mesh.n_vertices, len(problem.mesh.edges))
    except SceneError as exc:  # every rank decides the same
        raise collective(exc) from None
    check_indenter(scene, problem)
    # a refinement that cannot fit: refused
    check_memory(problem.mesh, scene.fe, comm.size,
                 _on_root(comm, lambda: largest_punch_dofs(scene, problem)))
    preflight = _on_root(comm, lambda: run_preflight(scene, problem.mesh, problem.fixed))
    if scene.runs("second_support"):  # a second support that does not hold: refused here
        _on_root(comm, lambda: check_second_support(scene, problem))
    keys = run_keys(scene, problem)
    parts = _Parts(out_path, keys)
    previous: dict[str, dict] = {}

    def take_previous() -> tuple[list[str], dict[str, dict]]:
        previous.update(previous_results(out_path, keys, problem))
        return sorted(previous), previous_failures(out_path, keys)
    reused, failed_before = _on_root(comm, take_previous)  # arrays stay on rank 0
    parts.reused = _on_root(comm, lambda: {e: previous[e]["arrays"] for e in AFTER.values()
                                           if e in previous})
    skip = set(reused) | {e for test in failed_before for e in HELD_OUT_TESTS[test]}
    items = work_items(scene, len(problem.test_points),
                       tuple(e for e in scene.experiments if e not in skip))
    if reused or failed_before:
        log.info("reusing %s from %s (same keys); computing %d work item(s)",
                 ", ".join(reused + [f"the {test} failure" for test in failed_before]),
                 out_path, len(items))
    _on_root(comm, parts.start)
    mesh_seconds = time.perf_counter() - start

    points = _Points(scene, problem, parts)
    scheduled: list[WorkItem] = []
    computed: list[str] = []
    build_seconds = 0.0
    bar = _Progress(parts, items, progress_stream(progress, comm.rank))
    try:
        while items:  # a round: the items, then the replacements of the points that failed
            scheduled += items
            failure, seconds, done = _work(scene, points, items, parts, bar)
            build_seconds += seconds
            computed += [name for names in comm.allgather(done) for name in names]
            _raise_failures([f for f in comm.allgather(failure) if f is not None], parts)
            items = points.update(_on_root(comm, parts.point_failures))
            bar.extend(items)
    finally:
        bar.close()

    def finish() -> Reference:
        failures = {test: failed_before.get(test) or parts.test_failure(scheduled, kinds)
                    for test, kinds in HELD_OUT_TESTS.items()}
        # the preflight checked the scene's own support: a gravity failure it expected says so
        failures = points.records({**failures,
                                   "gravity": with_preflight(failures["gravity"], preflight)})
        if failures.gravity is not None:
            log.warning("the FE gravity test failed (%s: %s): both gravity experiments are "
                        "left out of %s, the force curves are kept", failures.gravity[
                            "experiment"], failures.gravity["reason"], out_path)
        if failures.second_support is not None:
            log.warning("the FE test of the second support failed (%s: %s): second_support "
                        "is left out of %s", failures.second_support["experiment"],
                        failures.second_support["reason"], out_path)
        reference = _assemble(scene, points, scheduled, parts, previous, computed, keys,
                              comm.size, mesh_seconds + build_seconds,
                              time.perf_counter() - start, failures, preflight)
        write_reference(out_path, reference)
        shutil.rmtree(parts.folder)
        log.info("wrote %s (%d test points, %.1f s)", out_path, len(points.current.test_points),
                 time.perf_counter() - start)
        return reference

    return _on_root(comm, finish)


def _raise_failures(failures: list[tuple[str, str]], parts: _Parts) -> None:
    """Raise, on every rank, the error that stopped the run (``(class name, message)`` of
    each rank that met one; none: return)."""
    if not failures:
        return
    kind = getattr(errors, failures[0][0], None)
    kind = kind if isinstance(kind, type) and issubclass(kind, ForcecalError) else RuntimeError
    kept = (f" (finished items are kept in {parts.folder}/ and reused by a rerun)"
            if parts.folder.is_dir() and any(parts.folder.glob("*.npz")) else "")
    messages = list(dict.fromkeys(m for _, m in failures))  # two ranks may say the same
    raise collective(kind("FE reference failed: " + "; ".join(messages) + kept))


class _Points:
    """The test points of a run: the scene's, with the failed ones replaced or dropped
    (:func:`forcecal.fe_failures.replay`, the same on every rank).

    Attributes:
        slots: the problem whose test point ``k`` is slot k's current vertex (replacements
            applied, dropped points still in place: the items' ``point`` indexes it).
        current: the problem the reference stores (dropped points removed).
    """

    def __init__(self, scene: Scene, problem: Problem, parts: _Parts):
        self.scene, self.original, self.parts = scene, problem, parts
        self.slots = self.current = problem
        self._records = FEFailures()
        self.replacements = [0] * len(problem.test_points)  # per slot
        self.dropped: set[int] = set()
        self._quality: np.ndarray | None = None
        self._logged = 0  # failures already logged (rank 0 logs the decisions)

    def _replacement(self, problem: Problem, index: int, tried: set[int]) -> int | None:
        return replacement_point(self.scene, problem, index, tried)

    def update(self, failures: list[PointFailure]) -> list[WorkItem]:
        """Apply every point failure recorded so far; return the items of the replacements
        not computed yet (none: the run is complete).

        Raises:
            ConvergenceError: more than a quarter of the test points failed.
        """
        error = self.too_many(failures)
        if error is not None:  # met here by a resumed run whose failures were all recorded
            raise collective(ConvergenceError(f"FE reference failed: {error}"))
        self.current, self._records, applied = replay(self.original, failures,
                                                      self._replacement)
        slots = self.original
        self.replacements = [0] * len(slots.test_points)
        for entry in self._records.replaced:
            slots = with_point(slots, entry["slot"], entry["by"])
            self.replacements[entry["slot"]] += 1
        self.slots = slots
        self.dropped = {entry["slot"] for entry in self._records.dropped}
        if MPI.COMM_WORLD.rank == 0:
            for f in applied[self._logged:]:
                self._log(f)
        self._logged = len(applied)
        items = []
        for slot, count in enumerate(self.replacements):
            if count and slot not in self.dropped:
                items += [it for it in point_items(self.scene, slot, count,
                                                   int(slots.test_points[slot]))
                          if it.kind in self.scene.experiments and not self.parts.done(it)
                          and self.parts.failure(it) is None]
        return items

    def _log(self, failure: PointFailure) -> None:
        for entry in self._records.replaced:
            if entry["slot"] == failure.slot and entry["point"] == failure.vertex:
                log.warning("test point %d (vertex %d, %s) failed in %s: replaced by vertex %d,"
                            " the next candidate of its selection rule (%s)", failure.slot,
                            failure.vertex, entry["role"], failure.experiment, entry["by"],
                            failure.reason)
                return
        log.warning("test point %d (vertex %d) failed in %s: dropped (an explicit list, or no "
                    "candidate left) (%s)", failure.slot, failure.vertex, failure.experiment,
                    failure.reason)

    def too_many(self, failures: list[PointFailure]) -> ConvergenceError | None:
        """The error that ends the run when more than a quarter of the points failed."""
        n_points = len(self.original.test_points)
        if too_many_failures(n_points, failures, []) is None:
            return None
        mesh = self.original.mesh
        if self._quality is None:
            self._quality = tet_quality(mesh)
        footprints = normals = None
        if self.scene.indentation.indenter == "punch":
            vertices = sorted({f.vertex for f in failures} | set(self.slots.test_points.tolist()))
            normals = dict(zip(vertices, mesh.inward_normals(np.array(vertices))))
            footprints = {v: punch_footprint(mesh, v, n, self.scene.indentation.radius,
                                             min_nodes=1)
                          for v, n in normals.items()}
        tested = np.union1d(self.slots.test_points, [f.vertex for f in failures])
        features = common_features(mesh, self.original.fixed, tested, failures,
                                   self._quality, footprints)
        if footprints is not None:
            depths: dict[int, float] = {}  # each failed vertex's shallowest failed experiment
            for f in failures:
                depth = getattr(self.scene, f.experiment).depth
                depths[f.vertex] = min(depths.get(f.vertex, depth), depth)
            failed = {v: (normals[v], depth) for v, depth in sorted(depths.items())}
            reach = punch_reach(mesh, failed, footprints, self.scene.indentation.radius)
            features += [reach] if reach else []
        return too_many_failures(n_points, failures, features)

    def records(self, tests: dict[str, dict | None]) -> FEFailures:
        """What failed and what was done, with the held-out body tests' failures (``{"gravity": ..,
        "second_support": ..}``, None: none)."""
        return dataclasses.replace(self._records, **tests)


def _on_root(comm: MPI.Comm, task: Callable[[], T]) -> T:
    """``task()`` run on rank 0, its result broadcast; any exception there is raised on
    every rank (the others would otherwise wait for rank 0 forever)."""
    result, error = None, None
    if comm.rank == 0:
        try:
            result = task()
        except Exception as exc:  # noqa: BLE001 - any error, or the others wait forever
            error = exc
    if comm.size > 1:
        try:
            result, error = comm.bcast((result, error), root=0)
        except Exception:  # an exception that does not pickle: send its text
            result, error = comm.bcast((None, RuntimeError(f"{type(error).__name__}: "
                                                           f"{error}")), root=0)
    if error is not None:
        raise collective(error)
    return result


def _work(scene: Scene, points: _Points, items: list[WorkItem], parts: _Parts,
          bar: _Progress) -> tuple[tuple[str, str] | None, float, list[str]]:
    """Claim and compute items until none is left.

    Returns ``(failure, build_seconds, computed)``: ``failure`` is None or (exception
    class name, message) of what stops the run; ``build_seconds`` the time spent building
    the FE model; ``computed`` the names of the items this rank computed.
    """
    experiments.set_stop_check(lambda: parts.failed)
    try:
        return _claim_and_compute(scene, points, items, parts, bar)
    except experiments.Stopped:  # another rank failed: its message is reported
        log.info("stopping: another rank's work item failed")
        return None, 0.0, []
    finally:
        experiments.set_stop_check(None)


#: seconds between two looks at the folder while the only items left wait for another one
WAIT_POLL_S = 0.2
#: an experiment that fails with these is recorded and the run goes on (anything else stops it)
ITEM_FAILURES = (ConvergenceError, StabilityError)
#: the items whose failure (:data:`ITEM_FAILURES`) is recorded: a test point's curves are
#: replaced or dropped, a failed gravity or second-support test is left out; any other item's
#: failure (the whole-body data, asked for explicitly) stops the run
RECORDED_KINDS = ("indentation", "relaxation") + GRAVITY_EXPERIMENTS + ("second_support",)


def _claim_and_compute(scene: Scene, points: _Points, items: list[WorkItem], parts: _Parts,
                       bar: _Progress) -> tuple[tuple[str, str] | None, float, list[str]]:
    model, fe, build_seconds, computed = None, None, 0.0, []
    pending = list(items)
    while pending:
        if parts.failed:  # another rank failed: stop early, its message is reported
            break
        item = _next_item(pending, items, parts)
        if item is None:
            if pending:  # what is left waits for an item another rank computes
                time.sleep(WAIT_POLL_S)
            continue
        t0 = time.perf_counter()
        try:
            if model is None and item.kind not in OWN_MODEL_KINDS:
                fe = fe_problem(points.slots, scene.fe)
                model = FEModel(fe.problem.mesh, scene.material, scene.fe)
                build_seconds = time.perf_counter() - t0
                t0 = time.perf_counter()
            after = (parts.arrays(WorkItem(AFTER[item.kind], item.point, 0.0))
                     if item.kind in AFTER else None)
            arrays = compute_item(model, scene, points.slots, item, fe, after)
        except experiments.Stopped:
            raise
        except Exception as exc:  # noqa: BLE001 - recorded, or reported on every rank
            if isinstance(exc, ITEM_FAILURES) and item.kind in RECORDED_KINDS:
                # recorded; the point is replaced or dropped later, or the held-out test left out
                vertex = int(points.slots.test_points[item.point]) if item.point >= 0 else -1
                parts.save_failure(item, exc, time.perf_counter() - t0, vertex)
                log.warning("%s%s failed: %s", item.name,
                            f" (vertex {vertex})" if vertex >= 0 else "", exc)
                too_many = (points.too_many(parts.point_failures()) if item.point >= 0
                            else None)
                if too_many is not None:
                    parts.fail(str(too_many))
                    return (type(too_many).__name__, str(too_many)), build_seconds, computed
                bar.poll()
                continue
            message = f"{item.name}: {exc}"  # not left to hang the other ranks
            parts.fail(message)
            log.error("%s", message)
            return (type(exc).__name__, message), build_seconds, computed
        arrays["seconds"] = np.float64(time.perf_counter() - t0)
        parts.save(item, arrays)
        computed.append(item.name)
        log.debug("%s done in %.2f s (%d Newton iterations so far on this rank)", item.name,
                  float(arrays["seconds"]), 0 if model is None else model.newton_iterations)
        bar.poll()
    return None, build_seconds, computed


def _next_item(pending: list[WorkItem], items: list[WorkItem], parts: _Parts
               ) -> WorkItem | None:
    """The first item of ``pending`` this rank may compute, claimed (and removed from
    ``pending``), or None if every item left waits for another one (:data:`AFTER`).

    Dropped from ``pending`` on the way: items finished or failed (by any rank, in this run
    or an interrupted one), claimed by another rank, or not worth computing any more (the
    other curve of the same test point failed; the release after a failed sag).
    """
    names = {it.name: it for it in items}
    for item in list(pending):
        if parts.done(item) or parts.failure(item) is not None:
            pending.remove(item)
            continue
        if item.point >= 0:
            sibling = [it for it in items if it.point == item.point and it.kind != item.kind
                       and it.replacement == item.replacement]
            if any(parts.failure(it) is not None for it in sibling):
                pending.remove(item)
                continue
        before = names.get(AFTER.get(item.kind, ""))
        if before is not None:
            if parts.failure(before) is not None:
                log.info("%s not run: %s failed", item.name, before.name)
                pending.remove(item)
                continue
            if not parts.done(before):
                continue
        if not parts.claim(item):
            pending.remove(item)
            continue
        pending.remove(item)
        return item
    return None


def previous_results(out_path: Path, keys: dict[str, str], problem: Problem
                     ) -> dict[str, dict]:
    """The experiments of an existing ``out_path`` whose stored key equals ``keys``':
    ``{experiment: {"arrays": {...}, "seconds": compute seconds}}``, the arrays as
    :func:`experiment_arrays` gives them (rank 0). Nothing when the file is absent,
    unreadable, older than per-experiment keys, or on other test points (a reference whose
    points failed holds other points than the scene's: it is recomputed)."""
    old = _previous_reference(out_path)
    if old is None:
        return {}
    stored = json.loads(old.meta.get("experiment_keys", "{}"))
    seconds = json.loads(old.meta.get("timings_s", "{}"))
    if not np.array_equal(old.problem.test_points, problem.test_points):
        return {}
    return {e: {"arrays": experiment_arrays(old, e), "seconds": float(seconds.get(e, 0.0))}
            for e in old.experiments if stored.get(e) == keys[e]}


#: the held-out body tests whose FE failure leaves their experiments out of the reference (the
#: ``fe_failures`` key of each -> its experiments)
HELD_OUT_TESTS = {"gravity": GRAVITY_EXPERIMENTS, "second_support": ("second_support",)}


def previous_failures(out_path: Path, keys: dict[str, str]) -> dict[str, dict]:
    """The held-out body test failures an existing ``out_path`` records (``fe_failures.gravity``,
    ``.second_support``: :data:`HELD_OUT_TESTS`) that were met with the current keys of all the
    test's experiments (they would fail again)."""
    old = _previous_reference(out_path)
    if old is None:
        return {}
    failed = json.loads(old.meta.get("failed_experiment_keys", "{}"))
    recorded = old.fe_failures.to_json()
    return {test: recorded[test] for test, kinds in HELD_OUT_TESTS.items()
            if recorded[test] is not None and all(failed.get(e) == keys[e] for e in kinds)}


def _previous_reference(out_path: Path) -> Reference | None:
    """``out_path`` read back, or None when absent or unreadable (logged)."""
    if not out_path.is_file():
        return None
    try:
        old = read_reference(out_path)
        json.loads(old.meta.get("experiment_keys", "{}"))
        json.loads(old.meta.get("timings_s", "{}"))
        json.loads(old.meta.get("failed_experiment_keys", "{}"))
    except (ForcecalError, TypeError, ValueError) as exc:
        log.info("not reusing %s: %s", out_path, exc)
        return None
    return old


def experiment_arrays(reference: Reference, experiment: str) -> dict[str, np.ndarray]:
    """The results of one experiment of ``reference``, named like its work items' parts
    (curves stacked over the test points)."""
    g = reference.gravity
    if experiment == "gravity_static":
        return {"displacement": g.static_displacement}
    if experiment == "gravity_dynamic":
        return {"time": g.time, "displacement": g.displacement}
    if experiment == "body":
        return body.arrays_of(reference.body)
    if experiment == "second_support":
        runs = reference.second_support.runs
        return {"static_displacement": runs.static_displacement, "time": runs.time,
                "displacement": runs.displacement}
    if experiment == "floor":
        return floor.arrays_of(reference.floor)
    return {"force": getattr(reference, experiment).force}


def _assemble(scene: Scene, points: _Points, items: list[WorkItem], parts: _Parts,
              previous: dict[str, dict], computed: list[str], keys: dict[str, str],
              n_ranks: int, mesh_seconds: float, total_seconds: float, failures: FEFailures,
              preflight: dict) -> Reference:
    """Build the :class:`Reference` from the checkpoint parts and the reused experiments
    of the previous file (rank 0): the curves of the current test points (each slot's last
    vertex, dropped slots left out), the gravity runs unless the gravity test failed."""
    data, seconds = {}, {k: 0.0 for k in KINDS}
    for item in items:
        failed = parts.failure(item)
        if failed is not None:
            seconds[item.kind] += float(failed.get("seconds", 0.0))
            continue
        arrays = parts.load(item)
        if arrays is None:
            continue  # never run: the other curve of its point, or the sag before it, failed
        data[item.name] = arrays
        seconds[item.kind] += float(arrays["seconds"])
    results = {e: p["arrays"] for e, p in previous.items()}
    seconds.update({e: p["seconds"] for e, p in previous.items()})
    slots = [k for k in range(len(points.original.test_points)) if k not in points.dropped]
    for kind in ("indentation", "relaxation"):
        if kind not in scene.experiments:
            continue
        reused = results.get(kind, {}).get("force")
        rows = []
        for k in slots:  # a reused curve for a scene point, a part for the others
            name = WorkItem(kind, k, 0.0, points.replacements[k]).name
            if reused is not None and not points.replacements[k]:
                rows.append(reused[k])
            elif name in data:
                rows.append(data[name]["force"])
            else:
                raise DataFileError(f"checkpoint of {name} is missing from {parts.folder}")
        results[kind] = {"force": np.stack(rows)}
    recorded = failures.to_json()
    for test, kinds in HELD_OUT_TESTS.items():
        for kind in kinds:
            if recorded[test] is not None:
                results.pop(kind, None)  # the test failed: none of its runs is kept
            elif kind in data:
                results[kind] = {k: v for k, v in data[kind].items() if k != "seconds"}
    for kind in ("body", "floor"):
        if kind in data:
            results[kind] = {k: v for k, v in data[kind].items() if k != "seconds"}
    body_result = (body.result_of(results["body"],
                                  float(np.linalg.norm(scene.gravity.acceleration)))
                   if "body" in results else None)
    present = [e for e in EXPERIMENTS if e in results]
    problem = points.current
    normals = problem.normals

    def normal(force: np.ndarray) -> np.ndarray:
        return np.einsum("psk,pk->ps", force, normals)

    f_ind = results["indentation"]["force"]
    relaxation = None
    if "relaxation" in results:
        f_rel = results["relaxation"]["force"]
        times, depths = relaxation_schedule(scene.relaxation)
        relaxation = RelaxationCurves(times, depths, f_rel, normal(f_rel))
    gravity = None
    if "gravity_static" in results or "gravity_dynamic" in results:
        static = results.get("gravity_static", {}).get("displacement")
        dyn = results.get("gravity_dynamic", {})
        gravity = GravityResult(static_displacement=static, time=dyn.get("time"),
                                displacement=dyn.get("displacement"),
                                settings=dataclasses.replace(scene.gravity,
                                                             tracked_node=problem.tracked_node))
    second = None
    if "second_support" in results:
        support = second_support(scene, problem)
        runs = results["second_support"]
        second = SecondSupportResult(
            scene.second_support, support.fixed,
            GravityResult(runs["static_displacement"], runs["time"], runs["displacement"],
                          dataclasses.replace(scene.gravity,
                                              tracked_node=support.tracked_node)))
    floor_result = (floor.result_of(results["floor"], dataclasses.replace(
        scene.gravity, tracked_node=problem.tracked_node)) if "floor" in results else None)
    counted = {k: sum(1 for name in computed if name.split("-")[0] == k) for k in KINDS}
    failed_keys = {e: keys[e] for test, kinds in HELD_OUT_TESTS.items() if recorded[test] is not None
                   for e in kinds if e in scene.experiments}
    meta = {
        "dolfinx_version": dolfinx.__version__,
        "scene_fingerprint": scene.fingerprint(*REFERENCE_SECTIONS),
        "mesh_fingerprint": problem.mesh.fingerprint(),
        # item times are compute seconds summed over ranks (and over an interrupted
        # earlier run for resumed items, or the run that computed a reused experiment);
        # total is this call's wall time
        "timings_s": json.dumps({"mesh": mesh_seconds, **seconds, "total": total_seconds}),
        "n_ranks": n_ranks,
        "experiment_keys": json.dumps({e: keys[e] for e in present}),
        "reused": json.dumps([e for e in present if e in previous]),
        "items_computed": json.dumps({k: n for k, n in counted.items() if n}),
        "fe_failures": json.dumps(failures.to_json()),
        "failed_experiment_keys": json.dumps(failed_keys),
        "mesh_preflight": json.dumps(preflight),
    }
    return Reference(
        problem=problem, material=scene.material,
        indentation=IndentationCurves(indentation_depths(scene.indentation), f_ind,
                                      normal(f_ind), indenter=scene.indentation.indenter,
                                      radius=scene.indentation.radius),
        relaxation=relaxation, gravity=gravity, meta=meta, fe=scene.fe, body=body_result,
        second_support=second, floor=floor_result)
