"""Shared by the benchmarks: environment records, atomic JSON, and the round-robin timer."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from omniscape_torch.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


def git_commit() -> tuple[str, bool | None]:
    """(HEAD commit or "unknown", working tree dirty or None)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, timeout=10)
        if commit.returncode != 0:
            return "unknown", None
        status = subprocess.run(["git", "status", "--porcelain"], cwd=ROOT, capture_output=True,
                                text=True, timeout=10)
        return commit.stdout.strip(), bool(status.stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return "unknown", None


def machine_info(device: torch.device) -> dict:
    info = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
    }
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def loadavg() -> list[float] | None:
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def measure(fns: list[Callable[[], object]], repeats: int, warmup: int,
            device: torch.device) -> list[dict]:
    """Median and IQR (seconds) of ``repeats`` timed calls of each of ``fns``, after ``warmup``
    untimed calls of each, timed round-robin (one call of each per repeat)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for fn in fns:
        for _ in range(warmup):
            fn()
    sync()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for fn, t in zip(fns, times):
            sync()
            start = time.perf_counter()
            fn()
            sync()
            t.append(time.perf_counter() - start)
    out = []
    for t in times:
        q1, median, q3 = np.percentile(t, [25, 50, 75])
        out.append({"median_s": float(median), "iqr_s": float(q3 - q1), "min_s": float(min(t)),
                    "times_s": [float(x) for x in t]})
    return out


def write_json_atomic(data: dict, path: Path) -> None:
    """``data`` as indented JSON at ``path``, atomically (temp file + rename)."""
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")
