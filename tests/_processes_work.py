"""Work functions for tests/test_processes.py, importable by name in a spawned worker (each is a
``setup`` of ``run_in_processes``: called in the worker, it returns the unit's function)."""

from __future__ import annotations

import os
import time


def counting(delay: float):
    def work(unit, report):
        for item in unit:
            time.sleep(delay)
            report(item)
    return work


def failing(bad: int):
    def work(unit, report):
        for item in unit:
            if item == bad:
                raise ValueError(f"item {item} is bad")
            report(item)
    return work


def dying():
    def work(unit, report):
        os._exit(3)
    return work


def first_fast_then_stuck():
    """Item 0 at once; any other unit sleeps far past any grace."""
    def work(unit, report):
        for item in unit:
            if item != 0:
                time.sleep(60)
            report(item)
    return work
