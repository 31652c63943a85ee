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

from omniscape_torch.cli import positive_int  # noqa: E402  (re-exported: argparse type)
from omniscape_torch.io import atomic_write_text  # noqa: E402

__all__ = ["begin_run", "ROOT", "SETTLE_S", "git_commit", "loadavg", "machine_info", "measure",
           "positive_int", "run_record", "write_json_atomic"]

#: Untimed pause before every timed call: the worker threads of the previous call (OpenMP's,
#: OpenCV's, OpenBLAS's) keep spinning for a while after it, and on 2 cores they take the next
#: row's cores (measured: the augmentation benchmark's IQR 20 ms without the pause, 10-12 ms
#: with it). Short: after 50 ms idle this VM ran the next 5 ms call at up to 13 ms.
SETTLE_S = 0.01


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
        per function ``{"median_s", "iqr_s", "min_s", "times_s"}``.
    """
    from tqdm import tqdm

    cuda = torch.device(device).type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    times: list[list[float]] = [[] for _ in fns]
    for r in tqdm(range(warmup + repeats), desc="timing", unit="round", disable=not progress,
                  file=sys.stderr):
        for fn, t in zip(fns, times):
            sync()
            if r >= warmup and settle_s > 0:
                time.sleep(settle_s)
            start = time.perf_counter()
            fn()
            sync()
            if r >= warmup:
                t.append(time.perf_counter() - start)
    out = []
    for t in times:
        q1, median, q3 = np.percentile(t, [25, 50, 75])
        out.append({"median_s": float(median), "iqr_s": float(q3 - q1), "min_s": float(min(t)),
                    "times_s": [float(x) for x in t]})
    return out


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
