"""Past one machine: chunks of work as Ray tasks, and ``--shard K/N`` for other schedulers.

``generate`` and ``convert`` hand this module a plain function of their arguments and a chunk
of items (frame numbers, capture folders) that writes its files and returns what it did; the
function is the same one a local run calls, so a task writes the same bytes wherever and
however often it runs.

* `run_on_ray`: each chunk becomes a Ray task (one CPU, and the memory the caller
  estimates, so that Ray places no more tasks on a node than fit) on an existing cluster
  (``address``; ``$RAY_ADDRESS``; one ``ray start`` started on this machine) or on a local one
  started for the run and stopped after it.
  A task whose worker dies or whose body raises is run again by Ray (`RETRIES` times);
  one that still fails has each of its items reported with the error, while the other tasks
  finish. A progress bar counts the items of each task as it completes. Ray is an optional
  dependency (`RAY_INSTALL`); without it `import_ray` says how to install it.
* `shard_part`: ``--shard K/N`` for schedulers without Ray (Slurm arrays, Kubernetes
  indexed jobs, a shell loop): run ``K`` of ``N`` takes items ``K, K + N, K + 2 N, ...``, so
  the ``N`` runs take disjoint sets that together are all of them, and a longer run (more
  frames) keeps every earlier item in the same run.

What is finished is read from the files themselves (the dataset's ``.done`` markers and
manifest), not from the scheduler: a run that stopped, for whatever reason, is completed by
running the same command again.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
from typing import Any, Callable, Iterator, Sequence

__all__ = ["RAY_INSTALL", "RETRIES", "TaskErrors", "check_shard", "describe_error",
           "import_ray", "parse_shard", "ray_cluster", "run_on_ray", "shard_part",
           "split_chunks"]

#: The command that installs the optional Ray dependency (named by every error about it).
RAY_INSTALL = 'pip install -e ".[ray]"'

#: How many times Ray runs a failed task again (a dead worker or node, or an exception
#: escaping the task's function) before its items are reported as failed.
RETRIES = 2

#: The most items one task takes when the caller leaves the chunking to `split_chunks`:
#: small enough that the progress bar moves and a lost task costs little, large enough that
#: a task's start-up (Ray's dispatch, the task building its renderer) stays a small share.
MAX_CHUNK = 8


class TaskErrors(RuntimeError):
    """Some items failed for good; the others were done.

    Attributes:
        what: the kind of item (``"frame"``).
        failures: ``{item: message}`` of the items that failed.
        done: the items done.
    """

    def __init__(self, what: str, failures: dict, done: Sequence):
        self.what = what
        self.failures = dict(sorted(failures.items()))
        self.done = list(done)
        lines = [f"{len(failures)} of {len(failures) + len(self.done)} {what}s failed:"]
        lines += [f"  {what} {item}: {message}" for item, message in self.failures.items()]
        super().__init__("\n".join(lines))

    def __reduce__(self):   # pickles (a Ray task may raise it)
        return type(self), (self.what, self.failures, self.done)


def describe_error(err: BaseException) -> str:
    """One line for an item's error: the message of a ``ValueError`` or a missing file (they
    name the file at fault), the type and message of anything else."""
    if isinstance(err, (ValueError, FileNotFoundError)):
        return " ".join(str(err).split())
    return " ".join(f"{type(err).__name__}: {err}".split())


# --------------------------------------------------------------------------------------------
# --shard K/N
# --------------------------------------------------------------------------------------------

def check_shard(shard) -> tuple[int, int] | None:
    """``shard`` as ``(K, N)`` with ``0 <= K < N`` (or None).

    Raises:
        ValueError: anything else, naming ``shard``.
    """
    if shard is None:
        return None
    ok = (isinstance(shard, (tuple, list)) and len(shard) == 2
          and all(isinstance(v, int) and not isinstance(v, bool) for v in shard)
          and 0 <= shard[0] < shard[1])
    if not ok:
        raise ValueError(f"shard: expected (K, N), run K of N with 0 <= K < N, got {shard!r}")
    return int(shard[0]), int(shard[1])


def parse_shard(text: str) -> tuple[int, int]:
    """``"K/N"`` (run ``K`` of ``N``, counted from 0: Slurm's ``$SLURM_ARRAY_TASK_ID`` of
    ``--array=0-(N-1)``, Kubernetes' ``$JOB_COMPLETION_INDEX``) -> ``(K, N)``.

    Raises:
        ValueError: not of that form, or not ``0 <= K < N``.
    """
    parts = str(text).split("/")
    try:
        shard = (int(parts[0]), int(parts[1])) if len(parts) == 2 else None
    except ValueError:
        shard = None
    if shard is None or not 0 <= shard[0] < shard[1]:
        raise ValueError(f"shard: expected K/N with 0 <= K < N (run K of N, counted from 0), "
                         f"e.g. 0/4, got {text!r}")
    return shard


def shard_part(items: Sequence, shard: tuple[int, int] | None) -> list:
    """The items of run ``K`` of ``N``: ``items[K::N]`` (all of them for ``shard=None``)."""
    if shard is None:
        return list(items)
    k, n = check_shard(shard)
    return list(items[k::n])


# --------------------------------------------------------------------------------------------
# Ray
# --------------------------------------------------------------------------------------------

def import_ray():
    """The ``ray`` module.

    Raises:
        ImportError: Ray is not installed; the message names `RAY_INSTALL`.
    """
    try:
        import ray
    except ImportError:
        raise ImportError(f"ray: Ray is not installed; install the optional dependency with "
                          f"{RAY_INSTALL} (or pip install 'ray>=2.9')") from None
    return ray


@contextlib.contextmanager
def ray_cluster(address: str | bool | None = None) -> Iterator[Any]:
    """Connected to a Ray cluster for the ``with`` block; yields the ``ray`` module.

    ``address``: ``"HOST:PORT"`` of a cluster's head (``ray start --head`` prints it),
    ``"auto"`` for the cluster ``ray start`` started on this machine; ``True``, ``""`` or None:
    as ``ray.init()`` chooses, ``$RAY_ADDRESS`` when set, else the cluster ``ray start``
    started on this machine, else a local cluster on this machine's CPUs started for the block
    and stopped after it. A process already connected (``ray.init`` called before) keeps its
    connection, whatever ``address`` says.
    """
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    address = address if isinstance(address, str) and address else None
    kwargs: dict[str, Any] = {"logging_level": logging.WARNING}
    if address is None and not os.environ.get("RAY_ADDRESS"):
        kwargs["include_dashboard"] = False    # a cluster of our own: no dashboard to serve
    ray.init(address=address, **kwargs)
    try:
        yield ray
    finally:
        ray.shutdown()


def split_chunks(items: Sequence, cpus: int, max_chunk: int = MAX_CHUNK) -> list[list]:
    """``items`` in order, cut into chunks: about two per CPU (a CPU that finishes early takes
    another), at most ``max_chunk`` items each."""
    items = list(items)
    if not items:
        return []
    size = max(1, min(max_chunk, math.ceil(len(items) / (2 * max(1, cpus)))))
    return [items[i:i + size] for i in range(0, len(items), size)]


def _task(fn: Callable, args: tuple, chunk: list) -> tuple[dict, dict]:
    """What a Ray worker runs: ``fn(*args, chunk)`` on one torch thread (the task holds one
    CPU)."""
    import torch

    torch.set_num_threads(1)
    return fn(*args, chunk)


def _check_memory(ray, memory: int | None) -> None:
    """Refuse tasks that no node of the cluster has the memory for (Ray would wait for such a
    node forever)."""
    if not memory:
        return
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    largest = max((n.get("Resources", {}).get("memory", 0) for n in nodes), default=0)
    if largest < memory:
        raise MemoryError(f"each task needs about {memory / 1e9:.1f} GB of memory, but the "
                          f"largest node of the Ray cluster offers {largest / 1e9:.1f} GB; "
                          "lower the image size, or add larger nodes")


def run_on_ray(fn: Callable, args: tuple, items: Sequence, *, address: str | bool | None = None,
               chunks: list[list] | None = None, memory: int | None = None,
               progress: bool | None = None, total: int | None = None, initial: int = 0,
               desc: str = "ray", unit: str = "item",
               log: Callable[[str], None] | None = None) -> tuple[dict, dict]:
    """Run ``fn(*args, chunk)`` for chunks of ``items`` as Ray tasks; wait for them all.

    ``fn`` must be importable (a module-level function of an installed package: the workers
    import it) and return ``(done, failures)``: ``{item: result}`` of the items it did and
    ``{item: message}`` of those that failed, having tried every item of its chunk. Ray
    retries a task whose worker dies or whose ``fn`` raises (`RETRIES` times); after
    that every item of its chunk is a failure with the error's message.

    Args:
        fn: the task's function (pickled to the workers).
        args: its leading arguments (pickled to the workers).
        items: what to do; cut by `split_chunks` over the cluster's CPUs, unless
            ``chunks`` gives the chunks.
        address: the cluster (`ray_cluster`).
        memory: bytes one task needs at its peak (Ray's ``memory`` resource), or None.
        progress: a tqdm bar on stderr (default: when stderr is a terminal), of ``total``
            items (default ``len(items)``) from ``initial``; each completed task adds its
            chunk's items less its failures.
        log: called with one-line messages.

    Returns:
        ``(done, failures)``: the union of the tasks' results.

    Raises:
        ImportError: Ray is not installed (`RAY_INSTALL`). MemoryError: ``memory`` is
        more than any node offers. KeyboardInterrupt: the tasks still running are cancelled.
    """
    from tqdm import tqdm

    log = log or (lambda msg: None)
    with ray_cluster(address) as ray:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        if chunks is None:
            chunks = split_chunks(items, cpus)
        _check_memory(ray, memory)
        options: dict[str, Any] = {"num_cpus": 1, "max_retries": RETRIES,
                                   "retry_exceptions": True}
        if memory:
            options["memory"] = int(memory)
        remote = ray.remote(_task).options(**options)
        log(f"ray: {len(chunks)} task(s) of up to {max(map(len, chunks), default=0)} {unit}(s) "
            f"on {cpus} CPU(s)")
        refs = {remote.remote(fn, args, chunk): chunk for chunk in chunks}
        done: dict = {}
        failures: dict = {}
        if progress is None:
            progress = sys.stderr.isatty()
        bar = tqdm(total=len(items) if total is None else total, initial=initial,
                   disable=not progress, file=sys.stderr, unit=unit, desc=desc)
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    chunk = refs[ref]
                    try:
                        ok, failed = ray.get(ref)
                    except ray.exceptions.RayError as err:
                        cause = getattr(err, "cause", None)
                        message = describe_error(cause if isinstance(cause, BaseException)
                                                 else err)
                        ok, failed = {}, {item: message for item in chunk}
                    done.update(ok)
                    failures.update(failed)
                    bar.update(len(chunk) - len([i for i in chunk if i in failed]))
        except BaseException:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref)
            raise
        finally:
            bar.close()
    for item in done:
        failures.pop(item, None)
    return done, failures
