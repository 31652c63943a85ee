"""Shared by the benchmarks: environment records, atomic JSON, and the round-robin timer.

The records and the timer are those of ``omniscape_torch.benchmark`` (the package's own
benchmark, ``omniscape-torch bench``), adapted to the one-device signatures used here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable

import torch

from omniscape_torch import benchmark as _bench
from omniscape_torch.benchmark import git_commit
from omniscape_torch.io import atomic_write_text

__all__ = ["ROOT", "git_commit", "loadavg", "machine_info", "measure", "run_record",
           "write_json_atomic"]

ROOT = Path(__file__).resolve().parents[1]


def machine_info(device: torch.device) -> dict:
    return _bench.machine_info([device])


def loadavg() -> list[float] | None:
    return _bench._loadavg()


def measure(fns: list[Callable[[], object]], repeats: int, warmup: int,
            device: torch.device) -> list[dict]:
    """Median and IQR (seconds) of ``repeats`` timed calls of each of ``fns``, after ``warmup``
    untimed rounds, timed round-robin (one call of each per repeat)."""
    return _bench.measure(fns, repeats, warmup, cuda=device.type == "cuda", progress=False)


def write_json_atomic(data: dict, path: Path) -> None:
    """``data`` as indented JSON at ``path``, atomically (temp file + rename)."""
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")


def run_record(name: str, device: torch.device, threads: int, cv2=None) -> dict:
    """The head of a benchmark's JSON: name, commit (and dirty flag), machine, versions, the
    environment knobs that change timings without changing the code (threads, allocator,
    inductor), and the thread counts in effect."""
    import numpy as np

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
