"""FE test points that fail, what is done about them, and what the failures have in common.

A test point whose FE indentation or relaxation does not converge (even with step cutting)
does not end the reference: with a rule (``test_points.calibration`` / ``held_out`` =
``"auto"`` or ``"cover"``) it is **replaced** by the next candidate of that rule
(:func:`forcecal.problem.replacement_point`), in the same slot of the test points; with an
explicit list it is **dropped**. A failed FE gravity test leaves both gravity experiments out
of the reference: the gravity checks are then not run; a failed FE test of the second
support (experiment ``second_support``) leaves it out likewise. Only when more than
:data:`MAX_FAILED_FRACTION` of the test points fail is the FE set-up itself wrong for the
scene: the reference stops with :func:`too_many_failures`, which says what the failures share
(:func:`common_features`).

:class:`FEFailures` is what ``reference.h5`` (root attribute ``fe_failures``, JSON) and
``report.json`` (key ``fe_failures``) hold::

    {"replaced": [{"point", "by", "experiment", "reason", "role", "slot", "reached"}],
     "dropped":  [{"point", "experiment", "reason", "role", "slot", "reached"}],
     "gravity":  null | {"experiment", "reason", "reached"},
     "second_support": null | {"experiment", "reason", "reached"}}

``point`` and ``by`` are vertex ids, ``slot`` the index into the scene's test points
(calibration points first), ``reached`` how far the experiment got (``{"depth_m": ..}``,
``{"time_s": ..}`` or ``{"load_factor": ..}``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from forcecal.errors import ConvergenceError, DataFileError
from forcecal.indenter import face_gaps, radii_within_reach
from forcecal.mesh import TetMesh
from forcecal.point_selection import free_surface_vertices
from forcecal.preflight import POOR_QUALITY
from forcecal.problem import Problem

#: the reference stops when more than this fraction of the test points fail
MAX_FAILED_FRACTION = 0.25


@dataclass(frozen=True)
class PointFailure:
    """One FE indentation or relaxation that failed.

    Attributes:
        slot: index into the test points (calibration points first).
        vertex: the test vertex that failed there.
        experiment: ``"indentation"`` or ``"relaxation"``.
        reason: the solver's message.
        reached: how far it got (``{"depth_m": ..}`` or ``{"time_s": ..}``; empty if unknown).
    """
    slot: int
    vertex: int
    experiment: str
    reason: str
    reached: dict = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class FEFailures:
    """What failed in an FE reference and what was done (module docstring)."""
    replaced: tuple[dict, ...] = ()
    dropped: tuple[dict, ...] = ()
    gravity: dict | None = None
    second_support: dict | None = None

    def to_json(self) -> dict[str, Any]:
        return {"replaced": list(self.replaced), "dropped": list(self.dropped),
                "gravity": self.gravity, "second_support": self.second_support}

    @property
    def any(self) -> bool:
        return bool(self.replaced or self.dropped or self.gravity or self.second_support)

    @classmethod
    def from_json(cls, text: str | None, origin: str) -> FEFailures:
        """Parse the ``fe_failures`` attribute (None or absent: nothing failed).

        Raises:
            DataFileError: not the documented structure.
        """
        if text is None:
            return cls()
        try:
            data = json.loads(text)
            replaced = tuple(data["replaced"])
            dropped = tuple(data["dropped"])
            gravity = data["gravity"]
            second = data.get("second_support")  # absent in files written before the test
            ok = (all(isinstance(r.get("point"), int) and isinstance(r.get("by"), int)
                      for r in replaced)
                  and all(isinstance(d.get("point"), int) for d in dropped)
                  and all(f is None or isinstance(f.get("experiment"), str)
                          for f in (gravity, second)))
        except (TypeError, ValueError, KeyError, AttributeError):
            ok = False
        if not ok:
            raise DataFileError(f"{origin}: attribute fe_failures = {text!r} is not "
                                '{"replaced": [...], "dropped": [...], "gravity": ..., '
                                '"second_support": ...}')
        return cls(replaced, dropped, gravity, second)


def role_of(problem: Problem, slot: int) -> str:
    """``"calibration"`` or ``"held_out"``: the role of test point ``slot``."""
    return "calibration" if slot < len(problem.calibration) else "held_out"


def with_point(problem: Problem, slot: int, vertex: int | None) -> Problem:
    """``problem`` with test point ``slot`` replaced by ``vertex`` (None: removed)."""
    n_cal = len(problem.calibration)
    which, index = ("calibration", slot) if slot < n_cal else ("held_out", slot - n_cal)
    points = getattr(problem, which)
    points = (np.delete(points, index) if vertex is None
              else np.concatenate([points[:index], [vertex], points[index + 1:]]))
    return dataclasses.replace(problem, **{which: points.astype(np.int64)})


def apply_fe_failures(problem: Problem, failures: FEFailures) -> Problem:
    """The test points of the reference ``failures`` describe, from the scene's ``problem``:
    each replacement and drop applied in the recorded order.

    Raises:
        DataFileError: a recorded point is not a test point at that stage.
    """
    for entry in failures.replaced + failures.dropped:
        nodes = problem.test_points
        hit = np.nonzero(nodes == entry["point"])[0]
        if not len(hit):
            raise DataFileError(f"fe_failures names vertex {entry['point']}, which is not a "
                                "test point of the scene")
        problem = with_point(problem, int(hit[0]), entry.get("by"))
    return problem


def replay(problem: Problem, failures: list[PointFailure],
           replacement: Callable[[Problem, int, set[int]], int | None] | None
           ) -> tuple[Problem, FEFailures, list[PointFailure]]:
    """Apply the point failures to the scene's ``problem``, deterministically.

    Passes over the slots in order; in each pass a slot whose current vertex has a failure
    is replaced (``replacement(problem, slot, tried)``: the next vertex of the selection
    rule, avoiding the vertices ``tried``, None if there is none) or, when ``replacement``
    is None (an explicit list) or finds nothing, dropped. A replacement's own failure is
    met in the next pass. The result depends only on the set of failures, so a resumed run
    (or another rank) decides the same.

    Returns:
        (the problem with its current test points, the replaced/dropped records, the
        failures that were applied in the order they were applied).
    """
    by_key = {(f.slot, f.vertex): f for f in failures}
    current = problem
    slots = list(range(len(problem.test_points)))  # slot -> index in current (None: dropped)
    vertices: list[int | None] = [int(v) for v in problem.test_points]
    tried: set[int] = set()
    replaced, dropped, applied = [], [], []
    changed = True
    while changed:
        changed = False
        for slot in range(len(vertices)):
            v = vertices[slot]
            failure = by_key.get((slot, v)) if v is not None else None
            if failure is None:
                continue
            changed = True
            applied.append(failure)
            tried.add(v)
            record = {"point": v, "experiment": failure.experiment, "reason": failure.reason,
                      "role": role_of(problem, slot), "slot": slot, "reached": failure.reached}
            index = slots[slot]
            new = None if replacement is None else replacement(current, index, tried)
            if new is None:
                current = with_point(current, index, None)
                slots = [s if s is None or s < index else (None if s == index else s - 1)
                         for s in slots]
                vertices[slot] = None
                dropped.append(record)
            else:
                current = with_point(current, index, new)
                vertices[slot] = int(new)
                replaced.append({**record, "by": int(new)})
    return current, FEFailures(tuple(replaced), tuple(dropped)), applied


def common_features(mesh: TetMesh, fixed: np.ndarray, test_points: np.ndarray,
                    failed: list[PointFailure], quality: np.ndarray,
                    footprints: dict[int, np.ndarray] | None = None) -> list[str]:
    """What the failed test points share, as short phrases: the experiments always, the rest
    when it stands out.

    Compared with the test points that did not fail: the experiment; how far it got; the
    distance to the clamp (in the quarter of the free surface nearest to it); the spread
    (one region: all within a quarter of the body's size); the worst tet touching the point
    (or its punch footprint, ``footprints``: vertex -> footprint vertices) by
    :func:`forcecal.preflight.tet_quality`.
    A feature is named when it holds for at least 3/4 of the failures and is at least
    twice as frequent among them as among the others.
    """
    said = []
    kinds = {}
    for f in failed:
        kinds[f.experiment] = kinds.get(f.experiment, 0) + 1
    said.append(", ".join(f"{n} in {k}" for k, n in sorted(kinds.items())))
    reached = [f.reached for f in failed if f.reached]
    for unit, name, scale in (("depth_m", "depth", 1e3), ("time_s", "time", 1.0)):
        values = [r[unit] for r in reached if unit in r]
        if values:
            said.append(f"{name} reached {min(values) * scale:.3g}-{max(values) * scale:.3g} "
                        f"{'mm' if unit == 'depth_m' else 's'}")
    bad = np.array(sorted({f.vertex for f in failed}), dtype=np.int64)
    good = np.setdiff1d(np.asarray(test_points, dtype=np.int64), bad)
    x = mesh.vertices

    def share(mask_bad: np.ndarray, mask_good: np.ndarray) -> bool:
        fb = float(np.mean(mask_bad)) if len(mask_bad) else 0.0
        fg = float(np.mean(mask_good)) if len(mask_good) else 0.0
        return fb >= 0.75 and fb >= 2.0 * fg

    def to_clamp(v: np.ndarray) -> np.ndarray:
        return np.min(np.linalg.norm(x[v][:, None] - x[fixed][None], axis=2), axis=1)

    # near: in the quarter of the free surface nearest the clamp
    near = float(np.quantile(to_clamp(free_surface_vertices(mesh, fixed)), 0.25))
    near_bad, near_good = to_clamp(bad) <= near, to_clamp(good) <= near
    if share(near_bad, near_good):
        said.append(f"{int(near_bad.sum())} of {len(bad)} near the clamp (within "
                    f"{near * 1e3:.3g} mm, as the nearest quarter of the free surface; of the "
                    f"others: {int(near_good.sum())} of {len(good)})")
    size = float(np.linalg.norm(np.ptp(x, axis=0)))
    if len(bad) >= 2:
        centre = x[bad].mean(axis=0)
        radius = float(np.linalg.norm(x[bad] - centre, axis=1).max())
        if radius <= 0.25 * size:
            nearest = int(bad[np.argmin(np.linalg.norm(x[bad] - centre, axis=1))])
            said.append(f"all in one region: within {radius * 1e3:.3g} mm of vertex {nearest} "
                        f"(body size {size * 1e3:.3g} mm)")
    worst_bad = _worst_quality_near(mesh, bad, quality, footprints)
    worst_good = _worst_quality_near(mesh, good, quality, footprints)
    poor = 0.1
    if share(worst_bad < poor, worst_good < poor):
        said.append(f"poorly shaped tets: the worst tet at {int((worst_bad < poor).sum())} of "
                    f"{len(bad)} has a quality below {poor:g} (median "
                    f"{np.median(worst_bad):.2g}; at the others "
                    f"{np.median(worst_good) if len(good) else math.nan:.2g})")
    return said


def _worst_quality_near(mesh: TetMesh, vertices: np.ndarray, quality: np.ndarray,
                        footprints: dict[int, np.ndarray] | None) -> np.ndarray:
    """(len(vertices),) the smallest quality of the tets touching each vertex (or its
    footprint)."""
    out = np.empty(len(vertices))
    for k, v in enumerate(vertices):
        nodes = footprints.get(int(v), [v]) if footprints else [v]
        touching = np.isin(mesh.tets, nodes).any(axis=1)
        out[k] = float(quality[touching].min())
    return out


#: what :func:`with_preflight` adds to a failure's reason (once)
EXPECTED = "expected by the mesh preflight"


def with_preflight(record: dict | None, preflight: dict) -> dict | None:
    """A failed FE gravity test's ``fe_failures`` record (``{"experiment", "reason",
    "reached"}``, or None) with what the mesh preflight (:func:`forcecal.preflight.
    mesh_preflight`) said of the scene's support when it said the support does not hold the
    body under its weight: the failure was expected, and the reason says why (a reason that
    says it already is kept)."""
    support = preflight.get("support") or {}
    if (record is None or support.get("holds", True) or support.get("linear_sag_m") is None
            or EXPECTED in record["reason"]):
        return record
    sag, size = support["linear_sag_m"], support["body_size_m"]
    return {**record, "reason": (
        f"{record['reason']}; {EXPECTED}: the support does not hold the body under its weight "
        f"(linear sag under full gravity {sag * 1e3:.3g} mm, {sag / size:.2g} x the body's size "
        f"{size * 1e3:.3g} mm)")}


def punch_reach(mesh: TetMesh, failed: dict[int, tuple[np.ndarray, float]],
                footprints: dict[int, np.ndarray], radius: float,
                which: str = "failed points") -> str | None:
    """What the punch footprints of failed test points (or others: ``which`` names them)
    hold beyond the punch's reach, as a short phrase for :func:`too_many_failures` (None
    unless it holds for at least 3/4 of the points), with a radius that keeps every point's
    footprint within reach and at least :data:`forcecal.indenter.MIN_FOOTPRINT` particles
    (:func:`forcecal.indenter.radii_within_reach`), if one radius does for all of them.

    A flat punch pushed ``depth`` [m] never touches a footprint node lying farther than that
    from the plane of its face (on a surface curved within the footprint): the footprint
    holds it as if glued to the face, and the FE runs of such points are the ones that
    diverge on the corpus torus (studies/punch_reach.py).

    Args:
        failed: failed test vertex -> (its indentation direction (3,), the depth [m] of the
            shallowest experiment that failed there).
        footprints: vertex -> its footprint's vertices at the scene's ``radius`` [m].
    """
    gaps = {v: float(face_gaps(mesh, v, n, footprints[v]).max()) for v, (n, _) in failed.items()}
    beyond = [v for v, gap in gaps.items() if gap > failed[v][1]]
    if len(beyond) < 0.75 * len(failed):
        return None
    depths = sorted({failed[v][1] for v in beyond})
    said = (f"the punch footprints of {len(beyond)} of the {len(failed)} {which} hold "
            f"particles beyond the punch's reach, up to {max(gaps[v] for v in beyond) * 1e3:.3g}"
            f" mm from its face against the {' / '.join(f'{d * 1e3:.3g}' for d in depths)} mm "
            f"depth (a flat punch never touches them, its footprint holds them as if glued)")
    ranges = {v: radii_within_reach(mesh, v, n, radius, depth)
              for v, (n, depth) in failed.items()}
    none = [v for v, r in ranges.items() if r is None]
    if none:
        return (f"{said}: no radius holding enough particles keeps vertex {none[0]}'s within "
                f"reach (test points where the surface is flat within the depth)")
    low, high = max(r[0] for r in ranges.values()), min(r[1] for r in ranges.values())
    if not low < high:
        return (f"{said}: no one radius keeps every one of them within reach with enough "
                f"particles (between {low:.4g} and {high:.4g} m at different points)")
    return f"{said}: indentation.radius = {_round_within(low, high)} m keeps them within reach"


def _round_within(low: float, high: float) -> str:
    """A radius [m] to write for the range ``low <= r < high``: of the decimals with the
    fewest digits in it (to 1 um at most), the largest, the closest to the scene's radius and
    the tool's contact size."""
    for digits in range(2, 7):
        r = (math.ceil(high * 10 ** digits) - 1) / 10 ** digits
        if r >= low:
            return f"{r:.{digits}f}".rstrip("0")
    return f"{low:.6f}"


