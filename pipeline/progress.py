"""A tiny progress bar on stderr: ``done/total``, rate and ETA, shown only for work over a second.

Driven from the client loop (``update`` after each finished batch), so it works the same with a local
or a remote dask scheduler. On a terminal it redraws one line; otherwise it prints a line at most every
``line_interval_s`` seconds and a final line.
"""

from __future__ import annotations

import sys
import time
from types import TracebackType
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """Progress of ``total`` items (frames).

    Args:
        total: items expected (0 if unknown).
        desc: label in front of the bar.
        quiet: print nothing.
        stream: where to write (default ``sys.stderr``).
        delay_s: show nothing until this much time has passed (short work stays silent).
        line_interval_s: least time between lines when ``stream`` is not a terminal.
        unit: name of the items.
    """

    def __init__(
        self,
        total: int,
        desc: str = "",
        quiet: bool = False,
        stream: TextIO | None = None,
        delay_s: float = 1.0,
        line_interval_s: float = 10.0,
        unit: str = "frames",
    ) -> None:
        self.total = max(0, int(total))
        self.desc = desc
        self.quiet = quiet
        self.stream = stream if stream is not None else sys.stderr
        self.delay_s = delay_s
        self.unit = unit
        self.done = 0
        self._start = time.monotonic()
        self._last_draw = 0.0
        self._shown = False
        self._closed = False
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._min_interval = 0.1 if self._tty else line_interval_s

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self._start

    @property
    def rate(self) -> float:
        """Items per second so far."""
        elapsed = self.elapsed_s
        return self.done / elapsed if elapsed > 0 else 0.0

    def update(self, n: int = 1) -> None:
        """Count ``n`` more items done and redraw if due."""
        self.done += n
        if self.quiet or self._closed:
            return
        now = time.monotonic()
        if now - self._start < self.delay_s or now - self._last_draw < self._min_interval:
            return
        self._draw(now)

    def close(self) -> None:
        """Final line (only if the bar was shown, i.e. the work took longer than ``delay_s``)."""
        if self._closed:
            return
        self._closed = True
        if self.quiet:
            return
        if self._shown or self.elapsed_s >= self.delay_s:
            self._draw(time.monotonic())
            if self._tty:
                self.stream.write("\n")
            self.stream.flush()

    def format(self) -> str:
        """The current line, e.g. ``lidar  120/500 frames [=====     ] 24.0 frames/s  eta 16s``."""
        rate = self.rate
        prefix = f"{self.desc} " if self.desc else ""
        if self.total:
            frac = min(1.0, self.done / self.total)
            width = 20
            filled = round(frac * width)
            bar = "[" + "=" * filled + " " * (width - filled) + "]"
            left = (self.total - self.done) / rate if rate > 0 else float("inf")
            eta = f"eta {left:.0f}s" if left != float("inf") else "eta ?"
            return f"{prefix}{self.done}/{self.total} {self.unit} {bar} {rate:.1f} {self.unit}/s {eta}"
        return f"{prefix}{self.done} {self.unit} {rate:.1f} {self.unit}/s"

    def _draw(self, now: float) -> None:
        self._last_draw = now
        self._shown = True
        if self._tty:
            self.stream.write("\r\x1b[2K" + self.format())
        else:
            self.stream.write(self.format() + "\n")
        self.stream.flush()

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
