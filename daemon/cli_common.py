"""What every ``cellcal`` sub-command shares: the usage error and the progress line.

A sub-command raises :class:`UsageError` for bad usage or input found after
argument parsing (``cli`` turns it into exit status 2 with one message), and
reports progress with :func:`print_progress`, on stderr, so that with ``--json``
stdout carries the JSON object alone.
"""
from __future__ import annotations

import sys


class UsageError(Exception):
    """Bad usage or input detected after parsing; exit status 2."""


def print_progress(message: str) -> None:
    """One progress line on stderr, shown at once."""
    print(f"cellcal: {message}", file=sys.stderr, flush=True)


def check_folds(folds: int) -> None:
    """Cross-validation needs at least two folds."""
    if folds < 2:
        raise UsageError(f"--folds must be at least 2, got {folds}")
