"""Would support-free (free-free) natural modes tell the calibration what its body data miss?

The punch scenes fit the FE's natural modes *with the scene's support* (experiment
``body``), and the calibrated model matches them; yet under the held-out second support its
release is further from the FE's than the closed-form baseline's (``report.json``
``second_support``). One explanation: modes with one support constrain the stiffness only in
the combinations that support exercises, so the fit is free to misplace stiffness where
another support loads the body. The free-free modes do not depend on any support; if the
calibrated model's free-free frequencies are off where its supported ones are right, they
carry information the fitted data lack, and are a candidate whole-body item (to be chosen
by the calibration's cross-validation, never on the held-out tests).

This study measures it on a finished run, nothing refitted: for each support -- the scene's
(``main``, the fitted one), the second support (``second``, held out: read here to test the
explanation, not to choose anything) and none (``free``) -- the ``count`` lowest natural
modes about the rest state of the FE (Taylor-Hood or the scene's element on the gravity
experiments' mesh, :func:`reference_fe.body.natural_modes` and
:func:`~reference_fe.body.unsupported_modes`, shapes read at the particle vertices) and of
each particle-model variant (``baseline``, ``calibrated``: the tangent at rest,
:func:`particle.body.model_modes`, lumped masses), at the instantaneous and long-term
moduli. Each FE mode is paired with a model mode by MAC
(:func:`particle.body.pair_modes`, among ``count + 4`` model modes); the row is the pair's
frequency error ``f_model / f_FE - 1`` and its MAC. With them, how the calibrated model
splits its stiffness between springs and volume term (``calibrated_split``: the median of
its springs' ``K0`` over the baseline's, the same at the instantaneous stiffness, its median
``kv``). Free-free problems are solved shifted,
their six rigid modes left out (:func:`forcecal.eigen.free_modes`).

``python -m studies.free_modes --scene scenes/liver_punch.toml [--run DIR] [--count 6]
[--out FILE]`` (default ``runs/studies/free_modes_<scene name>.json``; seconds per
scene on a finished run folder: 6 s on the liver punch scene).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np

from forcecal.problem import second_support
from studies._finished_run import finished_run, parse_study, study_parser, write_result

log = logging.getLogger(__name__)

#: the moduli the modes are compared at (:data:`reference_fe.body.MODULI`)
MODULI = ("instantaneous", "long_term")
#: the model modes each FE mode may pair with, beyond ``count``
EXTRA = 4


class FEModes:
    """The FE model of the gravity experiments and its modes, read at the particle vertices."""

    def __init__(self, scene, problem):
        from reference_fe.model import FEModel
        from reference_fe.refine import fe_problem

        self.scene, self.problem = scene, problem
        self.fe = fe_problem(problem, scene.fe)
        self.model = FEModel(self.fe.problem.mesh, scene.material, scene.fe)

    def modes(self, fixed: np.ndarray | None, modulus: str, count: int
              ) -> tuple[np.ndarray, np.ndarray]:
        """((count,) frequencies [Hz], (count, N, 3) shapes at the particle vertices) with the
        particle vertices ``fixed`` clamped (None: free-free)."""
        from reference_fe.body import natural_modes, unsupported_modes
        from reference_fe.refine import fe_clamp

        if fixed is None:
            frequencies, shapes = unsupported_modes(self.model, count, modulus)
        else:
            frequencies, shapes = natural_modes(
                self.model, fe_clamp(self.problem, fixed, self.fe, self.scene.fe), count,
                modulus)
        return frequencies, shapes[:, self.fe.vertex_map]


def model_modes(model, fixed: np.ndarray | None, modulus: str, count: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The particle ``model`` with the vertices ``fixed`` held (None: free-free): ((count,)
    frequencies [Hz], (n, count) shapes on its free dofs, (n,) dof masses [kg], (Nf,) free
    particles)."""
    from particle.body import RestOperators
    from particle.body import model_modes as lowest

    held = np.zeros(model.n_particles, bool)
    if fixed is not None:
        held[fixed] = True
    supported = dataclasses.replace(model, fixed=held)
    ops = RestOperators.of(supported)
    values, vectors, _ = lowest(supported, ops, modulus, count, free_free=fixed is None)
    return np.sqrt(values) / (2.0 * np.pi), vectors, ops.mass, supported.free_nodes


