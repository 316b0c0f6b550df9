"""The verdict: did the calibration give a model that passes the scene's checks?

Computed in the report stage from what the report measured (:func:`measurements`), against
the scene's ``[verdict]`` goals (:func:`judge`, a pure function), into ``report.json``'s
``verdict`` block::

    {"passed": bool, "require_no_worse_than_baseline": bool,
     "checks": {<check>: {"calibrated", "baseline", "goal", "status", "passed", "reason"}}}

Checks (:data:`CHECKS`), each the calibrated model's value against its goal and, with
``verdict.no_worse_than_baseline``, against the closed-form baseline's value:

* ``held_out_indentation``, ``held_out_relaxation``: mean relative RMS force error at the
  held-out points (``errors.<experiment>_held_out``); at most the goal;
* ``static_sag``: ``errors.gravity_static``; at most;
* ``release_period``, ``release_first_peak``: ``|period_error|``, ``|first_peak_error|`` of
  ``gravity.dynamic_metrics``; at most;
* ``release_rms``: ``errors.gravity_dynamic``; at most;
* ``carries_its_weight``: the fraction of the scene's gravity the model's static sag carried
  (1 when it completed, else the load its Newton solve reached: the smallest load factor of
  the model's ``gravity_static`` records in ``failures``, the gravity stage's or a
  calibration's that fitted a load its model could not carry); at least; failed also when
  the calibration failed its whole-body data (``body.status == "failed"``: no equilibrium
  under a body load it was fitted to, or no modes);
* ``second_support_static_sag``, ``second_support_release_rms``: the second held-out body
  test's ``second_support.errors.static_sag`` and ``.release_rms`` (the gravity test with the
  ``[second_support]`` clamp); at most; ``not_run`` when the scene's experiments do not
  include ``second_support`` (or its FE test failed).

A check's status is ``failed`` when the calibrated model failed its experiment (a record
in ``failures``: at a held-out point for the curve checks; the static sag or the release for
the gravity ones), when its value misses the goal, or when (required) it is worse than the
baseline's; ``not_run`` (null values) when nothing was measured (the experiment is not in the
scene, the scene has no held-out points, the FE gravity test failed); ``passed`` otherwise.
A baseline that failed the experiment has a null value and no comparison is made. The
verdict passes only when every check passed: a check that was not run has not passed. The
checks of an opt-in experiment (:data:`OPT_IN`: the second support) that the scene does not
ask for are left out of the verdict (a scene is judged on the tests it asks for; its
``not_run`` says why they are absent).

A held-out check whose points drive the calibrated model's connectors beyond the strains
the calibration points reached (``report.json``'s ``strain_ranges``) says so in its reason,
whatever its status: there the fitted spring law (``K(eps) = K0 + a eps + b eps^2``) is
extrapolated, which the goal alone does not tell.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from forcecal.scene import SECOND_SUPPORT_PARTS, VerdictSection

AT_MOST, AT_LEAST = "at most", "at least"


@dataclass(frozen=True)
class CheckSpec:
    """One check: the experiment whose failures fail it, and how a value meets its goal."""
    experiment: str
    direction: str = AT_MOST
    unit: str = "%"


CHECKS = {
    "held_out_indentation": CheckSpec("indentation"),
    "held_out_relaxation": CheckSpec("relaxation"),
    "static_sag": CheckSpec("gravity_static"),
    "release_period": CheckSpec("gravity_dynamic"),
    "release_first_peak": CheckSpec("gravity_dynamic"),
    "release_rms": CheckSpec("gravity_dynamic"),
    "carries_its_weight": CheckSpec("gravity_static", AT_LEAST, "g"),
    "second_support_static_sag": CheckSpec("second_support_static"),
    "second_support_release_rms": CheckSpec("second_support_dynamic"),
}
STATUSES = ("passed", "failed", "not_run")
#: the checks of the opt-in second support (not in the default experiments): judged only when
#: the scene asks for it
OPT_IN = frozenset(name for name, spec in CHECKS.items()
                   if spec.experiment in SECOND_SUPPORT_PARTS)
#: the start of ``not_run``'s reason for an experiment the scene's list does not hold
NOT_ASKED = "not in the scene's experiments"


@dataclass(frozen=True)
class Measured:
    """What the report measured for one check.

    Attributes:
        calibrated, baseline: the models' values (None: not measured, or the model failed).
        failure: why the calibrated model failed the check's experiment (None if it did not).
        not_run: why nothing was measured (None if something was).
        note: what the reason says whatever the status (held-out points judged on an
            extrapolated spring law), or None.
    """
    calibrated: float | None
    baseline: float | None
    failure: str | None = None
    not_run: str | None = None
    note: str | None = None


def judge_check(m: Measured, goal: float, spec: CheckSpec, no_worse: bool
                ) -> dict[str, Any]:
    """One check's entry of the verdict (module docstring)."""
    def entry(status: str, reason: str | None) -> dict[str, Any]:
        if status != "not_run" and m.note is not None:
            reason = m.note if reason is None else f"{reason}; {m.note}"
        return {"calibrated": m.calibrated, "baseline": m.baseline, "goal": goal,
                "status": status, "passed": None if status == "not_run" else status == "passed",
                "reason": reason}

    def worse(a: float, b: float) -> bool:
        return a > b if spec.direction == AT_MOST else a < b

    if m.failure is not None:
        return entry("failed", m.failure)
    if m.calibrated is None:
        return entry("not_run", m.not_run or "not measured")
    if worse(m.calibrated, goal):
        return entry("failed", f"{_value(m.calibrated, spec)} is not {spec.direction} the goal "
                     f"{_value(goal, spec)}")
    if no_worse and m.baseline is not None and worse(m.calibrated, m.baseline):
        return entry("failed", f"{_value(m.calibrated, spec)} is worse than the closed-form "
                     f"baseline's {_value(m.baseline, spec)}")
    return entry("passed", None)


