"""The four experiments of the FE reference, each a march of Newton steps with step cutting.

* :func:`indentation_curve` - one vertex pushed along its inward normal,
  quasi-static, long-term material, no gravity; :func:`punch_indentation_curve`
  the same with a rigid flat punch (every FE node of its footprint held).
* :func:`relaxation_curve` - ramp-and-hold indentation, quasi-static (no
  inertia, like a static analysis with a time-dependent material), viscoelastic.
* :func:`gravity_static` - sag under gravity, long-term material, load-stepped.
* :func:`gravity_dynamic` - released from rest at t = 0 with gravity on,
  viscoelastic, implicit Newmark average acceleration (no numerical damping:
  the viscoelasticity is the only dissipation).

Every experiment clamps the problem's fixed vertices (:meth:`FEModel.clamp_dofs`).
A step whose Newton solve fails is halved, up to ``fe.max_step_cuts`` times;
then :class:`~forcecal.errors.ConvergenceError` names the experiment, the
step and the load or time it failed at (its ``reached`` attribute: the last converged
value of the control variable).
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Iterator

import numpy as np

from forcecal.errors import ConvergenceError, SceneError, StabilityError
from forcecal.fe_failures import crushed_tet
from forcecal.preflight import tet_quality
from forcecal.schedules import record_times
from forcecal.indenter import footprint_edges, punch_footprint
from reference_fe.model import (Constraint, FEModel, FEState, Load, StepFailed, clamp,
                                initial_state, prescribe_dofs, solve_step)

log = logging.getLogger(__name__)

Step = Callable[[FEState, FEState | None, float], FEState]


class Stopped(Exception):
    """Raised between two steps when the stop check says so (another rank's item failed)."""


_stop_check: Callable[[], bool] | None = None


def set_stop_check(check: Callable[[], bool] | None) -> None:
    """Install ``check`` (None: remove it), asked before every step of every experiment: a
    failed work item on one rank stops the others at their next step, not after their item
    (:func:`reference_fe.run.compute_reference`)."""
    global _stop_check
    _stop_check = check


def march(state: FEState, targets: np.ndarray, step: Step, *, max_cuts: int, what: str,
          unit: str) -> Iterator[FEState]:
    """Yield the converged state at each target value of the control variable, in order.

    ``step(state, previous, target)`` solves from ``state`` (``previous`` is the
    converged state before it, for extrapolated guesses) to ``target``. A failed
    step is retried with half the increment, at most ``max_cuts`` times per target.
    """
    previous = None
    for k, target in enumerate(targets):
        increment = target - state.progress
        cuts = 0
        while state.progress < target:
            if _stop_check is not None and _stop_check():
                raise Stopped(what)
            nxt = state.progress + increment
            if target - nxt <= 1e-9 * abs(increment):  # land exactly on the target
                nxt = target
            try:
                new = step(state, previous, nxt)
            except StepFailed as exc:
                cuts += 1
                if cuts > max_cuts:
                    error = ConvergenceError(
                        f"{what}: step {k + 1}/{len(targets)} (to {target:.6g} {unit}) did not "
                        f"converge from {state.progress:.6g} {unit} even after {max_cuts} "
                        f"halvings of the increment (last try: to {nxt:.6g} {unit}; {exc})")
                    error.reached = state.progress  # how far the experiment got
                    raise error from None
                increment /= 2.0
                log.info("%s: step to %.6g %s failed, halving the increment (cut %d/%d)",
                         what, nxt, unit, cuts, max_cuts)
                continue
            previous, state = state, new
        yield state


#: fraction of the linear extrapolation in time that guesses a held step (the creep of a
#: relaxation hold, :func:`extrapolate`): the Prony terms decay, so the creep slows and the
#: full linear extrapolation overshoots. Measured on three liver punch points (24k TH dofs):
#: Newton iterations of a relaxation curve 291 / 283 / 282 with the last state as the guess,
#: 251 / 237 / 239 with 0.8 (0.5: 271 / 263 / 264; 1.0 at the first point: 266)
HELD_EXTRAPOLATION = 0.8


def extrapolate(state: FEState, previous: FEState | None, drive: Callable[[float], float],
                target: float, *, held: float = 0.0) -> np.ndarray:
    """Newton guess: the solution extrapolated linearly in the driving load ``drive(progress)``.

    Exact for the prescribed dofs; a much better start than the last solution
    for the rest. When the drive does not change (a hold), the last step's change
    extrapolated linearly in the progress (time) and scaled by ``held``
    (0: the last solution; the prescribed dofs do not move either way).
    """
    if previous is None:
        return state.u
    span = drive(state.progress) - drive(previous.progress)
    if span == 0.0:
        if not held:
            return state.u
        ratio = (target - state.progress) / (state.progress - previous.progress)
        return state.u + held * ratio * (state.u - previous.u)
    ratio = (drive(target) - drive(state.progress)) / span
    return state.u + ratio * (state.u - previous.u)


#: extra terms of :func:`creep_guess`'s fit besides the constant and the Prony exponentials:
#: a linear and a quadratic term in time. Measured on four default-liver relaxation curves
#: (Newton iterations of the 40 steps): 750 with ``HELD_EXTRAPOLATION`` alone, 669 fitting
#: the constant and the two exponentials to the last 3 held states, 628 with the linear term
#: (4 states), 600 with the quadratic one too (5 states)
CREEP_POLYNOMIAL_TERMS = 2


def creep_guess(held: list[FEState], target: float, taus: np.ndarray) -> np.ndarray | None:
    """Newton guess of a held step: the last converged states of the hold (``held``, oldest
    first, all at the same prescribed depth) fitted in time and evaluated at ``target`` [s].

    While the depth stands still the displacement creeps as the Prony terms relax: a
    constant plus the exponentials ``exp(-t / tau_i)`` of the relaxation times ``taus`` [s]
    (the slowest first), then ``CREEP_POLYNOMIAL_TERMS`` powers of t for what they miss (the
    body's own time constants are combinations of them). The fit uses as many of these
    functions, in that order, as there are states (at most all of them), interpolating the
    last states exactly; the result is a weighted sum of their solutions. None with fewer
    than 3 states (the caller extrapolates linearly).
    """
    n = min(len(held), 1 + len(taus) + CREEP_POLYNOMIAL_TERMS)
    if n < 3:
        return None
    states = held[-n:]
    t_last = states[-1].progress

    def basis(t: float) -> np.ndarray:
        dt = t - t_last
        terms = [1.0, *np.exp(-dt / np.sort(np.asarray(taus, float))[::-1]),
                 *(dt ** k for k in range(1, CREEP_POLYNOMIAL_TERMS + 1))]
        return np.array(terms[:n])

    B = np.array([basis(s.progress) for s in states])  # (n states, n functions)
    scale = np.abs(B).max(axis=0)  # each function of order 1 over the states (conditioning)
    weights = np.linalg.lstsq((B / scale).T, basis(target) / scale, rcond=None)[0]
    return sum(w * s.u for w, s in zip(weights, states))


def _indent(held: tuple[Constraint, ...], dofs: np.ndarray, normal: np.ndarray,
            depth: float) -> Load:
    """The clamp ``held`` and the nodes ``dofs`` moved by ``depth * normal``."""
    return Load(held + prescribe_dofs(dofs, depth * normal))


def punch_dofs(model: FEModel, fixed: np.ndarray, vertex: int, normal: np.ndarray,
               radius: float) -> np.ndarray:
    """(K, 3) dofs a rigid flat punch of ``radius`` [m] centred on ``vertex`` holds: every FE
    node of its footprint (:func:`forcecal.indenter.punch_footprint` on the FE mesh; for
    P2/TH the mid-edge nodes of the surface edges between two footprint vertices too)."""
    nodes = punch_footprint(model.mesh, vertex, normal, radius, fixed=fixed, min_nodes=1)
    return model.surface_patch_dofs(nodes, footprint_edges(model.mesh, nodes))


def held_indentation_curve(model: FEModel, fixed: np.ndarray, dofs: np.ndarray,
                           normal: np.ndarray, depths: np.ndarray, what: str) -> np.ndarray:
    """(S, 3) total force on the held nodes ``dofs`` (K, 3), all moved by ``depth * normal``,
    at each depth [N] (long-term material): the sum of their reactions.

    Args:
        fixed: (F,) clamped vertex ids.
        normal: (3,) inward unit normal.
        depths: (S,) increasing depths > 0 [m].
        what: names the experiment in a ConvergenceError.
    """
    held = clamp(model.clamp_dofs(fixed))  # once per curve (its dofs cost ~1 ms to find)

    def step(state: FEState, previous: FEState | None, depth: float) -> FEState:
        guess = extrapolate(state, previous, float, depth)
        return solve_step(model, state, _indent(held, dofs, normal, depth), depth,
                          dt=None, guess=guess)

    states = march(initial_state(model), np.asarray(depths, float), step,
                   max_cuts=model.fe.max_step_cuts, what=what, unit="m")
    return np.array([s.force[dofs].sum(axis=0) for s in states])


def held_relaxation_curve(model: FEModel, fixed: np.ndarray, dofs: np.ndarray,
                          normal: np.ndarray, times: np.ndarray, depths: np.ndarray,
                          what: str) -> np.ndarray:
    """(S, 3) total force on the held nodes ``dofs`` at each sample time of a ramp-and-hold
    test [N] (viscoelastic).

    The depth follows the piecewise-linear history through (0, 0) and the
    samples ``(times, depths)`` (from :func:`forcecal.schedules.relaxation_schedule`),
    so a halved time step stays on the prescribed history.
    """
    t_knots = np.r_[0.0, np.asarray(times, float)]
    d_knots = np.r_[0.0, np.asarray(depths, float)]

    def depth_at(t: float) -> float:
        return float(np.interp(t, t_knots, d_knots))

    held = clamp(model.clamp_dofs(fixed))
    taus = np.asarray(model.material.prony_tau, float)
    hold: list[FEState] = []  # the last converged states at the current depth, oldest first

    def step(state: FEState, previous: FEState | None, t: float) -> FEState:
        if not hold or hold[-1] is not state:  # a new converged state (not a retried step)
            if hold and depth_at(hold[-1].progress) != depth_at(state.progress):
                hold.clear()
            hold.append(state)
            del hold[:-(1 + len(taus) + CREEP_POLYNOMIAL_TERMS)]
        guess = (creep_guess(hold, t, taus) if depth_at(t) == depth_at(state.progress)
                 else None)
        if guess is None:
            guess = extrapolate(state, previous, depth_at, t, held=HELD_EXTRAPOLATION)
        return solve_step(model, state, _indent(held, dofs, normal, depth_at(t)), t,
                          dt=t - state.progress, guess=guess)

    states = march(initial_state(model), t_knots[1:], step, max_cuts=model.fe.max_step_cuts,
                   what=what, unit="s")
    return np.array([s.force[dofs].sum(axis=0) for s in states])


def indentation_curve(model: FEModel, fixed: np.ndarray, vertex: int, normal: np.ndarray,
                      depths: np.ndarray) -> np.ndarray:
    """(S, 3) force the indenter applies to ``vertex`` at each depth [N] (long-term material):
    the paper's indenter, the vertex itself moved by ``depth * normal``."""
    return held_indentation_curve(model, fixed, model.vertex_dofs[[vertex]], normal, depths,
                                  f"indentation of vertex {vertex}")


def relaxation_curve(model: FEModel, fixed: np.ndarray, vertex: int, normal: np.ndarray,
                     times: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """(S, 3) indenter force on ``vertex`` at each sample time of a ramp-and-hold test [N]."""
    return held_relaxation_curve(model, fixed, model.vertex_dofs[[vertex]], normal, times,
                                 depths, f"relaxation of vertex {vertex}")


def punch_indentation_curve(model: FEModel, fixed: np.ndarray, vertex: int, normal: np.ndarray,
                            depths: np.ndarray, *, radius: float) -> np.ndarray:
    """(S, 3) force of a rigid flat punch of ``radius`` [m] centred on ``vertex`` pushed to each
    depth along ``normal`` [N]: the sum of the reactions of its footprint (:func:`punch_dofs`)."""
    return held_indentation_curve(model, fixed, punch_dofs(model, fixed, vertex, normal, radius),
                                  normal, depths, f"punch indentation at vertex {vertex}")


def punch_relaxation_curve(model: FEModel, fixed: np.ndarray, vertex: int, normal: np.ndarray,
                           times: np.ndarray, depths: np.ndarray, *, radius: float) -> np.ndarray:
    """(S, 3) punch force at each sample time of a ramp-and-hold test [N] (viscoelastic)."""
    return held_relaxation_curve(model, fixed, punch_dofs(model, fixed, vertex, normal, radius),
                                 normal, times, depths, f"punch relaxation at vertex {vertex}")


def largest_displacement(displacement: np.ndarray) -> float:
    """The largest vertex displacement [m] of an (N, 3) displacement field [m]."""
    return float(np.linalg.norm(displacement, axis=1).max())


#: the scene section of a clamp -> the name of its gravity test in the messages
TEST_NAMES = {"fixed": "gravity", "second_support": "second support"}


def gravity_static(model: FEModel, fixed: np.ndarray, acceleration: np.ndarray,
                   load_steps: int, *, section: str = "fixed", with_state: bool = False,
                   what: str | None = None) -> np.ndarray | tuple[np.ndarray, FEState]:
    """(N, 3) static displacement of every vertex under gravity [m] (long-term material), and
    with ``with_state`` the converged :class:`FEState` too.

    Gravity is applied in ``load_steps`` equal increments (a single P2 step diverges).
    ``section`` is the scene section of the clamp ``fixed`` (named in the messages), ``what``
    the load (default: the section's gravity test, "gravity static").
    """
    what = what or f"{TEST_NAMES[section]} static"
    held = clamp(model.clamp_dofs(fixed))
    g = np.asarray(acceleration, float)

    def step(state: FEState, previous: FEState | None, factor: float) -> FEState:
        # from the last equilibrium, not extrapolated in the load: on the default liver the
        # extrapolated guesses of the steps to 0.75 and 1 g diverged (each step halved: 8
        # solves, 16 factorisations), from the last equilibrium every step converged (4
        # solves, 8 factorisations; 1,691 vertices: 8 -> 6 solves, 17 -> 11 factorisations,
        # 87 -> 43 s at one load); the sag equal to 4e-11
        return solve_step(model, state, Load(held, factor * g), factor, dt=None)

    factors = np.arange(1, load_steps + 1) / load_steps
    extent = float(np.linalg.norm(np.ptp(model.mesh.vertices, axis=0)))
    first = None  # sag per unit load of the first step
    for factor, state in zip(factors, march(initial_state(model), factors, step,
                                            max_cuts=model.fe.max_step_cuts,
                                            what=what,
                                            unit="x gravity")):
        u = model.vertex_values(state.u)
        sag = largest_displacement(u)
        first = sag / factor if first is None else first
        try:
            check_sag(sag, factor, first, extent, len(fixed), section, what)
        except StabilityError as error:
            error.reached = factor  # how far the experiment got
            raise
    return (u, state) if with_state else u


#: the static sag per unit load may grow this much over the load steps before the support is
#: called unstable (a hyperelastic body hung from a sound support stiffens instead)
SAG_GROWTH_LIMIT = 5.0


def check_sag(sag: float, factor: float, first: float, extent: float, n_fixed: int,
              section: str = "fixed", what: str | None = None) -> None:
    """Refuse a static sag that grows much faster than the load or exceeds half the body.

    Args:
        sag: largest vertex displacement at this load step [m].
        factor: fraction of the full gravity applied.
        first: sag per unit load of the first load step [m].
        extent: diagonal of the mesh's bounding box [m].
        n_fixed: number of fixed vertices (named in the message).
        section: the scene section whose rule clamps them (its keys are named).
        what: the static load named in the message (default: the section's gravity test's).

    Raises:
        StabilityError: the support does not hold the body; the message says which of the
            two happened.
    """
    growth = (sag / factor) / first if first > 0 else 1.0
    if growth > SAG_GROWTH_LIMIT:
        cause = (f"unstable support: the sag grows much faster than the load ({sag * 1e3:.3g} "
                 f"mm at {factor:.3g} x gravity, {growth:.3g} x the first load step's sag per "
                 f"unit load; body size {extent * 1e3:.3g} mm)")
    elif sag > 0.5 * extent:
        cause = (f"the support does not hold the body: the sag reaches more than half the "
                 f"body's size ({sag * 1e3:.3g} mm at {factor:.3g} x gravity, body size "
                 f"{extent * 1e3:.3g} mm; {growth:.3g} x the first load step's sag per unit "
                 f"load)")
    else:
        return
    raise StabilityError(
        f"{what or TEST_NAMES[section] + ' static'}: {cause}: the {n_fixed} fixed vertices of "
        f"the [{section}] section do not hold the body; clamp a larger patch "
        f"({section}.tolerance) or another side ({section}.axis, {section}.side)")


def gravity_dynamic(model: FEModel, fixed: np.ndarray, acceleration: np.ndarray,
                    duration: float, dt: float, record_interval: float,
                    section: str = "fixed", *, static_sag: float | None = None,
                    watched: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Release from rest in the undeformed shape with gravity on at t = 0 (``fixed`` clamped
    by the rule of scene section ``section``, named in the messages).

    Each record interval is split into ``ceil(record_interval / dt)`` equal
    steps (so the step never exceeds ``dt``). Newton starts from the
    constant-velocity predictor ``u + dt v``.

    A support that does not hold the body in motion ends the release at the first record
    past it (:func:`check_release`: the body falls over or buckles instead of swinging about
    its sag), and a release whose Newton solve fails says what its last completed time step
    shows (:func:`release_state`).

    Args:
        static_sag: the largest displacement of the same support's static sag [m] at the
            ``watched`` vertices (None: unknown, as for a scene that does not ask for the
            static sag; the release is then checked against the body's size only).
        watched: the vertices whose displacement is compared with ``static_sag`` (default:
            all).

    Returns:
        time: (S,) sample times [s], from 0 (:func:`forcecal.schedules.record_times`).
        displacement: (S, N, 3) displacement of every vertex [m] (zero at t = 0).
    """
    if not 0 < dt <= record_interval:
        raise SceneError(f"gravity.fe_dt = {dt} s must be > 0 and <= gravity.record_interval "
                         f"= {record_interval} s")
    times = record_times(duration, record_interval)
    substeps = math.ceil(record_interval / dt * (1 - 1e-9))
    step_times = np.linspace(0.0, times[-1], (len(times) - 1) * substeps + 1)[1:]
    load = Load(clamp(model.clamp_dofs(fixed)), np.asarray(acceleration, float))

    def step(state: FEState, previous: FEState | None, t: float) -> FEState:
        h = t - state.progress
        return solve_step(model, state, load, t, dt=h, inertia=True,
                          guess=state.u + h * state.velocity)

    what = f"{TEST_NAMES[section]} dynamic"
    extent = float(np.linalg.norm(np.ptp(model.mesh.vertices, axis=0)))
    watched = np.arange(model.mesh.n_vertices) if watched is None else watched
    state = initial_state(model)
    out = [model.vertex_values(state.u)]
    states = march(state, step_times, step, max_cuts=model.fe.max_step_cuts, what=what,
                   unit="s")
    try:
        for k, state in enumerate(states, start=1):
            if k % substeps == 0:
                out.append(model.vertex_values(state.u))
                log.debug("gravity dynamic: t = %.4g s", state.progress)
                moved = largest_displacement(out[-1][watched])
                check_release(moved, state.progress, static_sag, extent, len(fixed), section,
                              what)
    except ConvergenceError as error:
        # the last state the march yielded: its last completed time step (a failed step's
        # halvings may have gone a little further)
        shown = release_state(model, fixed, model.vertex_values(state.u), watched, static_sag)
        failure = ConvergenceError(f"{error}; at {state.progress:.6g} s, the last completed "
                                   f"time step: {shown}")
        failure.reached = error.reached
        raise failure from None
    return times, np.array(out)


#: the release may move the body this many times as far as the same support's static sag
#: before the support is called unable to hold it in motion. A body released from rest under
#: its weight stays within twice its long-term static sag in the linear viscoelastic limit
#: (the weight's work bounds the long-term elastic energy: u^T K u <= 2 f^T u, so
#: |u - u_s|_K <= |u_s|_K with u_s = K^-1 f); the rest is margin for the vertex-wise maximum
#: and the nonlinear material. The cantilever beam of tests/test_fe_second_support.py peaks at
#: 2.0 x nearly elastic, 0.85 x with the default Prony terms (its sag the long-term one).
RELEASE_RUNAWAY_LIMIT = 3.0


def check_release(moved: float, time: float, static_sag: float | None, extent: float,
                  n_fixed: int, section: str, what: str) -> None:
    """Raise :class:`~forcecal.errors.StabilityError` (``reached`` = ``time``) when a release
    has moved the body (``moved``, its largest displacement [m] at ``time`` [s]) more than
    :data:`RELEASE_RUNAWAY_LIMIT` x the static sag ``static_sag`` [m] of the same support, or,
    that sag unknown (None or 0), more than the body's size ``extent`` [m] (twice the most a sag
    may reach, :func:`check_sag`)."""
    if static_sag:
        if moved <= RELEASE_RUNAWAY_LIMIT * static_sag:
            return
        cause = (f"the release has moved the body by {moved * 1e3:.3g} mm at {time:.4g} s, "
                 f"{moved / static_sag:.2f} x its static sag of {static_sag * 1e3:.3g} mm (a "
                 f"body that holds on its support swings within about twice it): it falls "
                 f"over or buckles")
    elif moved > extent:
        cause = (f"the release has moved the body by {moved * 1e3:.3g} mm at {time:.4g} s, "
                 f"more than its size ({extent * 1e3:.3g} mm)")
    else:
        return
    error = StabilityError(
        f"{what}: {cause}: the {n_fixed} fixed vertices of the [{section}] section do not "
        f"hold the body in motion; clamp a larger patch ({section}.tolerance) or another side "
        f"({section}.axis, {section}.side)")
    error.reached = time
    raise error


def release_state(model: FEModel, fixed: np.ndarray, displacement: np.ndarray,
                  watched: np.ndarray, static_sag: float | None) -> str:
    """What a release's state (``displacement`` (N, 3) at the vertices [m]) shows, for the
    message of a release that failed from it: how far the body has moved against its static
    sag, and the most compressed tet (:func:`forcecal.fe_failures.crushed_tet`)."""
    moved = largest_displacement(displacement[watched])
    said = [f"the body has moved by {moved * 1e3:.3g} mm"
            + (f" ({moved / static_sag:.2g} x its static sag)" if static_sag else "")]
    crushed = crushed_tet(model.mesh, displacement, fixed, tet_quality(model.mesh))
    if crushed:
        said.append(f"on the FE mesh, {crushed}")
    return "; ".join(said)
