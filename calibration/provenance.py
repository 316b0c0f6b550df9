"""What a calibration depends on and what produced it: input fingerprints and software versions.

* :func:`fit_inputs`: the fingerprints a calibration's result is a function of
  (the reference file, the scene sections the fit reads, the forcecal version
  and the fit's code); the checkpoint is keyed on them, so a changed input never
  resumes a stale fit (:class:`calibration.checkpoint.Checkpoint`);
  :func:`checkpoint_inputs` is that key, assembled in one place.
* :func:`versions`: the software that produced a ``params.h5``, with the git
  commit of the checkout (or None outside one).
"""

from __future__ import annotations

import platform
from pathlib import Path
from typing import Sequence

import numpy as np

import forcecal
from forcecal.provenance import FIT, CodeDependencies, file_digest, git_commit, json_digest
from forcecal.scene import Scene
from forcecal.sections import FIT_SECTIONS

#: settings that change how fast a fit runs, not its result
NOT_RESULT_SETTINGS = ("workers",)


def fit_settings(scene: Scene) -> dict[str, dict]:
    """The scene sections a calibration reads, as plain dicts (recorded in ``params.h5``)."""
    settings = {s: scene.section_dict(s) for s in FIT_SECTIONS}
    # the model the fit fits (the rest of [particle] is about the explicit runs, not the fit);
    # the volume element only when it is not the per-tet default (absent: "tet"), so the
    # settings of a per-tet fit, and the checkpoints and files compared with them, stay as
    # they were
    settings["model"] = {"particle.volume": scene.particle.volume}
    if scene.particle.volume_element != "tet":
        settings["model"]["particle.volume_element"] = scene.particle.volume_element
    return settings


def code_fingerprint(code: CodeDependencies = FIT) -> str:
    """Code fingerprint of a fit (:data:`forcecal.provenance.FIT`: the code it declares,
    without comments, formatting or docstrings, which cannot change a fit)."""
    return code.digest()


def fit_inputs(scene: Scene, reference_path: str | Path) -> dict[str, str]:
    """Fingerprints of everything a calibration's result depends on.

    Keys: ``reference`` (the file's SHA-256), ``scene [<section>]`` for each of
    :data:`FIT_SECTIONS` (``[calibration]`` without :data:`NOT_RESULT_SETTINGS`),
    ``forcecal`` (the version) and ``code`` (:func:`code_fingerprint`).
    """
    inputs = {"reference": file_digest(reference_path)}
    for section, table in fit_settings(scene).items():
        if section == "calibration":
            table = {k: v for k, v in table.items() if k not in NOT_RESULT_SETTINGS}
        inputs[f"scene [{section}]"] = json_digest(table)
    inputs["forcecal"] = forcecal.__version__
    inputs["code"] = code_fingerprint()
    return inputs


def checkpoint_inputs(scene: Scene, reference_path: str | Path, experiments: Sequence[str],
                      whole_body: bool) -> dict[str, str]:
    """The key of a calibration's checkpoint: :func:`fit_inputs`, the ``experiments`` it fits,
    ``particle.strain_margin`` (both methods keep the springs stiff on the gravity release
    range that margin widens) and, when the fit reads the whole-body data (``whole_body``),
    ``body.load_steps``. A checkpoint whose key differs is discarded."""
    inputs = {**fit_inputs(scene, reference_path), "experiments": ",".join(experiments)}
    inputs["particle.strain_margin"] = repr(scene.particle.strain_margin)
    if whole_body:
        inputs["body.load_steps"] = repr(scene.body.load_steps)
    return inputs


def versions() -> dict[str, str | None]:
    """Software versions of a calibration run (``mpi4py`` None when it is not installed)."""
    import h5py
    import numba
    import scipy
    try:
        import mpi4py  # the package only: importing mpi4py.MPI would initialise MPI
        mpi = mpi4py.__version__
    except ImportError:
        mpi = None
    return {"python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "numba": numba.__version__, "h5py": h5py.__version__,
            "mpi4py": mpi, "forcecal": forcecal.__version__, "git_commit": git_commit()}
