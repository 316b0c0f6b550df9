"""Content-addressed stage cache: a stage reruns only when something it reads has changed.

A stage's *inputs* are recorded as fingerprints (:class:`StageInputs`):

* ``scene``: ``Scene.fingerprint(section)`` of every scene section the stage reads;
* ``mesh``: the mesh fingerprint (only for the stage that reads the mesh itself,
  the FE reference; later stages read the mesh back from ``reference.h5``);
* ``upstream``: SHA-256 of the content of every upstream file it reads;
* ``code``: the code fingerprint of the code the stage declares, per file
  (:class:`forcecal.provenance.CodeDependencies`: editing a module outside it
  does not invalidate it; comments, formatting and docstrings are left out).

After a successful run :meth:`Cache.store` writes ``<out>/cache/<stage>.json``
with those inputs and the content hash of every output file. :meth:`Cache.check`
compares the current inputs and outputs with that record and returns the list
of reasons to rerun (empty = up to date), e.g. ``["scene [material] changed",
"output params.h5 is missing"]``. Outputs are hashed too, so a file deleted or
replaced by hand is noticed.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from forcecal.h5io import atomic_path
from forcecal.provenance import file_digest

log = logging.getLogger(__name__)

RECORD_VERSION = 3


@dataclass(frozen=True)
class StageInputs:
    """Fingerprints of everything a stage reads (see module docstring)."""
    scene: dict[str, str] = field(default_factory=dict)
    mesh: str | None = None
    upstream: dict[str, str] = field(default_factory=dict)
    code: dict[str, str] = field(default_factory=dict)

    def changes_from(self, old: dict[str, Any]) -> list[str]:
        """Human-readable differences between these inputs and a stored record's ``old``."""
        reasons = [f"scene [{k}] changed" for k in sorted(self.scene)
                   if old.get("scene", {}).get(k) != self.scene[k]]
        if self.mesh != old.get("mesh"):
            reasons.append("mesh changed")
        reasons += [f"{k} changed" for k in sorted(self.upstream)
                    if old.get("upstream", {}).get(k) != self.upstream[k]]
        old_code = old.get("code", {})
        changed = sorted(set(self.code) ^ set(old_code)
                         | {k for k in self.code if old_code.get(k) != self.code[k]})
        if changed:
            shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more"
                                              if len(changed) > 5 else "")
            reasons.append(f"code changed: {shown}")
        return reasons


class Cache:
    """The cache records of one output folder (``<out>/cache/<stage>.json``)."""

    def __init__(self, out: str | Path) -> None:
        self.out = Path(out)
        self.folder = self.out / "cache"

    def record_path(self, stage: str) -> Path:
        return self.folder / f"{stage}.json"

    def load(self, stage: str) -> dict[str, Any] | None:
        """The stored record of ``stage``, or None if there is none (or it is unreadable)."""
        path = self.record_path(stage)
        if not path.is_file():
            return None
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            log.warning("ignoring unreadable cache record %s: %s", path, exc)
            return None
        return record if record.get("version") == RECORD_VERSION else None

    def check(self, stage: str, inputs: StageInputs) -> list[str]:
        """Reasons why ``stage`` must run (empty list = its recorded outputs are up to date)."""
        record = self.load(stage)
        if record is None:
            return ["no cache record"]
        reasons = inputs.changes_from(record.get("inputs", {}))
        for name, digest in record.get("outputs", {}).items():
            path = self.out / name
            if not path.is_file():
                reasons.append(f"output {name} is missing")
            elif digest != file_digest(path):
                reasons.append(f"output {name} was modified")
        return reasons

    def store(self, stage: str, inputs: StageInputs, outputs: list[str], elapsed: float,
              note: str = "") -> None:
        """Record a successful run of ``stage`` (written atomically)."""
        record = {"version": RECORD_VERSION, "stage": stage, "inputs": asdict(inputs),
                  "outputs": {n: file_digest(self.out / n) for n in outputs},
                  "elapsed_s": elapsed, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "note": note}
        with atomic_path(self.record_path(stage)) as tmp:
            tmp.write_text(json.dumps(record, indent=1, sort_keys=True))

    def elapsed(self, stage: str) -> float | None:
        """Wall time [s] of the recorded run of ``stage``, if any."""
        record = self.load(stage)
        return None if record is None else record.get("elapsed_s")
