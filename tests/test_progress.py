"""Progress lines: every 10 % off a terminal, with the time left at the pace so far."""

import io

from twinfocus.jobs.progress import Progress, remaining_text


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_progress_lines_estimate_what_remains(monkeypatch):
    clock = Clock()
    monkeypatch.setattr("twinfocus.jobs.progress.time.perf_counter", clock)
    out = io.StringIO()
    p = Progress("batch", stream=out)
    for done in range(1, 11):
        clock.t = 12.0 * done  # 12 s an item
        p(done, 10)
    lines = out.getvalue().splitlines()
    assert lines[0] == "[batch]  10.0%   12.0s, about 2 min left"  # 9 items of 12 s: 108 s
    assert lines[4] == "[batch]  50.0%   60.0s, about 60 s left"
    assert lines[-1] == "[batch] 100.0%  120.0s"  # done: nothing left to estimate
    assert len(lines) == 10


def test_remaining_text_reads_as_a_person_would_say_it():
    assert remaining_text(42.4) == "42 s"
    assert remaining_text(600) == "10 min"
    assert remaining_text(2 * 3600) == "2.0 h"
