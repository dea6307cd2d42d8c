"""A one-line progress bar on stderr, for the demo and the bag commands.

It redraws only when the percentage changes (at most about a hundred writes a
run), so a redirected stderr stays small and the bar costs nothing per item.
"""

from __future__ import annotations

import sys


class Progress:
    """``label [#####.....] done/total`` on one line of ``stream``, finished with a newline by :meth:`close`."""

    def __init__(self, label: str, total: int, width: int = 40, stream=None) -> None:
        self._label = label
        self._total = max(int(total), 1)
        self._width = width
        self._stream = sys.stderr if stream is None else stream
        self._shown = -1
        self._drawn = -1
        self._done = 0

    def update(self, done: int) -> None:
        """Show ``done`` items of the total."""
        self._done = done
        percent = min(100, 100 * done // self._total)
        if percent != self._shown:
            self._draw(percent)

    def _draw(self, percent: int) -> None:
        self._shown = percent
        self._drawn = self._done
        filled = self._width * percent // 100
        self._stream.write(f"\r  {self._label} [{'#' * filled}{'.' * (self._width - filled)}] "
                           f"{self._done}/{self._total}")
        self._stream.flush()

    def close(self) -> None:
        """Draw the last count (if not shown yet) and end the line."""
        if self._drawn != self._done:
            self._draw(min(100, 100 * self._done // self._total))
        self._stream.write("\n")
        self._stream.flush()
