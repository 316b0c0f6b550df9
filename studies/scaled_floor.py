"""Would a vertex-only continuum model, its shear stiffness scaled once to the FE's natural
modes, pass the held-out gravity tests better than the calibrated network?

``studies.shape_response`` found that a central-force network's stiffness does not follow the
body's change of shape as a continuum's does, while linear displacement-pressure tets on the
particle mesh (``ANP``, the discretisation floor's element) do. The floor itself, with the true
material, is far too stiff on the punch scenes' coarse meshes (its lowest mode ~20 % high).
Here the floor element's shear moduli (``C10``, ``C01``; the bulk modulus and the Prony
series kept) are scaled by one factor ``s`` chosen on calibration data only: the mean
frequency ratio of the FE's lowest rest modes at the instantaneous moduli (the reference's
whole-body data, experiment ``body``), matched by a fixed-point iteration ``s <- s (mean
f_FE / f_floor)^2``. The scaled element then runs the reference's held-out tests exactly as
the floor does (:func:`reference_fe.floor.element_arrays`: the gravity test, the second
support, the held-out curves), measured as the report measures the calibrated model
(:func:`pipelines.report.floor_block`), next to the calibrated and baseline models' errors
from the run's ``report.json``. Nothing of the gravity tests chooses ``s``. With them, what
each would cost an explicit (haptic) step: its exact stability limit at rest, the scaled
element's with the particles' lumped masses and its nodal pressures condensed, the calibrated
and baseline networks' at their instantaneous stiffness.

``python -m studies.scaled_floor --scene scenes/liver_punch.toml [--run DIR] [--out FILE]``
(the run folder needs ``reference.h5`` with the experiments ``body``, the gravity tests and
the floor, ``params.h5`` and ``report.json``; a minute on the punch scenes).
"""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np

from studies._finished_run import run_folder, study_main

log = logging.getLogger(__name__)

#: the floor element scaled
ELEMENT = "ANP"
#: the rest modes the scale is matched to (instantaneous moduli), and the fixed-point steps
MODES, ITERATIONS = 6, 4
#: the report's metrics compared
METRICS = ("static_sag", "release_rms", "period_error", "first_peak_error",
           "second_support_static_sag", "second_support_release_rms",
           "indentation_held_out", "relaxation_held_out")


def scaled_material(material, scale: float):
    """``material`` with its shear moduli ``C10, C01`` times ``scale`` (the rest kept)."""
    return dataclasses.replace(material, C10=scale * material.C10, C01=scale * material.C01)


def rest_frequencies(scene, problem, scale: float) -> np.ndarray:
    """(MODES,) the floor element's lowest rest frequencies [Hz] at the instantaneous moduli,
    shear moduli times ``scale``."""
    from reference_fe.body import natural_modes
    from reference_fe.floor import floor_fe
    from reference_fe.model import FEModel

    model = FEModel(problem.mesh, scaled_material(scene.material, scale),
                    floor_fe(scene, ELEMENT))
    try:
        return natural_modes(model, problem.fixed, MODES, "instantaneous")[0]
    finally:
        model.destroy()


def matched_scale(scene, problem, fe_frequencies: np.ndarray) -> tuple[float, list[dict]]:
    """The shear scale whose rest modes' mean frequency ratio to ``fe_frequencies`` is 1, by
    ``ITERATIONS`` fixed-point steps from 1, with each step's (scale, ratio)."""
    scale, steps = 1.0, []
    for _ in range(ITERATIONS):
        ratio = float(np.mean(fe_frequencies[:MODES] / rest_frequencies(scene, problem, scale)))
        steps.append({"scale": scale, "mean_frequency_ratio": ratio})
        scale *= ratio ** 2
    return scale, steps


def largest_frequency(stiffness, mass: np.ndarray) -> float:
    """``omega_max`` [rad/s] of ``stiffness`` (n, n) [N/m] with the diagonal ``mass`` (n,)
    [kg]: the explicit central-difference step is stable below ``2 / omega_max``."""
    import scipy.sparse as sp
    from particle.stability import largest_eigenvalue

    scale = sp.diags(1.0 / np.sqrt(mass))
    return float(np.sqrt(largest_eigenvalue(sp.csr_matrix(scale @ stiffness @ scale))))