#: a tet whose corners enclose less than this fraction of their volume at rest is called
#: crushed (or folded, below 0) in the diagnosis of a failed gravity test
CRUSHED_VOLUME_RATIO = 0.2


def crushed_tet(mesh: TetMesh, displacement: np.ndarray, fixed: np.ndarray,
                quality: np.ndarray) -> str | None:
    """What the most compressed tet of a deformed state says about a failed gravity test, as a
    short phrase (None when no tet is crushed): its index, the volume its corners enclose
    relative to rest (:data:`CRUSHED_VOLUME_RATIO`; negative: folded), and whether it touches
    the clamp (a bonded clamp's rim concentrates the strain) or is poorly shaped
    (:data:`forcecal.preflight.POOR_QUALITY`: a sliver the mesh should not have).

    The corners' volume is the linear element's: for a quadratic element a measure of where
    the mesh is crushed, not its Jacobian at the quadrature points.

    Args:
        displacement: (N, 3) displacement of the mesh's vertices [m].
        fixed: the clamped vertices.
        quality: (T,) :func:`forcecal.preflight.tet_quality` of ``mesh``.
    """
    x = mesh.vertices + displacement
    t = mesh.tets
    a, b, c = x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]], x[t[:, 3]] - x[t[:, 0]]
    ratio = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0 / mesh.signed_volumes
    worst = int(np.argmin(ratio))
    if ratio[worst] >= CRUSHED_VOLUME_RATIO:
        return None
    where = []
    if np.isin(t[worst], fixed).any():
        where.append("it touches the clamp")
    if quality[worst] < POOR_QUALITY:
        where.append(f"it is poorly shaped (quality {quality[worst]:.2g}, below "
                     f"{POOR_QUALITY:g}: remesh)")
    return (f"tet {worst} is {'folded' if ratio[worst] < 0 else 'crushed'} (its corners "
            f"enclose {ratio[worst]:.2g} x their volume at rest)"
            + (f": {' and '.join(where)}" if where else ""))


def too_many_failures(n_points: int, failed: list[PointFailure], features: list[str]
                      ) -> ConvergenceError | None:
    """The error that ends the reference when more than :data:`MAX_FAILED_FRACTION` of the
    ``n_points`` test points failed (None otherwise); ``features``: :func:`common_features`."""
    n_failed = len({(f.slot, f.vertex) for f in failed})
    if n_failed <= MAX_FAILED_FRACTION * n_points:
        return None
    example = failed[0]
    return ConvergenceError(
        f"{n_failed} FE test point runs failed, more than a quarter of the {n_points} test "
        f"points: the FE set-up does not suit this scene; what the failures share: "
        f"{'; '.join(features) if features else 'nothing found'}; first failure: vertex "
        f"{example.vertex} ({example.experiment}): {example.reason}")
