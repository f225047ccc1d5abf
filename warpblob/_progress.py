"""Progress bars that show only on a terminal."""

from __future__ import annotations

import sys


def progress(iterable, *, desc: str, total: int | None = None, mininterval: float = 0.1):
    """Wrap ``iterable`` in a tqdm bar when stderr is a TTY, else return it unchanged
    (``mininterval``: seconds between redraws; 0 draws every step)."""
    if not sys.stderr.isatty():
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, leave=False, mininterval=mininterval)
