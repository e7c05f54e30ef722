"""Progress of a long command-line run: a bar on a terminal, lines in a log file.

A tqdm bar redraws one line with carriage returns, which a log file (a cluster job's output)
shows as nothing useful, so where stderr is not a terminal the run's progress is written as
plain lines instead, one at most every :data:`PROGRESS_SECONDS` and one at the end. A frame
can take minutes (a wrong PSF model, a huge frame): a clock thread keeps the bar's elapsed time
moving and writes a line every :data:`PROGRESS_SECONDS` while no frame finishes.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import IO, Any

__all__ = ["PROGRESS_SECONDS", "Progress"]

#: Seconds between two progress lines when stderr is not a terminal.
PROGRESS_SECONDS = 30.0


def _duration(seconds: float) -> str:
    """``seconds`` as ``"42 s"``, ``"7 min"`` or ``"2.5 h"``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class Progress:
    """Frames done of ``total``: a tqdm bar on a terminal, else periodic lines.

    Parameters
    ----------
    total : int
        Frames to do.
    label : str
        What is running (the lines start with it).
    stream : file, optional
        Where to write; default ``sys.stderr``.

    Use as a context manager; :meth:`update` is the run's ``progress`` callback.
    """

    def __init__(self, total: int, label: str = "localize", stream: IO[str] | None = None):
        self.total = int(total)
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.done = 0
        self._bar: Any = None
        self._t0 = self._last = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._clock: threading.Thread | None = None

    def __enter__(self) -> Progress:
        isatty = getattr(self.stream, "isatty", None)
        if isatty is not None and isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, unit="frame", file=self.stream)
        self._clock = threading.Thread(target=self._tick, daemon=True)
        self._clock.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._clock is not None:
            self._clock.join()
        if self._bar is not None:
            self._bar.close()

    def _tick(self) -> None:
        """While the run lasts: the bar redrawn every second (its elapsed time), or a line
        every :data:`PROGRESS_SECONDS` when no frame has finished since the last one."""
        interval = 1.0 if self._bar is not None else max(PROGRESS_SECONDS, 0.05)
        while not self._stop.wait(interval):
            with self._lock:
                if self._bar is not None:
                    self._bar.refresh()
                elif time.monotonic() - self._last >= PROGRESS_SECONDS:
                    self._line()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more frames done."""
        with self._lock:
            self.done += int(n)
            if self._bar is not None:
                self._bar.update(n)
                return
            if time.monotonic() - self._last < PROGRESS_SECONDS and self.done < self.total:
                return
            self._line()

    def _line(self) -> None:
        """Write the progress line (the lock held)."""
        now = time.monotonic()
        self._last = now
        elapsed = now - self._t0
        share = self.done / max(self.total, 1)
        line = f"{self.label}: {self.done}/{self.total} frames ({share:.0%})"
        line += f", {_duration(elapsed)} elapsed"
        if 0 < self.done < self.total:
            line += f", about {_duration(elapsed * (self.total - self.done) / self.done)} left"
        self.stream.write(line + "\n")
        self.stream.flush()
