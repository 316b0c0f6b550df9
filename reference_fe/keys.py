"""What each FE experiment depends on: its key, which decides whether a stored result is reused.

Free of dolfinx, so the pipeline can ask "does this ``reference.h5`` already hold
what the scene wants?" without initialising MPI.

An experiment's key is the SHA-256 of the scene sections it reads
(:data:`COMMON_SECTIONS` plus :data:`EXPERIMENT_SECTIONS`), the mesh
fingerprint and the bytes of the FE code (every ``.py`` file of ``reference_fe``
and ``forcecal``: byte-exact, so conservative: a comment edit also discards a
stored result, which costs a rerun, never a wrong one). The scene's
``experiments`` list is not part of it: asking for one more experiment leaves
the keys of the others unchanged, so their stored results are reused (the
work items' checkpoint parts and the experiments of an earlier
``reference.h5``; see :func:`reference_fe.run.compute_reference`).
"""

from __future__ import annotations

import hashlib
import json

from forcecal.provenance import packages_digest
from forcecal.scene import EXPERIMENTS, Scene

#: scene sections every experiment reads (geometry, material, discretisation)
COMMON_SECTIONS = ("mesh", "material", "fixed", "test_points", "fe")
#: the sections each experiment reads besides :data:`COMMON_SECTIONS`
EXPERIMENT_SECTIONS = {"indentation": ("indentation",),
                       "relaxation": ("indentation", "relaxation"),  # the indenter
                       "gravity_static": ("gravity",),
                       "gravity_dynamic": ("gravity",)}
#: packages whose code computes the FE experiments
FE_PACKAGES = ("reference_fe", "forcecal")


def fe_code_digest() -> str:
    """SHA-256 over the path and bytes of every ``.py`` file of :data:`FE_PACKAGES`."""
    return packages_digest(FE_PACKAGES)


def experiment_keys(scene: Scene, mesh_fingerprint: str) -> dict[str, str]:
    """``{experiment: key}`` for every experiment of :data:`~forcecal.scene.EXPERIMENTS`
    (also those the scene does not ask for: a stored one may still be reused)."""
    code = fe_code_digest()
    out = {}
    for e in EXPERIMENTS:
        blob = json.dumps({"experiment": e, "mesh": mesh_fingerprint, "code": code,
                           "scene": scene.fingerprint(*COMMON_SECTIONS,
                                                      *EXPERIMENT_SECTIONS[e])}, sort_keys=True)
        out[e] = hashlib.sha256(blob.encode()).hexdigest()
    return out
