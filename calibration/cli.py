"""Command line of the calibration stage."""
from __future__ import annotations

import argparse
import logging

from forcecal.failures import run_command
from forcecal.logs import configure_logging


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m calibration",
                                     description="fit the particle model's connector parameters "
                                                 "to an FE reference and write params.h5")
    parser.add_argument("--scene", required=True, help="scene TOML file")
    parser.add_argument("--reference", required=True, help="reference.h5 of that scene")
    parser.add_argument("--out", required=True, help="params.h5 to write")
    parser.add_argument("--workers", type=int, default=None,
                        help="parallel workers (default: the scene's calibration.workers)")
    parser.add_argument("--verbose", action="store_true",
                        help="log every optimiser iteration and infeasible point")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)

    return run_command(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    from calibration.pool import mpi_world, serve_mpi
    comm = mpi_world()
    if comm is not None and comm.Get_rank() > 0:
        serve_mpi(comm)
        return 0
    configure_logging(logging.INFO)
    from forcecal.h5io import check_output_file
    check_output_file(args.out)  # before any work (and before its checkpoints/ folder)
    if args.verbose:
        logging.getLogger("forcecal.failures").setLevel(logging.DEBUG)
    from calibration.core import calibrate
    result = calibrate(args.scene, args.reference, args.out, progress=not args.no_progress,
                       verbose=args.verbose, workers=args.workers)
    print(result.summary())
    return 0
