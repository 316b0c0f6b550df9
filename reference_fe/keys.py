"""What each FE experiment depends on: its key, which decides whether a stored result is reused.

Free of dolfinx, so the pipeline can ask "does this ``reference.h5`` already hold
what the scene wants?" without initialising MPI.

An experiment's key is the SHA-256 of the scene sections it reads
(:data:`~forcecal.sections.COMMON_SECTIONS` plus its
:data:`~forcecal.sections.EXPERIMENT_SECTIONS`), the mesh fingerprint and the
FE code fingerprint (:data:`forcecal.provenance.FE`: this package and the shared
modules it reads). The scene's ``experiments`` list
is not part of it (but for an experiment that runs more with another one asked for,
:data:`~forcecal.sections.EXPERIMENT_OPTIONS`): asking for one more experiment leaves the keys
of the others unchanged, so their stored results are reused (the work items'
checkpoint parts and the experiments of an earlier ``reference.h5``; see
:func:`reference_fe.run.compute_reference`).
"""

from __future__ import annotations

from forcecal.provenance import FE, json_digest, section_fingerprint
from forcecal.scene import EXPERIMENTS, Scene
from forcecal.sections import COMMON_SECTIONS, EXPERIMENT_OPTIONS, EXPERIMENT_SECTIONS


def experiment_keys(scene: Scene, mesh_fingerprint: str) -> dict[str, str]:
    """``{experiment: key}`` for every experiment of :data:`~forcecal.scene.EXPERIMENTS`
    (also those the scene does not ask for: a stored one may still be reused)."""
    code = FE.digest()

    def identity(e: str) -> dict:
        out = {"experiment": e, "mesh": mesh_fingerprint, "code": code,
               "scene": section_fingerprint(scene, *COMMON_SECTIONS, *EXPERIMENT_SECTIONS[e])}
        if e in EXPERIMENT_OPTIONS:
            out["with"] = [o for o in EXPERIMENT_OPTIONS[e] if o in scene.experiments]
        return out

    return {e: json_digest(identity(e)) for e in EXPERIMENTS}
