"""Resumable calibration: a JSON checkpoint written atomically after every step that matters.

The checkpoint is a JSON object ``{"fingerprint": ..., "stages": {...}}``; the
stages store exactly what the next step needs (coordinates, costs, histories),
with floats written by ``repr`` so they read back bit for bit. A checkpoint
whose fingerprint (reference file + calibration settings) differs from the
current run's is ignored and overwritten, so a changed input never resumes a
stale fit. It is removed once ``params.h5`` has been written.
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

    def __init__(self, path: str | Path, fingerprint: str):
        self.path = Path(path)
        self.fingerprint = fingerprint
        self.stages: dict[str, Any] = {}
        if not self.path.is_file():
            return
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError) as exc:
            log.warning("ignoring unreadable checkpoint %s (%s)", self.path, exc)
            return
        if data.get("fingerprint") != fingerprint:
            log.warning("ignoring checkpoint %s: it belongs to another reference or other "
                        "calibration settings", self.path)
            return
        self.stages = data.get("stages", {})
        log.info("resuming from checkpoint %s (completed: %s)", self.path,
                 ", ".join(self.stages) or "nothing")

    def get(self, stage: str, default: Any = None) -> Any:
        return self.stages.get(stage, default)

    def put(self, stage: str, value: Any) -> None:
        """Store ``value`` (JSON-able) under ``stage`` and write the file atomically."""
        self.stages[stage] = value
        text = json.dumps({"fingerprint": self.fingerprint, "stages": self.stages})
        try:
            with atomic_path(self.path) as tmp:
                tmp.write_text(text)
        except OSError as exc:
            raise DataFileError(f"cannot write checkpoint {self.path}: {exc}") from exc

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)
