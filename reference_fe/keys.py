"""What each FE experiment depends on: its key, which decides whether a stored result is reused.

Free of dolfinx, so the pipeline can ask "does this ``reference.h5`` already hold
what the scene wants?" without initialising MPI.

An experiment's key is the SHA-256 of the scene sections it reads
(:data:`~forcecal.sections.COMMON_SECTIONS` plus its
:data:`~forcecal.sections.EXPERIMENT_SECTIONS`), the mesh fingerprint and the
FE code fingerprint (:func:`fe_code_digest`). The scene's ``experiments`` list
is not part of it: asking for one more experiment leaves the keys of the
others unchanged, so their stored results are reused (the work items'
checkpoint parts and the experiments of an earlier ``reference.h5``; see
:func:`reference_fe.run.compute_reference`).
"""

from __future__ import annotations

from forcecal.provenance import code_digest, json_digest, section_fingerprint
from forcecal.scene import EXPERIMENTS, SECTIONS, Scene
from forcecal.sections import COMMON_SECTIONS, EXPERIMENT_SECTIONS, REFERENCE_SECTIONS

#: the modules that compute the FE experiments (in-process and as ``python -m reference_fe``)
FE_ENTRIES = ("reference_fe.run", "reference_fe.__main__")


def unread_section_classes() -> frozenset[str]:
    """Names of the scene section classes the FE reference does not read (``[particle]``,
    ``[calibration]``, ``[outputs]``: every section but
    :data:`~forcecal.sections.REFERENCE_SECTIONS`)."""
    return frozenset(cls.__name__ for name, cls in SECTIONS.items()
                     if name not in REFERENCE_SECTIONS)


#: what the FE code fingerprints leave out (:func:`forcecal.provenance.code_digests`)
FE_CODE_IGNORED = {"forcecal.scene": unread_section_classes()}


def fe_code_digest() -> str:
    """Code fingerprint (:func:`forcecal.provenance.code_digest`) of :data:`FE_ENTRIES`: every
    module they import, comments, formatting and docstrings left out, and in
    ``forcecal.scene`` the classes of the sections the FE does not read
    (:func:`unread_section_classes`), whose keys cannot change its results."""
    return code_digest(*FE_ENTRIES, ignored=FE_CODE_IGNORED)


def experiment_keys(scene: Scene, mesh_fingerprint: str) -> dict[str, str]:
    """``{experiment: key}`` for every experiment of :data:`~forcecal.scene.EXPERIMENTS`
    (also those the scene does not ask for: a stored one may still be reused)."""
    code = fe_code_digest()
    return {e: json_digest({"experiment": e, "mesh": mesh_fingerprint, "code": code,
                            "scene": section_fingerprint(scene, *COMMON_SECTIONS,
                                                         *EXPERIMENT_SECTIONS[e])})
            for e in EXPERIMENTS}
