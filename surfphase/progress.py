"""Progress lines with elapsed time and an ETA, for the long stages' job logs.

Each finished item prints one line ``<what> k/N, <detail>, elapsed 1m05s, ETA 2m10s``. The
ETA is the mean duration of the latest items (at most :data:`ETA_WINDOW`) times the
items left: a fit's first frame (with densification) takes several times as long as
the later ones, so the mean over every item would overestimate what is left.
"""

from __future__ import annotations

import time
from collections.abc import Callable

ETA_WINDOW = 5  # items whose mean duration predicts the rest


def format_seconds(s: float) -> str:
    """``42s``, ``3m05s``, ``2h07m`` (seconds → a short human duration)."""
    s = max(0.0, float(s))
    if s < 60:
        return f"{s:.0f}s"
    if s < 3600:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"


class Progress:
    """Counts finished items of a known total and reports elapsed time and ETA.

    Args:
        total: number of items this run will do (frames, steps, windows).
        what: label printed before the count, e.g. ``"fit session01: frame"``.
        log: where lines go (``print`` by default, flushed); ``None`` keeps them quiet.
        clock: seconds, monotonic (a parameter so tests can drive it).
        offset: items done before this run (a resumed fit): counted in the line, not in
            the ETA.
    """

    def __init__(
        self,
        total: int,
        what: str,
        log: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        offset: int = 0,
    ):
        self.total, self.what, self.clock, self.offset = int(total), what, clock, int(offset)
        self.log = log if log is not None else (lambda line: print(line, flush=True))
        self.done = 0
        self.start = self.last = clock()
        self.recent: list[float] = []

    def eta(self) -> float | None:
        """Seconds still to go, from the latest items' mean duration (None before any)."""
        if not self.recent:
            return None
        return sum(self.recent) / len(self.recent) * max(self.total - self.done, 0)

    def step(self, detail: str = "", n: int = 1) -> str:
        """Mark ``n`` more items done; log and return the progress line."""
        now = self.clock()
        self.done += n
        self.recent = (self.recent + [(now - self.last) / max(n, 1)])[-ETA_WINDOW:]
        self.last = now
        eta = self.eta()
        line = f"{self.what} {self.done + self.offset}/{self.total + self.offset}"
        if detail:
            line += f", {detail}"
        line += f", elapsed {format_seconds(now - self.start)}"
        if self.done < self.total and eta is not None:
            line += f", ETA {format_seconds(eta)}"
        self.log(line)
        return line
