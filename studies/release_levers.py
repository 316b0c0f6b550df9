"""What would bring the particle model's gravity release to the FE's: two levers, measured.

The calibrated punch model's release is 27 % (RMS) from the FE's against the
goal of 10 % (docs/results.md, "Why the release misses"): its two dominant
modes are 7-9 % too low. A linear analysis (modes about the static sag) named
two levers, each worth about 3 %: a *relaxing volume term* (the FE's shear
stiffness at 5 Hz is its instantaneous one, the model's ``kv`` stays long-term)
and a mass *closer to the consistent one*. This study runs the nonlinear
release itself, the scene's gravity test sampled at the FE's record times,
for the committed model with each lever and both, **nothing refitted**:

* ``mass = "consistent"``: the P1 consistent mass of the tets
  (``rho V/20 (1 + delta_ab)``) instead of the lumped one; every step solves
  ``M a = f`` on the free dofs with a sparse LU (an explicit haptic step
  cannot afford that; this measures what it would buy). Its stable step is
  up to sqrt(5) x shorter than the lumped one (``M_c >= M_lumped / 5`` for P1
  tets), so it runs at a third of the gravity stage's step;
* ``volume_arms = r``: Maxwell arms on each tet's volume term with the global
  springs' relaxation times and stiffnesses ``r kv k_i / K0`` (``r`` = 1: the
  volume term relaxes exactly like the global spring), the paper's recursion;
* ``spring_arms = s``: every connector's arms scaled by ``s`` (stiffness and
  viscosity, so the times stay): with ``s = r`` = the FE's ``(mu0/mu_inf - 1)``
  over the global springs' ``(k1 + k2)/K0``, springs and volume term both rise
  by the FE shear modulus' ratio at high rate, roughly what a relaxation refit
  with a relaxing volume term would settle on.

``python -m studies.release_levers --scene scenes/liver_punch.toml [--run DIR]
[--out levers.json] [--figure levers.png]`` (minutes on a finished run folder of the punch
scene; the committed ones: ``runs/studies/release_levers.json``,
``runs/studies/release_levers.png``). The first row
(lumped, elastic) repeats the gravity stage's own release (checked against ``gravity.h5``
to 1e-9 of its largest displacement).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from calibration.loading import calibrated_model
from forcecal.errors import DataFileError
from particle.experiments import sample_steps
from particle.model import Model
from particle.reference_numpy import forces_numpy
from particle.volume import signed_volumes, volume_gradients_numpy
from studies._finished_run import finished_run, parse_study, study_parser, write_result
from pipelines.dynamics import release_modes
from pipelines.report import gravity_dynamic_error

log = logging.getLogger(__name__)

CONSISTENT_STEP_FRACTION = 1.0 / 3.0  # of the lumped step: below its 1/sqrt(5) bound
LEVER_COLORS = ("tab:red", "tab:green", "tab:orange", "tab:purple")  # the model is blue


@dataclass(frozen=True)
class Lever:
    """One variant of the release (module docstring).

    Attributes:
        label: short name.
        mass: "lumped" or "consistent".
        volume_arms: ratio r of the volume term's arms to the global spring's (None: elastic).
        spring_arms: factor s on every connector's arm stiffness and viscosity [1].
    """
    label: str
    mass: str = "lumped"
    volume_arms: float | None = None
    spring_arms: float = 1.0


def consistent_mass(model: Model, density: float) -> sp.csr_matrix:
    """(N, N) P1 consistent mass [kg]: ``rho V0 / 20 (1 + delta_ab)`` per tet."""
    n = model.n_particles
    block = (np.ones((4, 4)) + np.eye(4)) / 20.0
    rows = np.repeat(model.tets, 4, axis=1).ravel()
    cols = np.tile(model.tets, (1, 4)).ravel()
    vals = (density * model.rest_volumes)[:, None] * block.ravel()[None]
    return sp.csr_matrix((vals.ravel(), (rows, cols)), shape=(n, n))


def release(model: Model, density: float, gravity: np.ndarray, times: np.ndarray, dt: float,
            lever: Lever, global_arms: tuple[float, float, float, float, float]) -> np.ndarray:
    """(S, N, 3) displacements [m] at ``times`` of the release from rest with ``lever``.

    ``global_arms`` = (K0 [N/m], k1 [N/m], tau1 [s], k2 [N/m], tau2 [s]) of the global
    spring, whose relative arms the volume term takes. Position Verlet as the gravity
    stage's (start-up step ``x1 = x0 + dt^2/2 a0``), no damping.
    """
    p = model.params
    s = lever.spring_arms
    model = model.with_params(dataclasses.replace(p, k1=s * p.k1, b1=s * p.b1, k2=s * p.k2,
                                                  b2=s * p.b2))
    step_max = dt * (CONSISTENT_STEP_FRACTION if lever.mass == "consistent" else 1.0)
    h, record_steps = sample_steps(times, step_max)
    free = model.free_nodes
    if lever.mass == "consistent":
        lu = spla.splu(consistent_mass(model, density)[free][:, free].tocsc())
        acceleration = lu.solve
    elif lever.mass == "lumped":
        inv = 1.0 / model.masses[free, None]
        acceleration = lambda f: f * inv  # noqa: E731
    else:
        raise ValueError(f"mass = {lever.mass!r} is not 'lumped' or 'consistent'")
    if lever.volume_arms is not None and not model.has_volume:
        raise ValueError("volume arms need a model with the volume term")
    K0, k1, tau1, k2, tau2 = global_arms
    tau = np.array([tau1, tau2])
    arm_r = tau / (h + tau)
    arm_c = (lever.volume_arms or 0.0) * np.array([k1, k2]) / K0 * arm_r  # x kv_t
    state = model.state()
    e_prev = np.zeros(model.n_tets)
    pressure = np.zeros((model.n_tets, 2))  # the volume arms' stresses [Pa]
    out = np.empty((len(times), model.n_particles, 3))
    k = 0
    for n in range(int(record_steps[-1]) + 1):
        while k < len(times) and record_steps[k] == n:
            out[k] = state.x - model.rest_positions
            k += 1
        forces = forces_numpy(model, state, h, gravity=gravity)
        if lever.volume_arms is not None:
            e = signed_volumes(state.x, model.tets) / model.rest_volumes - 1.0
            pressure = arm_r * pressure + (p.kv[:, None] * arm_c) * (e - e_prev)[:, None]
            e_prev = e
            f = -pressure.sum(axis=1)[:, None, None] * volume_gradients_numpy(state.x,
                                                                                model.tets)
            np.add.at(forces, model.tets.ravel(), f.reshape(-1, 3))
        x, x_prev = state.x, state.x_prev
        scale = 0.5 if n == 0 else 1.0
        new = 2.0 * x[free] - x_prev[free] + scale * h * h * acceleration(forces[free])
        if not np.all(np.isfinite(new)):
            raise FloatingPointError(f"release with {lever.label} diverged at t = {n * h:.4g} s")
        x_prev[free] = x[free]
        x[free] = new
    return out


def default_levers(fe_ratio: float, global_ratio: float) -> list[Lever]:
    """The study's variants; ``fe_ratio`` = mu0/mu_inf - 1 of the FE material, ``global_ratio``
    = (k1 + k2)/K0 of the global spring."""
    s = fe_ratio / global_ratio
    return [Lever("model (lumped mass, elastic kv)"),
            Lever("consistent mass", mass="consistent"),
            Lever("relaxing kv", volume_arms=1.0),
            Lever(f"relaxing kv, all arms x{s:.3f}", volume_arms=s, spring_arms=s),
            Lever("consistent mass + relaxing kv", mass="consistent", volume_arms=1.0),
            Lever(f"consistent mass + relaxing kv, all arms x{s:.3f}", mass="consistent",
                  volume_arms=s, spring_arms=s)]


def study(scene_path: str | Path, run: str | Path | None = None) -> dict:
    """Every lever of :func:`default_levers` on the finished run of ``scene_path`` (folder
    ``run``, default ``runs/<scene name>``): RMS error and modes of the tracked vertex."""
    done = finished_run(scene_path, run)
    scene, ref, params, stage = done.scene, done.reference, done.params, done.gravity
    if ref.gravity is None or stage.time is None:
        raise DataFileError(f"{done.folder}: no gravity release to compare with")
    g = params.global_params
    model = calibrated_model(params, "calibrated", done.folder).model
    node = ref.problem.tracked_node
    times, fe = ref.gravity.time, ref.gravity.displacement
    sag = ref.gravity.static_displacement[node]
    direction = sag / np.linalg.norm(sag)  # the histories are plotted along the FE's sag
    gravity = np.asarray(scene.gravity.acceleration, dtype=np.float64)
    fe_ratio = 1.0 / (1.0 - sum(scene.material.prony_g)) - 1.0
    levers = default_levers(fe_ratio, (g.k1 + g.k2) / g.K0)
    rows = []
    fe_modes = release_modes(times, fe, node)
    for lever in levers:
        u = release(model, scene.material.density, gravity, times,
                    stage.models["calibrated"].dt, lever, (g.K0, g.k1, g.tau1, g.k2, g.tau2))
        if lever == levers[0]:
            own = stage.models["calibrated"].displacement
            gap = float(np.abs(u - own).max() / np.abs(own).max())
            if gap > 1e-9:
                raise DataFileError(f"the study's release differs from gravity.h5's by {gap:.3g} "
                                    f"of its largest displacement: not the same model")
        modes = release_modes(times, u, node)
        rows.append({"lever": dataclasses.asdict(lever),
                     "rms_error": gravity_dynamic_error(fe[:, node], u[:, node]),
                     "history_m": (u[:, node] @ direction).tolist(),
                     "modes": modes,
                     "mode_frequency_errors": [a["frequency_hz"] / b["frequency_hz"] - 1.0
                                               for a, b in zip(modes, fe_modes)]})
        log.info("%s: RMS %.4f, modes %s Hz", lever.label, rows[-1]["rms_error"],
                 [round(m["frequency_hz"], 3) for m in modes])
    return {"scene": scene.name, "tracked_node": int(node), "direction": direction.tolist(),
            "time_s": times.tolist(), "fe_history_m": (fe[:, node] @ direction).tolist(),
            "fe_modes": fe_modes, "rows": rows}


def levers_figure(path: str | Path, result: dict) -> Path:
    """PNG: the tracked vertex's release along the FE's sag direction, FE against the model
    and each lever (left: the mass, right: the relaxing volume term)."""
    from pipelines.figures import MM, STYLE, plt, save_figure

    t = np.asarray(result["time_s"])
    rows = {r["lever"]["label"]: r for r in result["rows"]}
    labels = list(rows)
    panels = ([labels[0], labels[1]], [labels[0]] + labels[2:])
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.6), sharey=True)
    for ax, panel in zip(axes, panels):
        ax.plot(t, MM * np.asarray(result["fe_history_m"]), **STYLE["fe"])
        for k, label in enumerate(panel):
            row = rows[label]
            style = (dict(STYLE["calibrated"]) if k == 0 else
                     dict(lw=1.2, color=LEVER_COLORS[(k - 1) % len(LEVER_COLORS)]))
            style["label"] = f"{label}: RMS {100 * row['rms_error']:.1f} %"
            ax.plot(t, MM * np.asarray(row["history_m"]), **style)
        ax.set(xlabel="time [s]", ylabel="displacement along the FE sag [mm]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    axes[0].set_title("mass: lumped (the model's) or P1 consistent")
    axes[1].set_title("volume term: elastic (the model's) or relaxing like the springs")
    fig.suptitle(f"{result['scene']}: release of vertex {result['tracked_node']} from rest, "
                 "committed calibrated model, nothing refitted")
    return save_figure(fig, Path(path))


def main(argv: list[str] | None = None) -> None:
    parser = study_parser("studies.release_levers", __doc__)
    parser.add_argument("--figure", help="draw the releases into this PNG")
    args = parse_study(parser, argv)
    result = study(args.scene, args.run)
    def modes(ms: list[dict]) -> str:
        return ", ".join(f"{m['frequency_hz']:.3f} Hz {1e3 * m['amplitude_m']:.2f} mm" for m in ms)

    print(f"{'lever':52s} {'RMS %':>6s}  modes (FE: {modes(result['fe_modes'])})")
    for row in result["rows"]:
        print(f"{row['lever']['label']:52s} {100 * row['rms_error']:6.2f}  {modes(row['modes'])}")
    write_result(parser, args.out, result)
    if args.figure:
        levers_figure(args.figure, result)


if __name__ == "__main__":
    main()
