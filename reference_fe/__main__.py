"""CLI: ``python -m reference_fe --scene FILE --out PATH [--no-progress]``.

Also under ``mpirun -n K``: the work items are shared between the ranks.
"""
from __future__ import annotations

import argparse
import logging
import sys

from forcecal.errors import ForcecalError
from forcecal.failures import collective, run_command
from forcecal.logs import configure_logging


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reference_fe",
                                     description="compute a scene's FE reference (reference.h5)")
    parser.add_argument("--scene", required=True, help="scene TOML file")
    parser.add_argument("--out", required=True, help="reference.h5 to write")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    return run_command(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    from mpi4py import MPI

    from forcecal.h5io import check_output_file
    from forcecal.scene import load_scene
    from reference_fe.run import compute_reference

    rank = MPI.COMM_WORLD.rank
    configure_logging(logging.INFO if rank == 0 else logging.WARNING, prefix=f"[rank {rank}] ")
    try:
        scene = load_scene(args.scene)
        check_output_file(args.out)  # before any FE work: not a directory, parent writable
    except ForcecalError as exc:  # every rank reads the same file
        raise collective(exc) from None
    compute_reference(scene, out_path=args.out, progress=not args.no_progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
