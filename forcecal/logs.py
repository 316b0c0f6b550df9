"""Logging set-up shared by every command line of the project.

One stderr handler: the project's own loggers at the level asked for, other
libraries' records only from WARNING up. The filter sits on the handler, not
on the root logger's level, because FFCx's JIT build of a form sets the root
logger to INFO (cffi's distutils verbosity) in the middle of a run, which would
otherwise print every gcc command line of a cold form cache.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable

from forcecal import PROJECT_PACKAGES


class _ProjectRecords(logging.Filter):
    """Pass the project's records and everybody's warnings and errors."""

    def filter(self, record: logging.LogRecord) -> bool:
        return (record.levelno >= logging.WARNING
                or record.name.partition(".")[0] in PROJECT_PACKAGES)


def configure_logging(level: int = logging.INFO, *, prefix: str = "",
                      loggers: Iterable[str] = PROJECT_PACKAGES) -> None:
    """Send log records to stderr as ``<prefix><LEVEL> <logger>: <message>``.

    Args:
        level: level of the named ``loggers`` (the other project loggers stay at WARNING).
        prefix: text in front of every line (e.g. ``"[rank 1] "`` under MPI).
        loggers: project loggers set to ``level``.
    """
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(f"{prefix}%(levelname)s %(name)s: %(message)s"))
    handler.addFilter(_ProjectRecords())
    # force=True: importing FFCx may have configured the root logger already
    logging.basicConfig(level=logging.WARNING, handlers=[handler], force=True)
    for name in PROJECT_PACKAGES:
        logging.getLogger(name).setLevel(logging.WARNING)
    for name in loggers:
        logging.getLogger(name).setLevel(level)
