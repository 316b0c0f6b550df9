"""The calibrated model must complete the scene's gravity test: it must be valid where it will
be used.

The gravity test (static sag, dynamic release from rest) is the honest measure of a
calibration: no fit sees its FE results. But a model whose fitted springs cannot carry the
organ's weight (a limit point of the static equilibrium below 1 g) or leave, in the release,
the strain range its explicit step was verified for fails the gravity checks. The fits
keep every spring stiff on the gravity release range of the FE sag (``Validity``), which is
necessary but not sufficient: springs that are each above their floor can still form a network
that buckles under its weight (measured: the paper's local tuning on the punch scene without
the volume term, Newton's last equilibrium at 0.914 g).

So after fitting, the calibrated model runs the particle side of the scene's gravity test
(:func:`gravity_outcome`, the very function the gravity stage runs, with the scene's load
steps, step rule and the FE's record times: one check, so the two cannot disagree) and only
its *completion* is used: its displacements are not compared with the FE's here, which only
the gravity stage does. If it does not complete, the fit is pulled back
towards the global fit, in the fit's own coordinates (the paper's ring offsets, the gradient
method's log/feasible coordinates), by the factors :data:`PULL_BACK` until one completes; the
global fit itself is the last candidate. The factor kept and every rejected candidate's failure
are returned (a warning in ``params.h5`` and ``report.json``), never silent.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from calibration.validation import MODEL_FAILURES, ValidationFailure, failure_from
from forcecal.errors import TimeStepError
from forcecal.problem import Problem
from forcecal.scene import GRAVITY_EXPERIMENTS, Scene
from particle.experiments import GravityTest, gravity_release, gravity_static_test
from particle.model import build_model
from particle.params import ConnectorParams

log = logging.getLogger(__name__)

#: fractions of the fit (over the global fit) tried after the fit itself fails the gravity test
PULL_BACK = (0.5, 0.25, 0.125, 0.0625, 0.0)


@dataclass(frozen=True)
class GravityCheck:
    """Outcome of :func:`carry_gravity`.

    Attributes:
        scale: fraction of the fit kept over the global fit (1: the fit as it is; 0: the
            global fit); None if no candidate completed (the fit is kept as it is).
        failures: (fraction, reason) of every candidate that did not complete, in order.
        seconds: wall time of the checks [s].
    """
    scale: float | None
    failures: tuple[tuple[float, str], ...]
    seconds: float

    def warning(self) -> str | None:
        """The line for ``params.h5``'s warnings, None when the fit completed as it is."""
        if not self.failures:
            return None
        first = self.failures[0][1]
        if self.scale is None:
            return (f"the calibrated model does not complete the scene's gravity test ({first}), "
                    "and neither does the global fit; the gravity stage records the failure "
                    "(the verdict's gravity checks fail)")
        kept = "the global fit" if self.scale == 0.0 else f"{self.scale:g} x the fit"
        return (f"the calibrated model does not complete the scene's gravity test ({first}); "
                f"pulled back towards the global fit to {kept} over the global fit, the "
                f"largest of {[1.0, *PULL_BACK]} that completes")


def gravity_outcome(scene: Scene, problem: Problem, params: ConnectorParams,
                    times: np.ndarray | None, strain_range: tuple[float, float], name: str,
                    parts: tuple[str, str] = GRAVITY_EXPERIMENTS
                    ) -> tuple[GravityTest | None, ValidationFailure | None]:
    """The particle side of ``scene``'s gravity test for one parameter set, as both the
    gravity stage and this check run it: the static sag under ``scene.gravity.acceleration``
    (:func:`particle.experiments.gravity_static_test`, ``scene.gravity.static_load_steps``)
    and, with ``times`` [s], the release sampled at them
    (:func:`particle.experiments.gravity_release`); ``strain_range`` is the calibration's,
    ``name`` the model's (``calibrated``, ``baseline``).

    Returns (the test, None) when it completes; a model that fails it is a result: (None,
    its failure) if the static sag fails, (the static sag alone, its failure) if the
    release does, the failure's experiment the first or the second of ``parts`` (the gravity
    test's; the second support's test, run with its clamp as ``problem.fixed``, names
    :data:`~forcecal.scene.SECOND_SUPPORT_PARTS`). An explicit ``particle.dt`` above the
    model's stability limit is the scene's setting, not the model's failure: refused
    (:class:`~forcecal.errors.TimeStepError`).
    """
    model = build_model(problem, scene.material.density, params,
                        volume_element=scene.particle.volume_element)
    gravity = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    settings = dict(particle=scene.particle, strain_range=strain_range, name=name)
    try:
        static = gravity_static_test(model, gravity, load_steps=scene.gravity.static_load_steps,
                                     **settings)
    except TimeStepError:  # the scene's particle.dt: a setting to change, refused
        raise
    except MODEL_FAILURES as exc:
        return None, failure_from(exc, name, parts[0])
    if times is None:
        return static, None
    try:
        return gravity_release(model, gravity, times, static, **settings), None
    except MODEL_FAILURES as exc:
        return static, failure_from(exc, name, parts[1])


def gravity_failure(scene: Scene, problem: Problem, params: ConnectorParams,
                    times: np.ndarray | None, strain_range: tuple[float, float]) -> str | None:
    """Why ``params`` do not complete ``scene``'s gravity test (None if they do): the
    :func:`gravity_outcome` of the calibrated model, the gravity stage's own run."""
    _, failure = gravity_outcome(scene, problem, params, times, strain_range, "calibrated")
    return None if failure is None else failure.reason


def carry_gravity(params_at: Callable[[float], ConnectorParams],
                  failure: Callable[[ConnectorParams], str | None]
                  ) -> tuple[ConnectorParams, GravityCheck]:
    """The largest fraction of the fit, of 1 then :data:`PULL_BACK`, whose parameters
    ``params_at(fraction)`` complete the gravity test (``failure`` returns None), and those
    parameters. If none does, the fit itself (``params_at(1)``) with ``scale`` None."""
    t = time.perf_counter()
    failures: list[tuple[float, str]] = []
    for fraction in (1.0, *PULL_BACK):
        params = params_at(fraction)
        reason = failure(params)
        if reason is None:
            if failures:
                log.warning("gravity check: %g x the fit completes the gravity test "
                            "(%d larger fractions did not)", fraction, len(failures))
            return params, GravityCheck(fraction, tuple(failures), time.perf_counter() - t)
        log.info("gravity check: %g x the fit does not complete the gravity test: %s",
                 fraction, reason)
        failures.append((fraction, reason))
    return params_at(1.0), GravityCheck(None, tuple(failures), time.perf_counter() - t)
