"""``particle.volume = true`` and ``false`` give what they gave before the viscoelastic volume
term existed.

:func:`scenario` runs the particle side (explicit steps, threaded step, haptic session,
stable step, static sag, indentation and relaxation curves, their adjoint Jacobians) and
two short calibrations (the paper's method and the gradient method) on the box, with the
elastic volume term and without it, and summarises every result (a few sums and values of
its float64 arrays). ``tests/data/volume_regression.json`` holds the summaries the code
computed before the viscoelastic term was added (``python -m tests.test_volume_regression``
writes them, run with that code first on the path). They must agree to round-off: the
compiled kernels and BLAS may round differently on another CPU (fused multiply-adds, vector
width), so "bit for bit" holds on one machine only; 1e-9 relative on the particle results
and 1e-6 on the short calibrations (whose simplex may take another step on a last-bit
tie) still catch any change of the physics.
"""
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parent / "data" / "volume_regression.json"
GRAVITY = np.array([0.0, 0.0, -9.81])


def digest(*arrays) -> list[float | None]:
    """Sum, absolute sum, largest magnitude, first and last value of each of ``arrays`` as
    float64 (None for an array that is None)."""
    out: list[float | None] = []
    for a in arrays:
        if a is None:
            out.append(None)
            continue
        a = np.asarray(a, dtype=np.float64).ravel()
        out += [float(a.sum()), float(np.abs(a).sum()), float(np.abs(a).max()),
                float(a[0]), float(a[-1])]
    return out


def particle_digests(volume: bool, step_basis: float | None = None) -> dict[str, str]:
    """Every particle-side result of the box with (``volume``) or without the elastic term.

    The runs take half of ``step_basis`` [s] as their step (None: of the stability limit
    computed now): the test passes the limit the summaries were computed with, so that a
    tighter (still rigorous) stable-step bound changes the limit's own summary only."""
    from particle.haptics import HapticSession
    from particle.integrator import VerletIntegrator
    from particle.sensitivity import sensitivity_evaluators
    from particle.stability import critical_time_step
    from particle.statics import gravity_static
    from tests.particle_models import box_model, deformed_start_and_push, top_centre

    model = box_model((3, 3, 2), a=-20.0, b=300.0)
    if volume:
        kv = 2000.0 + 100.0 * np.arange(model.n_tets) / model.n_tets
        model = model.with_params(dataclasses.replace(model.params, kv=kv))
    out = {}
    limit = critical_time_step(model, damping=3.0)
    out["critical_time_step"] = digest(limit)
    dt = 0.5 * (limit if step_basis is None else step_basis)
    state, motion = deformed_start_and_push(model, dt)
    VerletIntegrator(3.0).simulate(model, state, dt, 200, gravity=GRAVITY, prescribed=motion)
    out["explicit"] = digest(state.x, state.x_prev, state.arm_force, state.dx_prev)
    state = model.state()
    VerletIntegrator().simulate(model, state, dt, 100, gravity=GRAVITY, threads=2)
    out["threaded"] = digest(state.x, state.arm_force)
    node = top_centre(model)
    session = HapticSession(model, dt)
    forces = [session.step(node, model.rest_positions[node] + [0.0, 0.0, -2e-4 * (k + 1)])
              for k in range(5)]
    out["haptic"] = digest(np.array(forces), session.state.x)
    out["gravity_static"] = digest(gravity_static(model, GRAVITY))
    normal = np.array([[0.0, 0.0, -1.0]])
    evaluators = sensitivity_evaluators(model, np.array([node]), normal,
                                        np.array([2.5e-4, 5e-4, 1e-3]),
                                        np.array([0.05, 0.1, 1.0, 5.0]),
                                        np.full(4, 1e-3))
    for kind, ev in evaluators.items():
        sens = ev.jacobian(model.params)
        out[kind] = digest(sens.forces, sens.connectors, sens.kv)
    return out


def calibration_digests(volume: bool, method: str) -> dict[str, str]:
    """A short calibration of a synthetic box reference (elastic volume term or none)."""
    from calibration.core import calibrate
    from calibration.parametrisation import GlobalParams
    from calibration.synthetic import box_scene, synthetic_reference
    from forcecal.problem import build_problem
    from forcecal.scene import replace
    from particle.volume import network_bulk_modulus

    with tempfile.TemporaryDirectory() as d:
        scene = box_scene(d, test_points={"calibration": "cover", "n_calibration": 4,
                                          "n_held_out": 8},
                          indentation={"depth": 0.002}, relaxation={"depth": 0.002},
                          calibration={"static_max_evaluations": 12,
                                       "relaxation_max_evaluations": 12, "workers": 1,
                                       "method": method, "local_max_sweeps": 1,
                                       "local_max_evaluations": 6,
                                       "gradient_max_iterations": 1})
        scene = replace(scene, particle={"volume": volume})
        mesh = build_problem(scene).mesh
        truth = GlobalParams(K0=30.0, alpha=1.0, beta=10.0, k1=26.0, tau1=0.5, k2=19.0,
                             tau2=10.0,
                             kv=2.0 * network_bulk_modulus(mesh, 30.0) if volume else 0.0)
        synthetic_reference(scene, truth.connector_params(len(mesh.edges)), Path(d) / "ref.h5")
        result = calibrate(scene, Path(d) / "ref.h5", Path(d) / "params.h5", progress=False)
    p = result.connectors["calibrated"]
    g = result.global_params
    return {f"{method}_global": digest([g.K0, g.alpha, g.beta, g.k1, g.tau1, g.k2, g.tau2,
                                        g.kv]),
            f"{method}_calibrated": digest(p.K0, p.a, p.b, p.k1, p.b1, p.k2, p.b2, p.kv)}


def scenario(step_bases: dict[str, float] | None = None) -> dict[str, dict[str, list]]:
    """The summaries of both cases; ``step_bases``: per case the limit whose half the runs
    take as their step (None: the limit computed now)."""
    out = {}
    for volume in (False, True):
        case = f"volume={str(volume).lower()}"
        digests = particle_digests(volume, None if step_bases is None else step_bases[case])
        for method in ("paper", "gradient"):
            digests.update(calibration_digests(volume, method))
        out[case] = digests
    return out


def test_the_elastic_volume_term_and_no_volume_term_are_unchanged():
    """Every summary equal, to round-off, to the one computed before the viscoelastic term;
    the runs at the step those were computed with. The stability limit itself may only have
    grown (a tighter rigorous bound: with the volume term, its spectral bound), and is equal
    without the volume term."""
    want = json.loads(DATA.read_text())
    got = scenario({case: s["critical_time_step"][0] for case, s in want.items()})
    assert got["volume=false"]["critical_time_step"] == pytest.approx(
        want["volume=false"]["critical_time_step"], rel=1e-9)
    assert got["volume=true"]["critical_time_step"][0] >= want["volume=true"][
        "critical_time_step"][0]
    for case, summaries in want.items():
        for name, value in summaries.items():
            if name == "critical_time_step":
                continue
            rtol = 1e-6 if name.startswith(("paper_", "gradient_")) else 1e-9
            assert [v is None for v in got[case][name]] == [v is None for v in value], name
            np.testing.assert_allclose(
                [v for v in got[case][name] if v is not None], [v for v in value if v is not None],
                rtol=rtol, atol=rtol * max((abs(v) for v in value if v is not None), default=0),
                err_msg=f"{case}: {name} changed")


if __name__ == "__main__":
    DATA.parent.mkdir(exist_ok=True)
    DATA.write_text(json.dumps(scenario(), indent=1) + "\n")
    print(f"wrote {DATA}", file=sys.stderr)
