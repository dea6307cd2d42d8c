"""The progress bar of the demo and the bag commands: tqdm on stderr, drawn only in a terminal.

In a terminal the bar is redrawn in place, at tqdm's pace (at most ten times a
second).  When stderr is not a terminal -- a log file, a pipe, CI -- nothing is
drawn: every redraw would add a carriage-return update to the log, and each
command prints what it did when it is done.
"""

from __future__ import annotations

import sys

from tqdm import tqdm


def progress_bar(total: int, enabled: bool = True) -> tqdm:
    """A bar counting ``total`` pings on stderr (advance it with ``update(n)``, end it with ``close()``).

    Drawn when ``enabled`` and stderr is a terminal; otherwise a bar that draws
    nothing, so callers update and close it alike.
    """
    return tqdm(total=total, desc="pings", unit="ping", file=sys.stderr, disable=None if enabled else True)
