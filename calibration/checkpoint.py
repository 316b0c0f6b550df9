"""Resumable calibration: a JSON checkpoint written atomically after every step that matters.

The checkpoint is a JSON object ``{"inputs": {...}, "stages": {...}}``; ``stages``
holds one entry per finished calibration phase (the file's key keeps its
original name), exactly what the next phase needs (coordinates, costs, histories),
with floats written by ``repr`` so they read back bit for bit. ``inputs`` are
the fingerprints of everything the result depends on
(:func:`calibration.provenance.fit_inputs`: the reference file, the scene
sections the fit reads, the forcecal version, the code); a checkpoint whose
inputs differ from the current run's is discarded with a warning naming what
changed, so a changed input never resumes a stale fit. It is removed once
``params.h5`` has been written.

Why this is not the FE reference's checkpoint (``<out>.parts/``,
:class:`reference_fe.run._Parts`), though both are atomic records keyed on the
same fingerprints (:mod:`forcecal.provenance`) and written with
:func:`forcecal.h5io.atomic_path`: the FE parts are large arrays written
concurrently by several MPI ranks, one file per work item claimed without
messages, so each part carries its own key and no shared manifest is
rewritten; the calibration has one writer and small, ordered records (a phase
resumes part-way, from its last point fit) whose floats must read back bit for
bit, which one JSON file with one inputs record gives most simply.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from forcecal.errors import DataFileError
from forcecal.h5io import atomic_path

log = logging.getLogger(__name__)


class Checkpoint:
    """Key-value store of completed calibration steps, persisted at every :meth:`put`."""

    def __init__(self, path: str | Path, inputs: dict[str, str]):
        self.path = Path(path)
        self.inputs = dict(inputs)
        self.phases: dict[str, Any] = {}
        if not self.path.is_file():
            return
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError) as exc:
            log.warning("ignoring unreadable checkpoint %s (%s)", self.path, exc)
            return
        saved = data.get("inputs") if isinstance(data, dict) else None
        if not isinstance(saved, dict):
            log.warning("discarding checkpoint %s: it records no inputs (older format)",
                        self.path)
            return
        changed = [k for k in sorted(set(saved) | set(self.inputs))
                   if saved.get(k) != self.inputs.get(k)]
        if changed:
            log.warning("discarding checkpoint %s: %s changed since it was written", self.path,
                        ", ".join(changed))
            return
        self.phases = data.get("stages", {})
        log.info("resuming from checkpoint %s (completed: %s)", self.path,
                 ", ".join(self.phases) or "nothing")

    def get(self, phase: str, default: Any = None) -> Any:
        return self.phases.get(phase, default)

    def put(self, phase: str, value: Any) -> None:
        """Store ``value`` (JSON-able) under ``phase`` and write the file atomically."""
        self.phases[phase] = value
        text = json.dumps({"inputs": self.inputs, "stages": self.phases})
        try:
            with atomic_path(self.path) as tmp:
                tmp.write_text(text)
        except OSError as exc:
            raise DataFileError(f"cannot write checkpoint {self.path}: {exc}") from exc

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)
