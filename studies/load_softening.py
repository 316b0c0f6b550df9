"""Why does a body load lower the particle model's modes more than the FE's: the springs'
strain law, or the model's other terms under load?

The punch scenes fit the FE's whole-body data (experiment ``body``): among them the lowest
natural modes at rest and about the organ's weight along each axis perpendicular to the
scene's gravity (``loaded_modes``). A load lowers the model's modes more than the FE's
(``report.json`` ``body``: on the punch liver the calibrated model's lowest mode is 2.1 %
below the FE's at rest, 8.2 % below about the first load), and the release, held out, swings
about a loaded state. The connectors' springs stiffen or soften with strain
(``K(eps) = K0 + a eps + b eps^2``); if that law is what the load exercises, the same model
with linear springs (``a = b = 0``, every other parameter kept) takes the load as the FE
does. Nothing is refitted and only calibration data are read (the whole-body items are what
the calibration fits; nothing of the gravity tests).

For each variant -- the finished run's ``baseline`` and ``calibrated`` and each with linear
springs -- and each kind of modes the reference holds (at rest at the instantaneous and
long-term moduli, about each load, of the unsupported body), the frequency error of every FE
mode against its MAC partner (:func:`calibration.body.variant_summary`), and per load the
*load shift* of the mean error: the mean frequency error about that load less the mean at
rest at the same (instantaneous) moduli, which is negative where the load lowers the model's
modes more than the FE's, and how much each load moves the lowest mode from its frequency at
rest, the FE's and each variant's (``first_mode_shifts``). With them, the calibrated
connectors' strain range about each load and how far their springs' ``K(eps)/K0`` moves
over it.

``python -m studies.load_softening --scene scenes/liver_punch.toml [--run DIR] [--out FILE]``
(default ``runs/studies/load_softening_<scene name>.json``; a few seconds on a finished run
folder).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from studies._finished_run import finished_run, study_main

log = logging.getLogger(__name__)

#: the variants of the finished run compared (``report.json`` ``body`` has the same)
VARIANTS = ("baseline", "calibrated")
#: the mode kinds of :func:`calibration.body.variant_summary` at rest (the load shift's base)
REST = "instantaneous"


def linear_springs(params):
    """``params`` with every connector's spring linear (``a = b = 0``), the rest kept."""
    return dataclasses.replace(params, a=np.zeros_like(params.a), b=np.zeros_like(params.b))


def load_shifts(summary: dict) -> dict[str, float]:
    """{load kind: mean frequency error about it - mean at rest} of one variant's summary
    (:func:`calibration.body.variant_summary`; the loads' kinds are ``load <k>``)."""
    rest = float(np.mean(summary[REST]["frequency_errors"]))
    return {kind: float(np.mean(value["frequency_errors"])) - rest
            for kind, value in summary.items()
            if kind.startswith("load ") and isinstance(value, dict)}


def first_mode_shifts(body, summary: dict | None = None) -> list[float]:
    """Per load: how much the lowest mode's frequency changes from rest (instantaneous
    moduli) to about that load, ``f_load / f_rest - 1``: the FE's (``summary`` None) or a
    variant's (its modes paired with those two FE modes, ``f = (1 + e) f_FE``)."""
    rest = body.frequencies[0, 0]  # BODY_MODULI[0]: instantaneous
    out = []
    for k, loaded in enumerate(body.loaded_frequencies[:, 0]):
        ratio = loaded / rest
        if summary is not None:
            ratio *= ((1.0 + summary[f"load {k}"]["frequency_errors"][0])
                      / (1.0 + summary[REST]["frequency_errors"][0]))
        out.append(float(ratio - 1.0))
    return out


def mode_errors(summary: dict) -> dict[str, list[float]]:
    """{mode kind: the frequency errors of its modes} of one variant's summary."""
    return {kind: [float(e) for e in value["frequency_errors"]]
            for kind, value in summary.items()
            if isinstance(value, dict) and "frequency_errors" in value}


def strain_reach(model, body, load_steps: int) -> list[dict]:
    """Per load: the calibrated connectors' strain range at its static equilibrium and the
    range of ``K(eps)/K0`` over each connector's strain there (1 for linear springs)."""
    from particle.statics import weight_equilibrium

    p = model.params
    out = []
    for g in body.load_accelerations:
        x = weight_equilibrium(model, np.asarray(g, float), load_steps)
        d = x[model.edges[:, 1]] - x[model.edges[:, 0]]
        eps = np.linalg.norm(d, axis=1) / model.rest_lengths - 1.0
        ratio = p.stiffness(eps) / p.K0
        out.append({"acceleration": [float(v) for v in g],
                    "strain": [float(eps.min()), float(eps.max())],
                    "stiffness_ratio": [float(ratio.min()), float(ratio.max())]})
    return out


def study(scene_path, run=None) -> dict:
    """Every variant's mode errors and load shifts, with and without linear springs (module
    docstring)."""
    from calibration.body import BodyData, variant_summary
    from calibration.loading import calibrated_model

    done = finished_run(scene_path, run)
    body = done.reference.body
    if body is None:
        raise SystemExit(f"{done.folder}: the reference has no whole-body data (experiment "
                         "body)")
    load_steps = done.scene.body.load_steps
    models = {v: calibrated_model(done.params, v, done.folder).model for v in VARIANTS}
    rows = {}
    for variant, model in models.items():
        data = BodyData(model, body, (), load_steps)
        for springs, params in (("as fitted", model.params),
                                ("linear", linear_springs(model.params))):
            summary = variant_summary(data, params)
            name = f"{variant}, {springs} springs"
            rows[name] = {"mode_errors": mode_errors(summary),
                          "load_shifts": load_shifts(summary),
                          "first_mode_shifts": first_mode_shifts(body, summary),
                          "failures": summary.get("failures")}
            log.info("%s: load shifts %s", name,
                     {k: round(v, 4) for k, v in rows[name]["load_shifts"].items()})
    return {"scene": done.scene.name, "load_steps": load_steps,
            "fe_first_mode_shifts": first_mode_shifts(body), "variants": rows,
            "calibrated_strains": strain_reach(models["calibrated"], body, load_steps)}


def main(argv: list[str] | None = None) -> int:
    return study_main("studies.load_softening", __doc__, study, argv)


if __name__ == "__main__":
    raise SystemExit(main())
