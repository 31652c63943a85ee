"""Work on this machine's cores: units of work shared out to worker processes one at a time,
each finished item reported to the parent as it finishes, and a stop within a bound of time.

`run_in_processes` starts ``processes`` workers (the ``spawn`` start method: a fresh
interpreter each, as safe with threads and torch as it gets). Each worker builds its state
once (``setup(*args)``, e.g. a renderer with its town and layers), then takes the next unit not
taken yet (a shared counter: the fast workers take more, and none waits on a slow one) and
calls ``work(unit, report)``, which calls ``report(item)`` after each item it finishes (a
frame); the parent hears of each item at once (``on_item``: a progress bar that moves per
frame, with one worker as with many).

Stopping: Ctrl-C reaches the parent only (the workers ignore SIGINT). The parent asks every
worker to stop after the item in flight, waits at most ``grace`` seconds for them (the items
they finish meanwhile are reported), then ends those still working (SIGTERM) and removes
their temporaries (``cleanup``). The files of the items they dropped are either whole or not
there: the callers write atomically (`omniscape_torch.io.atomic`: a temporary renamed onto
the file), so the files of an item interrupted halfway are a temporary (removed) and whole
files without the item's marker (an unfinished item, done again by the next run). A worker
whose ``work`` raises has its error raised in the parent, once the others have finished the
item in flight; a worker that dies (killed, out of memory) is reported as a
`WorkerDied` error.
"""

from __future__ import annotations

import os
import pickle
import queue
import signal
import sys
import time
import traceback
from multiprocessing import get_context
from typing import Any, Callable, Sequence

__all__ = ["GRACE_S", "WorkerDied", "run_in_processes"]

#: Seconds the workers get, after Ctrl-C, to finish the item in flight before they are ended.
#: With the ending of the workers (0.1-0.3 s) and of the parent's interpreter (torch's
#: teardown: 0.1 s on an idle machine, 0.6-1.0 s measured on 2 cores at a load of 5), Ctrl-C
#: is honoured within 2 s.
GRACE_S = 0.5

#: Seconds between the parent's checks that its workers are alive while it waits for reports.
_POLL_S = 0.1


class WorkerDied(RuntimeError):
    """A worker process ended without finishing its share (killed, or out of memory)."""


class _RemoteTraceback(Exception):
    """A worker's traceback, as the cause of the error raised again in the parent."""

    def __init__(self, text: str):
        super().__init__(text)
        self.text = text

    def __str__(self) -> str:
        return self.text


class _Stopped(Exception):
    """Raised by ``report`` in a worker asked to stop: the unit's other items are left."""


def _next_unit(counter, count: int) -> int | None:
    with counter.get_lock():
        i = counter.value
        if i >= count:
            return None
        counter.value = i + 1
    return i


