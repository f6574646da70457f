"""Progress bars of long solves (drawn only when stderr is a terminal)."""
from __future__ import annotations

import sys


def _terminal() -> bool:
    """Whether stderr is a terminal: progress bars are drawn only there (in a log file or a pipe
    they would be runs of carriage returns)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _progress_on(args) -> bool:
    return not getattr(args, "no_progress", False) and _terminal()


class SolveProgress:
    """A progress bar on stderr for one solve, fed by the solver's ``progress(done, total, unit,
    note)`` calls (``unit`` "s": seconds of a time limit, then the bar also advances between calls;
    "task": tasks started). It appears only once the solve has run for :attr:`DELAY` seconds, so
    short solves print nothing."""

    DELAY = 2.0

    def __init__(self, desc: str, enabled: bool = True):
        import threading

        self.desc, self.enabled = desc, enabled
        self.bar = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ticker = None
        self._last = (0.0, 0.0)  # (done, wall clock) of the last call, for "s" bars

    def __call__(self, done: float, total: float | None = None, unit: str = "", note: str = "") -> None:
        import time

        if not self.enabled:
            return
        with self._lock:
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc=self.desc, unit=unit or "it", delay=self.DELAY, leave=False,
                                file=sys.stderr, bar_format=None if unit != "s" else
                                "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s{postfix}")
                import threading

                self._unit, self._t0 = unit, time.monotonic()
                self._ticker = threading.Thread(target=self._tick, daemon=True)
                self._ticker.start()
            if total is not None and self.bar.total != total:
                self.bar.total = total
            self._last = (done, time.monotonic())
            if note:
                self.bar.set_postfix_str(note, refresh=False)
            self._advance(done)

    def _advance(self, value: float) -> None:
        if self.bar.total is not None:
            value = min(value, self.bar.total)
        if value > self.bar.n:
            self.bar.update(value - self.bar.n)

    def _tick(self) -> None:
        import time

        while not self._stop.wait(0.5):
            with self._lock:
                done, at = self._last
                if self._unit == "s":  # seconds of a time limit pass between the solver's calls
                    self._advance(done + time.monotonic() - at)
                elif time.monotonic() - self._t0 >= self.DELAY:  # shown, its elapsed time going, between calls
                    self.bar.refresh()
                    self.bar.last_print_t = self.bar._time()  # shown: close() clears it (tqdm counts updates only)

    def close(self) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2.0)
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> "SolveProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
