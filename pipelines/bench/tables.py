"""Markdown table cells and tables of BENCH.md (shared by the report and the study sections)."""

from __future__ import annotations

from typing import Any

import numpy as np


def cell(v: Any, digits: int = 3) -> str:
    """One table cell: ``-`` for None, yes/no, integers as they are, floats to ``digits``."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(v)
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def table(header: list[str], rows: list[list[Any]]) -> list[str]:
    """A Markdown table, one line per entry, cells through :func:`cell`."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
    return lines
