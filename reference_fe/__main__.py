"""CLI: ``python -m reference_fe --scene FILE --out PATH [--no-progress]``.

Also under ``mpirun -n K``: the work items are shared between the ranks.
"""
from __future__ import annotations

import argparse
import logging
import sys

from forcecal.errors import ForcecalError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m reference_fe",
                                     description="compute a scene's FE reference (reference.h5)")
    parser.add_argument("--scene", required=True, help="scene TOML file")
    parser.add_argument("--out", required=True, help="reference.h5 to write")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    from mpi4py import MPI

    from forcecal.scene import load_scene
    from reference_fe.run import compute_reference

    rank = MPI.COMM_WORLD.rank
    # force=True: importing FFCx has already configured the root logger
    logging.basicConfig(level=logging.WARNING, format=f"[rank {rank}] %(levelname)s "
                        "%(name)s: %(message)s", force=True)
    if rank == 0:
        for name in ("forcecal", "reference_fe"):
            logging.getLogger(name).setLevel(logging.INFO)
    try:
        compute_reference(load_scene(args.scene), out_path=args.out,
                          progress=not args.no_progress)
    except ForcecalError as exc:
        if rank == 0:
            print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