def _worker(setup: Callable, args: tuple, units: Sequence, counter, results, stop) -> None:
    """A worker process: build the state, then take units until none is left or stopped."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the parent's to handle
    pid = os.getpid()

    def report(item) -> None:
        results.put(("item", item))
        if stop.is_set():
            raise _Stopped

    try:
        work = setup(*args)
        while not stop.is_set():
            i = _next_unit(counter, len(units))
            if i is None:
                break
            work(units[i], report)
    except _Stopped:
        pass
    except BaseException as err:   # noqa: BLE001 - handed to the parent, which raises it
        try:
            payload = pickle.dumps(err)
            pickle.loads(payload)
        except Exception:   # noqa: BLE001 - an error that does not pickle: its text only
            payload = None
        results.put(("error", payload, f"{type(err).__name__}: {err}",
                     "".join(traceback.format_exception(err))))
    results.put(("end", pid))
    # the reports flushed, end at once, as a forked worker does: the interpreter's teardown
    # (collecting torch's object graph) takes 0.1-1 s for nothing (the files are written)
    results.close()
    results.join_thread()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _error(message: tuple) -> BaseException:
    """The error a worker sent, with its traceback as the cause."""
    _, payload, text, tb = message
    err = None
    if payload is not None:
        try:
            err = pickle.loads(payload)
        except Exception:   # noqa: BLE001 - raised below as text
            err = None
    if err is None:
        err = RuntimeError(text)
    err.__cause__ = _RemoteTraceback(tb)
    return err


def run_in_processes(setup: Callable[..., Callable[[Any, Callable[[Any], None]], Any]],
                     args: tuple, units: Sequence, processes: int,
                     on_item: Callable[[Any], None] = lambda item: None, *,
                     grace: float = GRACE_S,
                     cleanup: Callable[[list[int]], None] = lambda pids: None) -> None:
    """Run every unit of ``units`` in ``processes`` worker processes.

    Args:
        setup: a module-level function (picklable), called once in each worker as
            ``setup(*args)``; returns ``work(unit, report)``, which does one unit and calls
            ``report(item)`` after each item of it that is finished (``report`` raises, to
            end ``work``, in a worker asked to stop).
        args: ``setup``'s arguments (picklable).
        units: the units (picklable), each done once by one worker, in order of start.
        processes: how many workers (at least 1; no more start than there are units).
        on_item: called in the parent with each item a worker reports, as it arrives.
        grace: seconds the workers get to finish their item in flight once the parent
            stops (Ctrl-C, an error), before those still working are ended.
        cleanup: called in the parent with the process ids of the workers it ended (their
            temporaries to remove), once they are gone.

    Raises:
        KeyboardInterrupt: Ctrl-C in the parent, after the workers are stopped (within
            ``grace`` seconds and the time to end them).
        WorkerDied: a worker ended without finishing (its exit code in the message).
        Exception: the first error a worker's ``setup`` or ``work`` raised, as it raised it
            (its traceback as the cause), once the other workers have finished their item
            in flight.
    """
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes: expected a positive integer, got {processes!r}")
    units = list(units)
    if not units:
        return
    ctx = get_context("spawn")
    counter, results, stop = ctx.Value("l", 0), ctx.Queue(), ctx.Event()
    procs = [ctx.Process(target=_worker, args=(setup, args, units, counter, results, stop),
                         daemon=True) for _ in range(min(processes, len(units)))]
    ended: set[int] = set()
    error: tuple | None = None

    def receive(timeout: float) -> bool:
        """Handle one report; False when none came within ``timeout`` seconds."""
        nonlocal error
        try:
            message = results.get(timeout=timeout)
        except queue.Empty:
            return False
        if message[0] == "item":
            on_item(message[1])
        elif message[0] == "error":
            if error is None:
                error = message
            stop.set()
        else:
            ended.add(message[1])
        return True

    try:
        for p in procs:
            p.start()
        while len(ended) < len(procs):
            if receive(_POLL_S):
                continue
            dead = [p for p in procs if p.pid not in ended and p.exitcode not in (None, 0)]
            if dead:
                raise WorkerDied(f"a worker process ended without finishing its frames (exit "
                                 f"code {dead[0].exitcode}: killed, or out of memory?)")
        if error is not None:
            raise _error(error)
    except BaseException:
        stop.set()
        deadline = time.monotonic() + grace
        try:
            while len(ended) < len(procs) and time.monotonic() < deadline and any(
                    p.is_alive() for p in procs if p.pid not in ended):
                receive(min(_POLL_S, max(0.0, deadline - time.monotonic())))
        except BaseException:   # noqa: BLE001 - a second Ctrl-C: end them now
            pass
        killed = [p.pid for p in procs if p.pid is not None and p.is_alive()
                  and p.pid not in ended]
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            if p.pid is not None:
                p.join()
        if killed:
            cleanup(killed)
        raise
    finally:
        for p in procs:
            if p.pid is not None:
                p.join()
        results.close()
        results.join_thread()