def judge(measured: dict[str, Measured], goals: VerdictSection) -> dict[str, Any]:
    """The ``verdict`` block of every check of :data:`CHECKS` in ``measured`` (those of an
    opt-in experiment the scene does not ask for are absent from it)."""
    checks = {name: judge_check(measured[name], getattr(goals, name), spec,
                                goals.no_worse_than_baseline)
              for name, spec in CHECKS.items() if name in measured}
    return {"passed": all(c["status"] == "passed" for c in checks.values()),
            "require_no_worse_than_baseline": goals.no_worse_than_baseline,
            "checks": checks}


def _value(value: float | None, spec: CheckSpec) -> str:
    if value is None:
        return "-"
    return f"{100 * value:.2f} %" if spec.unit == "%" else f"{value:.3g} {spec.unit}"


# ---------------------------------------------------------------------------- from a report

def measurements(report: dict[str, Any]) -> dict[str, Measured]:
    """Every check's :class:`Measured` from a report's keys (``errors``, ``baseline_errors``,
    ``gravity.dynamic_metrics``, ``second_support``, ``failures``, ``not_run``,
    ``test_points`` and, when the FE stage records one, ``fe_failures.gravity`` and
    ``.second_support``)."""
    failures = report.get("failures") or []
    errors, baseline = report["errors"], report["baseline_errors"]
    metrics = (report.get("gravity") or {}).get("dynamic_metrics") or {}
    out = {}
    second = report.get("second_support") or {}
    for name, spec in CHECKS.items():
        why_not = _not_run(report, spec.experiment)
        role = None
        if name.startswith("second_support_"):
            # its release starts from its static sag, as the gravity test's
            experiments = (SECOND_SUPPORT_PARTS if spec.experiment == SECOND_SUPPORT_PARTS[1]
                           else SECOND_SUPPORT_PARTS[:1])
            key = "static_sag" if name.endswith("static_sag") else "release_rms"
            values = [(second.get(group) or {}).get(key)
                      for group in ("errors", "baseline_errors")]
        elif name.startswith("held_out_"):
            role, experiments = "held_out", (spec.experiment,)
            if why_not is None and not report["test_points"]["held_out"]:
                why_not = "the scene has no held-out points"
            key = f"{spec.experiment}_held_out"
            values = [errors[key], baseline[key]]
        else:
            if spec.experiment == "gravity_dynamic" and why_not is None:
                why_not = _not_run(report, "gravity_static")  # it swings about the sag
            # a release needs the static sag it starts its step from
            experiments = ("gravity_static",) + (("gravity_dynamic",) if spec.experiment
                                                 == "gravity_dynamic" else ())
            if name == "carries_its_weight":
                values = [None if why_not else _carried(failures, m)
                          for m in ("calibrated", "baseline")]
            elif name in ("static_sag", "release_rms"):
                key = "gravity_static" if name == "static_sag" else "gravity_dynamic"
                values = [errors[key], baseline[key]]
            else:
                metric = "period_error" if name == "release_period" else "first_peak_error"
                values = [_magnitude((metrics.get(m) or {}).get(metric))
                          for m in ("calibrated", "baseline")]
        failure = _failed(failures, "calibrated", experiments, role)
        if name == "carries_its_weight" and failure is None:
            failure = _failed_body_fit(report)
        if name in ("release_period", "release_first_peak") and values[0] is None and not (
                failure or why_not) and metrics.get("calibrated"):
            failure = f"no {name.split('_', 1)[1].replace('_', ' ')} in the calibrated release"
        if name != "carries_its_weight" and _failed(failures, "baseline", experiments, role):
            values[1] = None  # a baseline that failed is no comparison
        if why_not is not None:
            values = [None, None]
        if name in OPT_IN and (why_not or "").startswith(NOT_ASKED):
            continue  # an opt-in test the scene does not ask for: not judged
        note = _extrapolated(report, spec.experiment) if role == "held_out" else None
        out[name] = Measured(values[0], values[1], failure, why_not, note)
    return out


