"""Progress lines of ``isolume chart``, on stderr (the charts' files and summary go to
stdout)."""

from __future__ import annotations

import sys


def say(text: str) -> None:
    """Print ``chart: TEXT`` on stderr at once."""
    print(f"chart: {text}", file=sys.stderr, flush=True)
