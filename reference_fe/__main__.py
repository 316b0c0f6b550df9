"""CLI: ``python -m reference_fe --scene FILE --out PATH [--no-progress] [--problem FILE]``.

Also under ``mpirun -n K``: the work items are shared between the ranks.
"""
from __future__ import annotations

import argparse
import logging
import sys

from forcecal.errors import DataFileError, ForcecalError
from forcecal.failures import collective, run_command
from forcecal.logs import configure_logging


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reference_fe",
                                     description="compute a scene's FE reference (reference.h5)")
    parser.add_argument("--scene", required=True, help="scene TOML file")
    parser.add_argument("--out", required=True, help="reference.h5 to write")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--problem", help="HDF5 file of the scene's mesh and test points "
                        "(forcecal.h5io.write_problem; default: built from the scene)")
    args = parser.parse_args(argv)

    return run_command(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    from mpi4py import MPI

    import h5py

    from forcecal.h5io import check_output_file, read_problem
    from forcecal.scene import load_scene
    from reference_fe.run import compute_reference

    rank = MPI.COMM_WORLD.rank
    configure_logging(logging.INFO if rank == 0 else logging.WARNING, prefix=f"[rank {rank}] ")
    try:
        scene = load_scene(args.scene)
        check_output_file(args.out)  # before any FE work: not a directory, parent writable
        problem = None
        if args.problem is not None:
            try:
                with h5py.File(args.problem, "r") as fh:
                    problem = read_problem(fh)
            except OSError as exc:
                raise DataFileError(f"cannot read the problem file {args.problem}: {exc}"
                                    ) from None
    except ForcecalError as exc:  # every rank reads the same files
        raise collective(exc) from None
    compute_reference(scene, problem, out_path=args.out, progress=not args.no_progress)
    return 0


if __name__ == "__main__":
    sys.exit(main())
