"""Shared by the benchmarks: environment records, atomic JSON, and the round-robin timer.

Every helper here is written once and imported by the scripts of this folder (``from common
import ...``, after putting this folder on ``sys.path``), the speed-against-accuracy harness
(``harness.py``) included.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
# the checkout this folder lives in, not whatever copy is installed
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.cli import positive_int  # noqa: E402  (re-exported: argparse type)
from omniscape_torch.io import atomic_write_text  # noqa: E402

# The whole package loaded before any timing, as every benchmark uses it (its top level loads
# on first use): what it allocates on import then lies below the heap a run measures, whose
# state (set_heap, page faults) would otherwise depend on what a benchmark happened to touch.
ot.Camera  # noqa: B018

__all__ = ["begin_run", "HEAP_MODES", "QUICK_RESULTS", "RESULTS", "ROOT", "SETTLE_S",
           "git_commit", "loadavg", "machine_info", "measure", "positive_int", "results_path",
           "run_record", "set_heap", "write_json_atomic"]

#: The committed results of full runs.
RESULTS = ROOT / "benchmarks" / "results"
#: Where ``--quick`` (smoke) runs write: git-ignored, so that a smoke run never overwrites the
#: committed full-run results beside it.
QUICK_RESULTS = RESULTS / "quick"


def results_path(name: str, *, quick: bool = False) -> Path:
    """The default output of a benchmark's file ``name``: ``benchmarks/results/<name>``, or
    for a ``--quick`` run ``benchmarks/results/quick/<name>``."""
    return (QUICK_RESULTS if quick else RESULTS) / name

#: Untimed pause before every timed call: the worker threads of the previous call (OpenMP's,
#: OpenCV's, OpenBLAS's) keep spinning for a while after it, and on 2 cores they take the next
#: row's cores (measured: the augmentation benchmark's IQR 20 ms without the pause, 10-12 ms
#: with it). Short: after 50 ms idle this VM ran the next 5 ms call at up to 13 ms.
SETTLE_S = 0.01

#: Where a run's large allocations come from (:func:`set_heap`). A call whose output is a fresh
#: mapping faults in each of its pages (a 50 MB float32 batch: 12,290 faults, ~40 ms on this
#: VM), one whose output the heap kept from an earlier call none; glibc's own choice between the
#: two moves within a run (its mmap threshold adapts, up to 32 MB), so a ratio of two rows of
#: different output sizes can flip with the rows around them.
HEAP_MODES = ("default", "warm", "fresh")


def measure(fns: list[Callable[[], object]], repeats: int, warmup: int,
            device: torch.device | str = "cpu", *, progress: bool = False,
            settle_s: float = SETTLE_S) -> list[dict]:
    """Median and IQR (seconds) of ``repeats`` timed calls of each of ``fns``, after ``warmup``
    untimed calls of each, timed round-robin (one call of each per repeat, so that a change of
    load hits every row alike), each after an untimed pause of ``settle_s`` (:data:`SETTLE_S`);
    ``time.perf_counter`` around single calls. On a CUDA ``device``,
    ``torch.cuda.synchronize()`` before and after every timed call. ``progress``: a tqdm bar
    on stderr.

    Returns:
        per function ``{"median_s", "iqr_s", "min_s", "times_s", "page_faults"}``: the last,
        the median count of minor page faults of the process during a timed call (fresh memory
        touched for the first time: a new allocation the heap did not hold; ``getrusage``,
        every thread of the process), where the platform counts them.
    """
    from tqdm import tqdm

    cuda = torch.device(device).type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    times: list[list[float]] = [[] for _ in fns]
    faults: list[list[int]] = [[] for _ in fns]
    for r in tqdm(range(warmup + repeats), desc="timing", unit="round", disable=not progress,
                  file=sys.stderr):
        for fn, t, f in zip(fns, times, faults):
            sync()
            if r >= warmup and settle_s > 0:
                time.sleep(settle_s)
            flt = _minor_faults()
            start = time.perf_counter()
            fn()
            sync()
            if r >= warmup:
                t.append(time.perf_counter() - start)
                if flt is not None:
                    f.append(_minor_faults() - flt)
    out = []
    for t, f in zip(times, faults):
        q1, median, q3 = np.percentile(t, [25, 50, 75])
        out.append({"median_s": float(median), "iqr_s": float(q3 - q1), "min_s": float(min(t)),
                    "times_s": [float(x) for x in t],
                    "page_faults": float(np.median(f)) if f else None})
    return out


def set_heap(mode: str) -> None:
    """Set the C heap (glibc's ``malloc``, which PyTorch's CPU tensors come from) for the rest of
    the process: ``default``, glibc's own (adaptive); ``warm``, every allocation from the heap
    and nothing returned to the system (no page faults once it has grown: a loop whose outputs
    reuse freed memory); ``fresh``, every allocation of 1 MiB or more a new mapping (every
    output faults in its pages: a loop that keeps no such block free). Raises ``ValueError``
    for another mode, ``RuntimeError`` where the C library is not glibc."""
    if mode not in HEAP_MODES:
        raise ValueError(f"heap: expected one of {HEAP_MODES}, got {mode!r}")
    if mode == "default":
        return
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    if not hasattr(libc, "mallopt"):
        raise RuntimeError(f"--heap {mode}: needs glibc's mallopt, not in this C library")
    m_trim_threshold, m_mmap_threshold, m_mmap_max = -1, -3, -4   # glibc's malloc.h
    settings = ([(m_mmap_max, 0), (m_trim_threshold, 2 ** 31 - 1)] if mode == "warm"
                else [(m_mmap_threshold, 1 << 20)])
    for param, value in settings:
        if libc.mallopt(param, value) != 1:
            raise RuntimeError(f"--heap {mode}: mallopt({param}, {value}) failed")


def _minor_faults() -> int | None:
    """The process's minor page faults so far (``getrusage``), None where not counted."""
    try:
        import resource
    except ImportError:   # not on Windows
        return None
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def git_commit() -> tuple[str, bool | None]:
    """(HEAD commit of the checkout this folder lives in, or "unknown"; dirty tree or None).
    Changed benchmark results (``benchmarks/results``, what a rerun rewrites) are not dirt."""
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, timeout=10)
        if commit.returncode != 0:
            return "unknown", None
        status = subprocess.run(["git", "status", "--porcelain", "--", ".",
                                 ":(exclude)benchmarks/results"], cwd=ROOT,
                                capture_output=True, text=True, timeout=10)
        return commit.stdout.strip(), bool(status.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return "unknown", None


def machine_info(devices: torch.device | str | Iterable[torch.device | str] = ()) -> dict:
    """Platform, CPU model and count, Python, and the GPU of the first CUDA device among
    ``devices`` (one device or several)."""
    if isinstance(devices, (torch.device, str)):
        devices = [devices]
    info = {"platform": platform.platform(), "processor": platform.processor()
            or platform.machine(), "cpu_count": os.cpu_count(),
            "python": platform.python_version()}
    try:
        with open("/proc/cpuinfo") as f:
            info["cpu_model"] = next((line.split(":", 1)[1].strip() for line in f
                                      if line.startswith("model name")), None)
    except OSError:
        pass
    gpus = [torch.cuda.get_device_name(d) for d in map(torch.device, devices)
            if d.type == "cuda"]
    if gpus:
        info["gpu"] = gpus[0]
    return info


def loadavg() -> list[float] | None:
    """The 1, 5 and 15-minute load averages, or None where the platform has none."""
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def begin_run(threads: int, cv2=None) -> list[float] | None:
    """What every timed run does first: warn when the machine is busy (1-minute load above
    0.5), set torch's (and OpenCV's) thread count. Returns the load at the start."""
    load = loadavg()
    if load is not None and load[0] > 0.5:
        print(f"# warning: 1-minute load average {load[0]:.2f} > 0.5: timings are "
              "unreliable on a busy machine", file=sys.stderr)
    torch.set_num_threads(threads)
    if cv2 is not None:
        cv2.setNumThreads(threads)
    return load


def write_json_atomic(data: dict, path: Path) -> None:
    """``data`` as indented JSON at ``path``, atomically (temp file + rename)."""
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")


def run_main(parse_args: Callable, run: Callable, markdown: Callable,
             argv: list[str] | None = None) -> int:
    """A benchmark's command line: ``parse_args(argv)``, ``run(args)``, its ``markdown(result)``
    printed and the result written as JSON to ``args.out`` (atomically). Returns 0."""
    args = parse_args(argv)
    result = run(args)
    print(markdown(result))
    write_json_atomic(result, args.out)
    print(f"\nwrote {args.out}")
    return 0


def run_record(name: str, device: torch.device, threads: int, cv2=None) -> dict:
    """The head of a benchmark's JSON: name, commit (and dirty flag), machine, versions, the
    environment knobs that change timings without changing the code (threads, allocator,
    inductor), and the thread counts in effect."""
    import omniscape_torch as ot

    commit, dirty = git_commit()
    return {
        "benchmark": name,
        "commit": commit,
        "dirty": dirty,
        "machine": machine_info(device),
        "versions": {"torch": torch.__version__, "numpy": np.__version__,
                     "cv2": None if cv2 is None else cv2.__version__,
                     "omniscape_torch": getattr(ot, "__version__", None)},
        "environment": {k: v for k, v in sorted(os.environ.items())
                        if k.startswith(("OMP_", "MKL_", "KMP_", "MALLOC_", "OPENCV_",
                                         "TORCHINDUCTOR_"))
                        or k in ("LD_PRELOAD", "ATEN_CPU_CAPABILITY")},
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "threads": threads,
        "torch_num_threads": torch.get_num_threads(),
        "cv2_num_threads": None if cv2 is None else cv2.getNumThreads(),
        "device": str(device),
    }
