"""A plain-text progress bar on stderr (no dependency), usable as the C++ progress callback."""
from __future__ import annotations

import sys
import time


class ProgressBar:
    """Call as bar(done, total). On a terminal it redraws one line; otherwise it prints a line
    every 10 %. `close()` ends the line. Silent when `enabled` is False."""

    def __init__(self, label: str = "", stream=None, enabled: bool = True, width: int = 30):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.width = width
        self.start = time.monotonic()
        self._last_decile = -1
        self._open = False
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or total <= 0:
            return
        frac = min(max(done / total, 0.0), 1.0)
        elapsed = time.monotonic() - self.start
        eta = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        filled = int(round(self.width * frac))
        text = (
            f"{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {100 * frac:5.1f}% "
            f"{done}/{total}  {elapsed:6.1f}s elapsed, ~{eta:5.1f}s left"
        )
        if self._tty:
            self.stream.write("\r" + text)
            self._open = True
            if done >= total:
                self.close()
        else:
            decile = int(10 * frac)
            if decile != self._last_decile:
                self._last_decile = decile
                self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False
