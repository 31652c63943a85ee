"""Worker processes on one machine (``data.processes.run_in_processes``, ``generate --workers``):
each item reported as it finishes, every unit done once, a worker's error raised in the parent,
a dead worker named, and a stop (Ctrl-C) within the grace period, the workers still busy ended.

Slow: each test spawns fresh interpreters that import torch (seconds each under load)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from omniscape_torch.data.processes import WorkerDied, run_in_processes

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _processes_work as work  # noqa: E402

pytestmark = pytest.mark.slow


def test_each_item_is_reported_once_as_it_finishes():
    seen: list[tuple[float, int]] = []
    units = [[0, 1, 2], [3, 4, 5], [6], [7]]
    run_in_processes(work.counting, (0.3,), units, 2,
                     lambda item: seen.append((time.monotonic(), item)))
    assert sorted(item for _, item in seen) == list(range(8))
    # the reports arrive while the units run (a bar that moves per item), not a unit at a time:
    # the items of the first unit come 0.3 s apart
    times = {item: t for t, item in seen}
    assert times[1] - times[0] > 0.2 and times[2] - times[1] > 0.2


def test_a_workers_error_is_raised_in_the_parent_after_the_others_finish():
    seen: list[int] = []
    with pytest.raises(ValueError, match="item 3 is bad") as err:
        run_in_processes(work.failing, (3,), [[0, 1], [2, 3, 4], [5]], 2, seen.append)
    assert "item 3 is bad" in str(err.value.__cause__)   # the worker's traceback
    assert 2 in seen and 4 not in seen


def test_a_dead_worker_is_named():
    with pytest.raises(WorkerDied, match="exit code 3"):
        run_in_processes(work.dying, (), [[0], [1]], 2)


def test_a_stop_ends_the_busy_workers_within_the_grace_period():
    """Ctrl-C in the parent (here raised by its handler of the first report): the worker
    stuck on its unit is ended after ``grace`` seconds, its process id handed to ``cleanup``
    (and the other's too where it had not finished starting yet)."""
    ended: list[list[int]] = []
    start = {}

    def on_item(item):
        start["t"] = time.monotonic()
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_in_processes(work.first_fast_then_stuck, (), [[0], [1]], 2, on_item, grace=0.5,
                         cleanup=ended.append)
    assert time.monotonic() - start["t"] < 1.5
    assert len(ended) == 1 and 1 <= len(ended[0]) <= 2