def floor_stable_step(scene, problem, scale: float) -> float:
    """The explicit step's exact stability limit [s] at rest of the scaled floor element with
    the particles' lumped masses (the P1 mass's row sums): its stiffness at the instantaneous
    moduli with the nodal pressures condensed (``K_uu - K_up K_pp^-1 K_pu``, ``K_pp`` the
    lumped pressure compliance, diagonal) on the free vertices' dofs."""
    import scipy.sparse as sp
    from reference_fe.body import stiffness_and_mass
    from reference_fe.floor import floor_fe
    from reference_fe.model import FEModel

    model = FEModel(problem.mesh, scaled_material(scene.material, scale),
                    floor_fe(scene, ELEMENT))
    try:
        stiffness, mass = stiffness_and_mass(model, "instantaneous")
        free = model.vertex_dofs[problem.free].ravel()
        every = model.vertex_dofs.ravel()
        p = model.pressure_dofs
        K = stiffness.tocsr()
        condensed = (K[free][:, free] - K[free][:, p]
                     @ sp.diags(1.0 / K[p][:, p].diagonal()) @ K[p][:, free])
        lumped = np.asarray(mass.tocsr()[free][:, every].sum(axis=1)).ravel()
        return 2.0 / largest_frequency(condensed, lumped)
    finally:
        model.destroy()


def study(scene_path, run=None) -> dict:
    """The scaled floor element's held-out test errors (module docstring)."""
    from forcecal.h5io import read_reference
    from forcecal.scene import load_scene
    from pipelines.report import floor_block, held_out_curves
    from pipelines.runners.common import REFERENCE, REPORT
    from reference_fe.floor import element_arrays, floor_fe, result_of

    scene = load_scene(scene_path)
    folder = run_folder(scene, run)
    reference = read_reference(folder / REFERENCE)
    report = json.loads((folder / REPORT).read_text())
    if reference.body is None or reference.gravity is None:
        raise SystemExit(f"{folder}: the reference needs the experiments body and gravity")
    problem = reference.problem
    scale, steps = matched_scale(scene, problem, reference.body.frequencies[0])
    scaled = dataclasses.replace(scene, material=scaled_material(scene.material, scale))
    arrays = element_arrays(scaled, problem, floor_fe(scaled, ELEMENT))
    if "second_support" in scene.experiments:
        arrays["second_support_tracked_node"] = report["second_support"]["tracked_node"]
    floor = result_of({(k if k == "second_support_tracked_node" else f"{ELEMENT}_{k}"): v
                       for k, v in arrays.items()},
                      dataclasses.replace(scene.gravity, tracked_node=problem.tracked_node))
    ran = scene.experiments
    block = floor_block(problem, reference.gravity, floor, report["errors"],
                        report["baseline_errors"], report["gravity"]["dynamic_metrics"],
                        held_out=held_out_curves(reference),
                        second_support=(reference.second_support if "second_support" in ran
                                        else None),
                        support_block=report.get("second_support"))
    unscaled = report["discretisation_floor"]["elements"][ELEMENT]
    rows = {"scaled floor": {m: block["elements"][ELEMENT].get(m) for m in METRICS},
            "floor": {m: unscaled.get(m) for m in METRICS},
            "calibrated": {m: block["calibrated"].get(m) for m in METRICS},
            "baseline": {m: block["baseline"].get(m) for m in METRICS}}
    from calibration import read_params
    from calibration.loading import calibrated_model
    from pipelines.runners.common import PARAMS
    from studies.stable_step_gap import exact_rest_step

    calibration = read_params(folder / PARAMS)
    stable_steps = {"scaled floor": floor_stable_step(scene, problem, scale),
                    **{v: exact_rest_step(calibrated_model(calibration, v,
                                                           folder / PARAMS).model)
                       for v in ("calibrated", "baseline")}}
    return {"scene": scene.name, "element": ELEMENT, "scale": scale, "scale_steps": steps,
            "stable_step_at_rest_s": stable_steps,
            "rest_frequencies_fe": reference.body.frequencies[0][:MODES].tolist(),
            "rest_frequencies_scaled": rest_frequencies(scene, problem, scale).tolist(),
            "failed": block["elements"][ELEMENT].get("failed"),
            "second_support_failed": block["elements"][ELEMENT].get("second_support_failed"),
            "rows": rows}


def main(argv: list[str] | None = None) -> int:
    return study_main("studies.scaled_floor", __doc__, study, argv)


if __name__ == "__main__":
    raise SystemExit(main())
