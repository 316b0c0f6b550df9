"""Command-line entry point of forcecal's pipelines."""
from __future__ import annotations

import argparse
import logging
import sys

from forcecal.errors import ForcecalError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipelines",
                                     description="forcecal pipelines")
    sub = parser.add_subparsers(dest="stage", required=True)
    sub.add_parser("scene-keys", help="print the Markdown table of every scene key")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.stage == "scene-keys":
            from forcecal.scene import keys_table
            print(keys_table())
            return 0
    except ForcecalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 1