def _failed_body_fit(report: dict[str, Any]) -> str | None:
    """Why the calibration failed its whole-body data (``body.status == "failed"``: the
    calibrated model has no equilibrium under a body load it was fitted to, or no modes),
    None if it did not."""
    body = report.get("body") or {}
    if body.get("status") != "failed":
        return None
    return f"failed calibration: {body.get('failure')}"


def _extrapolated(report: dict[str, Any], experiment: str) -> str | None:
    """Which held-out points drive the calibrated model's connectors beyond the strains its
    calibration points reached in ``experiment`` (``strain_ranges``), None if none do (or
    the report has no strain ranges)."""
    ranges = ((report.get("strain_ranges") or {}).get(experiment) or {}).get("calibrated")
    if not ranges or ranges["calibration"] is None:
        return None
    lo, hi = ranges["calibration"]
    outside = {int(p): r for p, r in ranges["held_out"].items()
               if r is not None and (r[0] < lo or r[1] > hi)}
    if not outside:
        return None
    reached = [min(r[0] for r in outside.values()), max(r[1] for r in outside.values())]
    return (f"held-out point(s) {sorted(outside)} drive connectors to strains "
            f"[{reached[0]:.3g}, {reached[1]:.3g}], beyond the range the calibration points "
            f"reached [{lo:.3g}, {hi:.3g}]: the fitted spring law is extrapolated there")


def _not_run(report: dict[str, Any], experiment: str) -> str | None:
    """Why ``experiment`` (or the second support's part of it) was not measured (None if
    it was)."""
    if experiment in SECOND_SUPPORT_PARTS:
        experiment = "second_support"
    if experiment in (report.get("not_run") or {}):
        return report["not_run"][experiment]
    fe = report.get("fe_failures") or {}
    for test, failed in (("gravity", fe.get("gravity")),
                         ("second_support", fe.get("second_support"))):
        if experiment.startswith(test) and failed:
            return f"the FE {test.replace('_', '-')} test failed: {failed.get('reason')}"
    return None


