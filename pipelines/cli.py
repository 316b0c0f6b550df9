"""Command-line entry point of forcecal's pipelines.

``python -m pipelines <stage> --scene FILE [--out DIR] [--force] [--no-progress] [--ranks K]``
with stages ``reference``, ``calibrate``, ``gravity``, ``report`` (each brings the
stages before it up to date first, like make) and ``demo`` (all of them).
``python -m pipelines scene-keys`` prints the table of scene keys (``docs/scenes.md``);
``python -m pipelines docs`` rewrites every generated table of ``README.md`` and ``docs/``
from the committed results (:mod:`pipelines.docs`).
``python -m pipelines export --params runs/<scene>/params.h5 --out DIR`` writes the
calibrated model as VTU and JSON (:mod:`pipelines.export`, ``docs/export.md``).
``report`` and ``demo`` end with the verdict table (``report.json`` ``verdict``); with
``--require-pass`` they exit with :data:`EXIT_VERDICT_FAILED` (3) when the verdict failed
and 0 when it passed (a CI job gates on it; under MPI rank 0 reads the verdict and every
rank returns its code). Every command ends through :func:`forcecal.failures.run_command`:
one ``error:`` line and exit code 2 on any failure, exit code 130 on Ctrl-C.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from forcecal.errors import DataFileError, ForcecalError
from forcecal.failures import collective, run_command
from forcecal.logs import configure_logging

STAGE_COMMANDS = {"reference": "reference", "calibrate": "calibrate", "gravity": "gravity",
                  "report": "report", "demo": "report"}
#: exit code of ``--require-pass`` when the verdict failed (2 stays "error")
EXIT_VERDICT_FAILED = 3


def default_out(scene_name: str) -> Path:
    """``runs/<scene name>/`` under the current directory."""
    return Path("runs") / scene_name


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text}: must be >= 1")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pipelines",
                                     description="forcecal pipelines: FE reference -> "
                                     "calibration -> gravity comparison -> report")
    sub = parser.add_subparsers(dest="stage", required=True)
    sub.add_parser("scene-keys", help="print the Markdown table of every scene key")
    p = sub.add_parser("results-table", help="print a report's results tables (docs/results.md)")
    p.add_argument("report", help="report.json")
    p = sub.add_parser("verdict-table", help="print a report's verdict table (docs/verdict.md)")
    p.add_argument("report", help="report.json")
    p = sub.add_parser("bench-table", help="print the benchmark goals table (docs/benchmarks.md)")
    p.add_argument("bench", help="bench.json")
    p = sub.add_parser("export", help="write a calibrated model (params.h5) as VTU for "
                       "ParaView and JSON for another engine (docs/export.md)")
    p.add_argument("--params", required=True, help="params.h5 of a calibration")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--variant", default="calibrated",
                   help="parameter set: calibrated (default), global or baseline")
    from pipelines.docs import add_arguments as docs_arguments
    docs_arguments(sub.add_parser("docs", help="rewrite every generated table of README.md and "
                                  "docs/ from runs/ (--check: only list the stale pages)"))
    from pipelines.bench.driver import add_arguments as bench_arguments
    bench_arguments(sub.add_parser("bench", help="speed and error benchmarks (make bench; "
                                   "--full: make bench-full)"))
    from pipelines.corpus import add_arguments as corpus_arguments
    corpus_arguments(sub.add_parser("corpus", help="every scenes/corpus/*.toml through the "
                                    "pipeline, one process each (make corpus)"))
    helps = {"reference": "FE reference (reference.h5)",
             "calibrate": "calibrate the particle model (params.h5); runs reference if needed",
             "gravity": "particle gravity runs (gravity.h5); runs earlier stages if needed",
             "report": "report.json, figures, XDMF fields; runs earlier stages if needed",
             "demo": "every stage for the scene"}
    for name, text in helps.items():
        p = sub.add_parser(name, help=text)
        p.add_argument("--scene", required=True, help="scene TOML file")
        p.add_argument("--out", help="output folder (default: runs/<scene name>/)")
        p.add_argument("--force", action="store_true",
                       help=f"rerun {'every stage' if name == 'demo' else 'this stage'} even if "
                       "its cache says it is up to date")
        p.add_argument("--no-progress", action="store_true", help="no progress bars")
        p.add_argument("--verbose", action="store_true",
                       help="log every optimiser iteration of the calibration, the "
                       "traceback of a failure and mpirun's own text")
        p.add_argument("--ranks", type=_positive_int, default=2,
                       help="MPI ranks of the FE reference when not already under mpirun "
                       "(1 = in-process; default 2)")
        if name in ("report", "demo"):
            p.add_argument("--require-pass", action="store_true",
                           help=f"exit with code {EXIT_VERDICT_FAILED} when the verdict "
                           "(report.json) failed, 0 when it passed (for CI)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    return run_command(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    if args.stage == "scene-keys":
        from forcecal.scene import keys_table
        print(keys_table())
        return 0
    if args.stage == "results-table":
        from pipelines.report import read_report, results_markdown
        print(results_markdown(read_report(args.report)))
        return 0
    if args.stage == "verdict-table":
        from pipelines.docs import report_verdict
        from pipelines.report import read_report
        from pipelines.verdict import verdict_markdown
        verdict, judged_now = report_verdict(read_report(args.report))
        if judged_now:  # written before it: its measurements, the default goals
            print(f"(judged now from the measurements of {args.report}, which has no verdict, "
                  "against the default [verdict] goals)\n")
        print(verdict_markdown(verdict))
        return 0
    if args.stage == "bench-table":
        from pipelines.bench.driver import read_bench
        from pipelines.bench.report import goals_markdown
        print(goals_markdown(read_bench(args.bench)))
        return 0
    if args.stage == "export":
        from calibration.loading import load_calibrated
        from pipelines.export import export_model
        calibrated = load_calibrated(args.params, args.variant)
        for path in export_model(calibrated, args.out):
            print(f"wrote {path}")
        return 0
    if args.stage == "docs":
        from pipelines.docs import main as docs_main
        return docs_main(args)
    if args.stage == "bench":
        from pipelines.bench.driver import main as bench_main
        configure_logging(logging.INFO)
        return bench_main(args)
    if args.stage == "corpus":
        from pipelines.corpus import main as corpus_main
        return corpus_main(args)
    from calibration.pool import mpi_world
    from forcecal.scene import load_scene
    from pipelines.stages import ORDER, run_pipeline
    comm = mpi_world()
    rank = 0 if comm is None else comm.Get_rank()
    # INFO on rank 0, warnings only on the other MPI ranks
    configure_logging(logging.INFO if rank == 0 else logging.WARNING)
    if args.verbose:  # tracebacks of failures, mpirun's own text
        for name in ("forcecal.failures", "pipelines.stages"):
            logging.getLogger(name).setLevel(logging.DEBUG)
    try:
        scene = load_scene(args.scene)
    except ForcecalError as exc:  # every MPI rank reads the same file
        raise collective(exc) from None
    out = Path(args.out) if args.out else default_out(scene.name)
    until = STAGE_COMMANDS[args.stage]
    force = (ORDER if args.stage == "demo" else (until,)) if args.force else ()
    outcomes = run_pipeline(scene, out, until=until, force=force,
                            progress=not args.no_progress, ranks=args.ranks,
                            verbose=args.verbose)
    code = 0
    if rank == 0:
        for o in outcomes:
            print(f"{o.stage:<10} {'ran' if o.ran else 'skipped':<8} "
                  f"{o.seconds:8.1f} s  {'; '.join(o.reasons) or 'up to date'}")
        print(f"outputs in {out}/")
        if until == "report":
            code = _print_verdict(out, getattr(args, "require_pass", False))
    if comm is not None:  # rank 0 decides; every rank ends with its code
        code = comm.bcast(code, root=0)
    return code


def _print_verdict(out: Path, require_pass: bool) -> int:
    """Print the verdict table of ``out``'s report; the exit code ``--require-pass`` asks for."""
    from pipelines.realtime import realtime_line
    from pipelines.report import read_report
    from pipelines.verdict import verdict_text
    report = read_report(out / "report.json")
    if "verdict" not in report:
        raise DataFileError(f"{out / 'report.json'} has no verdict (written before it); rerun "
                            "the report stage (--force)")
    print()
    print(verdict_text(report["verdict"]))
    print(realtime_line(report.get("realtime")))
    return EXIT_VERDICT_FAILED if require_pass and not report["verdict"]["passed"] else 0
