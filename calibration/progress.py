"""Progress bars of the calibration phases (tqdm on a terminal, silent otherwise)."""

from __future__ import annotations

import sys
from typing import Callable

from tqdm import tqdm


def progress_bar(desc: str, total: int, enabled: bool, initial: int = 0) -> tqdm:
    """A tqdm bar on stderr, disabled when ``enabled`` is False or stderr is not a terminal."""
    return tqdm(total=total, initial=initial, desc=desc, leave=False, dynamic_ncols=True,
                disable=not (enabled and sys.stderr.isatty()))


def cost_ticker(bar: tqdm) -> Callable[[float], None]:
    """Callback advancing ``bar`` by one evaluation and showing the best cost so far."""
    def tick(best_cost: float) -> None:
        bar.update(1)
        bar.set_postfix_str(f"cost {best_cost:.4g} N^2", refresh=False)
    return tick
