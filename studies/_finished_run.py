"""A finished run folder, as the studies that read one take it (release levers, sag split, sag
trade-off, fold cross-validation): the scene's TOML and its folder (``runs/<scene name>``
unless given), the same command-line arguments (``--scene``, ``--run``, ``--out``), the same
files read back, the result written under ``runs/studies/`` unless told otherwise."""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from forcecal.errors import DataFileError
from forcecal.h5io import Reference, atomic_path, read_reference
from forcecal.scene import Scene, load_scene
from pipelines.runners.common import GRAVITY, PARAMS, REFERENCE


RESULTS = Path("runs") / "studies"  # where the studies' results go unless told otherwise


def study_parser(module: str, doc: str) -> argparse.ArgumentParser:
    """The parser of ``python -m <module>`` with ``--scene`` (required), ``--run`` and
    ``--out`` (:func:`write_result`); the description is the first line of ``doc``."""
    parser = argparse.ArgumentParser(prog=f"python -m {module}",
                                     description=doc.splitlines()[0])
    parser.add_argument("--scene", required=True, help="scene TOML of a finished run")
    parser.add_argument("--run", help="its run folder (default runs/<scene name>)")
    name = module.rsplit(".", 1)[-1]
    parser.add_argument("--out", type=Path, help=f"the result as JSON (default "
                        f"{RESULTS.as_posix()}/{name}_<scene name>.json)")
    return parser


def write_result(parser: argparse.ArgumentParser, out: Path | None, result: dict[str, Any]
                 ) -> Path:
    """Write a study's ``result`` (which names its ``scene``) as JSON to ``out``, by default
    ``runs/studies/<study>_<scene name>.json`` (the study named by its parser's ``prog``);
    the path written."""
    name = parser.prog.rsplit(".", 1)[-1]
    path = out if out is not None else RESULTS / f"{name}_{result['scene']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path}")
    return path


def parse_study(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """Parse ``argv`` and log the study's progress at INFO level."""
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return args


def study_main(module: str, doc: str, study, argv: list[str] | None, *,
               switch: tuple[str, str, str] | None = None) -> int:
    """``python -m <module>`` of a study of a finished run with the common arguments:
    ``study(scene, run)`` written by :func:`write_result`; exit status 0. ``switch``:
    ``(option, keyword, help)`` of one more on/off option, passed as ``study(...,
    keyword=on)``."""
    parser = study_parser(module, doc)
    if switch is not None:
        parser.add_argument(switch[0], dest="switch", action="store_true", help=switch[2])
    args = parse_study(parser, argv)
    extra = {} if switch is None else {switch[1]: args.switch}
    write_result(parser, args.out, study(args.scene, args.run, **extra))
    return 0


def run_folder(scene: Scene, run: str | Path | None) -> Path:
    """``run``, or ``runs/<scene name>`` when None."""
    return Path(run) if run is not None else Path("runs") / scene.name


@dataclass(frozen=True)
class FinishedRun:
    """The scene and the files of a finished run (``reference.h5``, ``params.h5``,
    ``gravity.h5``), read and checked by their readers."""
    scene: Scene
    folder: Path
    reference: Reference
    params: Any  # calibration.results.CalibrationResult
    gravity: Any  # pipelines.gravity.GravityRuns

    def fe_static_sag(self) -> np.ndarray:
        """(N, 3) the FE's static sag [m] of the reference; :class:`DataFileError` naming the
        folder when the reference has no gravity experiments."""
        if self.reference.gravity is None:
            raise DataFileError(f"{self.folder}: the reference has no gravity sag to compare "
                                "with")
        return self.reference.gravity.static_displacement


def finished_run(scene_path: str | Path, run: str | Path | None = None) -> FinishedRun:
    """Read the finished run of ``scene_path`` (folder ``run``, default ``runs/<name>``)."""
    from calibration import read_params
    from pipelines.gravity import read_gravity

    scene = load_scene(scene_path)
    folder = run_folder(scene, run)
    return FinishedRun(scene, folder, read_reference(folder / REFERENCE),
                       read_params(folder / PARAMS), read_gravity(folder / GRAVITY))
