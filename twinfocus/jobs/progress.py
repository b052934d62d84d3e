"""Progress lines on stderr for long work (a bar on a terminal, a line every 10 % otherwise), with
an estimate of the time left at the pace so far."""

from __future__ import annotations

import sys
import time


class Progress:
    """Callable ``progress(done, total, *extra)``; ``extra[0]`` (e.g. a loss) is shown if given."""

    def __init__(self, label: str, stream=None, enabled: bool = True):
        self.label = label
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = getattr(self.stream, "isatty", lambda: False)()
        self.t0 = time.perf_counter()
        self._last_decile = -1
        self._last_t = 0.0

    def __call__(self, done: int, total: int, *extra) -> None:
        if not self.enabled or total <= 0:
            return
        frac = done / total
        now = time.perf_counter()
        suffix = f" {extra[0]:.4f}" if extra else ""
        if 0 < done < total:  # what remains at the pace so far
            suffix += f", about {remaining_text((now - self.t0) * (total - done) / done)} left"
        if self.tty:
            if now - self._last_t < 0.1 and done < total:
                return
            self._last_t = now
            bar = "#" * int(30 * frac)
            self.stream.write(f"\r[{self.label}] [{bar:<30}] {100 * frac:5.1f}% {now - self.t0:6.1f}s{suffix}")
            if done >= total:
                self.stream.write("\n")
        else:
            decile = int(10 * frac)
            if decile == self._last_decile and done < total:
                return
            self._last_decile = decile
            self.stream.write(f"[{self.label}] {100 * frac:5.1f}% {now - self.t0:6.1f}s{suffix}\n")
        self.stream.flush()


def remaining_text(seconds: float) -> str:
    """``"40 s"``, ``"3 min"``, ``"1.5 h"``: a duration as a person reads an estimate."""
    if seconds < 90:
        return f"{max(0.0, seconds):.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