def _failed(failures: list[dict], model: str, experiments: tuple[str, ...],
            role: str | None = None) -> str | None:
    """Why ``model`` failed one of ``experiments`` (at points of ``role``), None if it did not."""
    mine = [f for f in failures if f["model"] == model and f["experiment"] in experiments
            and (role is None or f["role"] == role)]
    if not mine:
        return None
    first = mine[0]
    if first["point"] is None:  # a body test: its static sag first, least far first
        first = min((f for f in mine if f["point"] is None), key=lambda f: (
            not f["experiment"].endswith("_static"), next(iter(f["reached"].values()))))
        (key, reached), = first["reached"].items()
        return f"{first['experiment']} stopped at {key} = {reached:.4g}: {first['reason']}"
    points = sorted({f["point"] for f in mine})
    (key, reached), = first["reached"].items()
    kind = "" if role is None else role.replace("_", "-") + " "
    return (f"did not complete {first['experiment']} at {len(points)} {kind}point(s) "
            f"{points} (point {first['point']} stopped at {key} = {reached:.4g}: "
            f"{first['reason']})")


def _carried(failures: list[dict], model: str) -> float:
    """The fraction of the gravity ``model`` carried: the smallest load factor of its
    ``gravity_static`` failures (the gravity stage's static sag, or a calibration that records
    a fitted body load its model had no equilibrium for), 1 when it has none."""
    return min((float(f["reached"]["load_factor"]) for f in failures
                if f["model"] == model and f["experiment"] == "gravity_static"), default=1.0)


def _magnitude(value: float | None) -> float | None:
    return None if value is None else abs(float(value))


# ---------------------------------------------------------------------------- tables

def verdict_rows(verdict: dict[str, Any]) -> list[list[str]]:
    """(check, calibrated, baseline, goal, status) per check, values formatted."""
    rows = []
    for name, c in verdict["checks"].items():
        spec = CHECKS.get(name, CheckSpec(""))
        goal = f"{'<=' if spec.direction == AT_MOST else '>='} {_value(c['goal'], spec)}"
        status = c["status"].replace("_", " ")
        rows.append([name, _value(c["calibrated"], spec), _value(c["baseline"], spec), goal,
                     status])
    return rows


HEADER = ["check", "calibrated", "baseline", "goal", "status"]


def verdict_text(verdict: dict[str, Any]) -> str:
    """The table the command line ends with, the reasons of the checks that did not pass and
    the verdict line."""
    rows = [HEADER] + verdict_rows(verdict)
    widths = [max(len(r[i]) for r in rows) for i in range(len(HEADER))]
    lines = ["  ".join(cell.ljust(w) if i == 0 else cell.rjust(w)
                       for i, (cell, w) in enumerate(zip(r, widths))) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    for name, c in verdict["checks"].items():
        if c["status"] != "passed":
            lines.append(f"  {name}: {c['status'].replace('_', ' ')}: {c['reason']}")
    lines.append(verdict_line(verdict))
    return "\n".join(lines)


def verdict_line(verdict: dict[str, Any]) -> str:
    """``verdict: PASSED`` or ``verdict: FAILED (...)``."""
    checks = verdict["checks"]
    if verdict["passed"]:
        return f"verdict: PASSED ({len(checks)} checks)"
    failed = [n for n, c in checks.items() if c["status"] == "failed"]
    not_run = [n for n, c in checks.items() if c["status"] == "not_run"]
    parts = ([f"failed: {', '.join(failed)}"] if failed else []) + (
        [f"not run: {', '.join(not_run)}"] if not_run else [])
    return f"verdict: FAILED ({'; '.join(parts)})"


def verdict_markdown(verdict: dict[str, Any]) -> str:
    """The Markdown verdict table of one report (docs/verdict.md)."""
    rows = verdict_rows(verdict)
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(f"`{r[0]}`" if i == 0 else (f"**{c}**" if i == 4 else c)
                                for i, c in enumerate(r)) + " |" for r in rows]
    return "\n".join(lines + ["", verdict_line(verdict)])