def compare(fe_freq: np.ndarray, fe_shapes: np.ndarray, model, fixed: np.ndarray | None,
            modulus: str) -> dict:
    """The FE modes ``fe_freq`` (M,), ``fe_shapes`` (M, N, 3) against ``model``'s: each FE
    mode's MAC partner, its frequency error and MAC."""
    from particle.body import pair_modes

    count = len(fe_freq)
    freq, vectors, mass, free_nodes = model_modes(model, fixed, modulus, count + EXTRA)
    fe = fe_shapes[:, free_nodes].reshape(count, -1).T  # (n, M) on the model's free dofs
    partner, mac = pair_modes(fe, vectors, mass)
    errors = freq[partner] / fe_freq - 1.0
    return {"frequency_hz": freq[partner].tolist(), "frequency_error": errors.tolist(),
            "mac": mac.tolist(), "partner": partner.tolist(),
            "mean_abs_frequency_error": float(np.mean(np.abs(errors)))}


def study(scene_path: str | Path, run: str | Path | None = None, count: int = 6) -> dict:
    """The modes of every support, modulus and variant (module docstring)."""
    from calibration.loading import calibrated_model

    done = finished_run(scene_path, run)
    scene, params = done.scene, done.params
    problem = params.problem
    supports = {"main": problem.fixed, "second": second_support(scene, problem).fixed,
                "free": None}
    fe = FEModes(scene, problem)
    models = {v: calibrated_model(params, v, done.folder).model
              for v in ("baseline", "calibrated")}
    rows = []
    for name, fixed in supports.items():
        for modulus in MODULI:
            fe_freq, fe_shapes = fe.modes(fixed, modulus, count)
            row = {"support": name, "modulus": modulus, "fe_frequency_hz": fe_freq.tolist()}
            for variant, model in models.items():
                row[variant] = compare(fe_freq, fe_shapes, model, fixed, modulus)
            log.info("%s support, %s: FE %s Hz; frequency errors baseline %s, calibrated %s",
                     name, modulus, np.round(fe_freq, 2).tolist(),
                     np.round(row["baseline"]["frequency_error"], 3).tolist(),
                     np.round(row["calibrated"]["frequency_error"], 3).tolist())
            rows.append(row)
    main = [r for r in rows if r["support"] == "main"]
    fitted = (done.reference.body.frequencies if done.reference.body is not None else None)
    check = None
    if fitted is not None:  # the body experiment's modes are the main support's
        ours = np.array([r["fe_frequency_hz"] for r in main])
        check = float(np.max(np.abs(ours[:, :fitted.shape[1]] / fitted[:, :ours.shape[1]]
                                    - 1.0)))
    base, cal = models["baseline"].params, models["calibrated"].params
    split = {"spring_ratio_median": float(np.median(cal.K0 / base.K0)),
             "instantaneous_spring_ratio_median": float(np.median(
                 (cal.K0 + cal.k1 + cal.k2) / (base.K0 + base.k1 + base.k2))),
             "kv_median_pa": None if cal.kv is None else float(np.median(cal.kv))}
    return {"scene": scene.name, "count": count, "calibrated_split": split,
            "fitted_body_data": "+".join(params.body.get("kinds", [])) or "none",
            "element": scene.fe.element, "fe_refine": scene.fe.refine,
            "main_support_vs_body_experiment_max_relative_difference": check,
            "load_average": list(os.getloadavg()), "rows": rows}


def main(argv: list[str] | None = None) -> None:
    parser = study_parser("studies.free_modes", __doc__)
    parser.add_argument("--count", type=int, default=6, help="FE modes compared per case")
    args = parse_study(parser, argv)
    write_result(parser, args.out, study(args.scene, args.run, args.count))


if __name__ == "__main__":
    main()
