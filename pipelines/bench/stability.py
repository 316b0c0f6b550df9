"""``make bench`` item ``stability limits``: the estimated stable step against the real one.

:func:`~particle.stability.critical_time_step` (the eigenvalue bound) must never
exceed the step at which the explicit run really blows up,
:func:`~pipelines.bench.empirical_limit.empirical_critical_step` (a bisection over real runs).
:func:`stability_table` reports both on every case of :mod:`pipelines.bench.stability_cases`,
the ones the test suite checks.
"""

from __future__ import annotations

import logging

from particle.model import Model
from particle.stability import critical_time_step
from pipelines.bench.empirical_limit import empirical_critical_step
from pipelines.bench.stability_cases import (PARAMETER_SETS, PRESTRAINS, clamped_cube,
                                             stability_cases)

log = logging.getLogger(__name__)


def stability_table(quick: bool = False) -> list[dict]:
    """Estimated vs empirical limit for every :func:`stability_cases` model (JSON-ready rows)."""
    rows = []
    for name, model in stability_cases(quick).items():
        estimate = critical_time_step(model)
        empirical = empirical_critical_step(model)
        rows.append(_row(name, model, estimate, empirical))
    for parameter_set in PARAMETER_SETS:
        model = clamped_cube(parameter_set)
        estimate = critical_time_step(model)
        for strain in PRESTRAINS:
            empirical = empirical_critical_step(model, prestrain=strain)
            rows.append(_row(f"clamped cube at strain {strain:+.1f} / {parameter_set}", model,
                             estimate, empirical))
    return rows


def _row(name: str, model: Model, estimate: float, empirical: float) -> dict:
    log.info("stability %-44s estimate %.4g s, empirical %.4g s, ratio %.3f", name, estimate,
             empirical, estimate / empirical)
    return {"case": name, "connectors": model.n_connectors, "estimate_s": estimate,
            "empirical_s": empirical, "ratio": estimate / empirical}
