"""The fast sampler's per-pixel loops as plain C++ (``csrc/fastsample.cpp``), built on first use.

Why hand-written: a bilinear tap is four loads a texel apart, which a C loop does in a few
instructions; ``torch.compile`` (inductor) turns each gather into a vector of 64-bit indices
stored to a buffer and read back one by one. Measured on 2 cores, 6 x 512 -> 1024 x 1024 RGB
float32 through a lookup table, into a reused buffer: 7.0 -> 5.2 ms at batch 1 and 78 -> 36 ms
at batch 8 (``cv2.remap`` of the same images: 5.9 and 34-47 ms).

The source is compiled once per machine with the C++ compiler ``torch.compile`` uses too
(``$CXX``, else ``c++``) and OpenMP, into ``$OMNISCAPE_TORCH_CACHE`` (default
``~/.cache/omniscape_torch``, else the temporary directory), named by a hash of the source, the
compiler, the flags and the CPU; written to a temporary file and renamed, so concurrent
processes never load half a library.
The library links ``libgomp.so.1``, the OpenMP runtime PyTorch has already loaded, so both
share one thread pool. Where no compiler or OpenMP is found, :func:`library` returns None
after one warning and the caller runs its eager torch maths (see
:func:`omniscape_torch.fastsample.compile_failures`).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch

__all__ = ["library", "function", "failure", "threads"]

SOURCE = Path(__file__).with_name("csrc") / "fastsample.cpp"
#: ``-march=native``: the library is built for this machine's CPU (its flags are part of the
#: cache key); ``-fno-trapping-math``: float comparisons may be evaluated speculatively, so the
#: tap computation vectorises (no result changes); ``-ffp-contract=off``: no fused
#: multiply-adds the torch maths does not make.
FLAGS = ("-O3", "-march=native", "-fno-trapping-math", "-fno-math-errno", "-ffp-contract=off",
         "-std=c++17", "-fopenmp", "-fPIC", "-shared")

_LOCK = threading.Lock()
_STATE: dict = {}   # "lib": the CDLL or None once tried, "error": why it is None

_P, _I, _C = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
# ring (src, weight, k), layout (face, pad, face stride, bilinear), fill, planes (batch,
# chans, pixels, width, cube batch and channel strides, output batch and channel strides), out,
# threads
_TAIL = [_P, _P, _I, _I, _I, _I, _C, _I, *[_I] * 8, _P, _C]
_SIGNATURES = {
    "os_lut_": [_P, _I, _I, _I, _I, _C, _P, _C],
    "os_sample_lut_": [_P, _P, _P, _I, *_TAIL],
    "os_sample_grid_": [_P, _P, _I, _P, _I, *_TAIL],
    "os_sample_rays_": [_P, _P, _I, _P, _I, _P, _I, *_TAIL],
    "os_face_cases": [_P],
}


def _cache_dirs() -> list[Path]:
    """Where the library may be kept: ``$OMNISCAPE_TORCH_CACHE`` alone when set, else the user
    cache, then (a read-only home) the temporary directory."""
    root = os.environ.get("OMNISCAPE_TORCH_CACHE")
    if root:
        return [Path(root)]
    return [Path.home() / ".cache" / "omniscape_torch",
            Path(tempfile.gettempdir()) / f"omniscape_torch-{getattr(os, 'getuid', int)()}"]


def _cpu() -> str:
    """What ``-march=native`` compiles for: the CPU's feature flags where Linux lists them."""
    try:
        with open("/proc/cpuinfo") as info:
            return next((line for line in info if line.startswith(("flags", "Features"))),
                        platform.processor())
    except OSError:
        return platform.machine() + platform.processor()


def _build(compiler: str) -> Path:
    source = SOURCE.read_bytes()
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True,
                             check=True).stdout
    key = hashlib.sha256(b"\0".join([source, version.encode(), " ".join(FLAGS).encode(),
                                     _cpu().encode()]))
    name = f"fastsample-{key.hexdigest()[:16]}.so"
    for folder in _cache_dirs():
        if (folder / name).exists():
            return folder / name
    for folder in _cache_dirs():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(suffix=".so", dir=folder)
            break
        except OSError as exc:   # not writable: the next place
            error = exc
    else:
        raise error
    os.close(fd)
    target = folder / name
    try:
        done = subprocess.run([compiler, *FLAGS, str(SOURCE), "-o", tmp], capture_output=True,
                              text=True)
        if done.returncode != 0:
            raise RuntimeError(f"{compiler} failed: {done.stderr.strip()[:2000]}")
        os.replace(tmp, target)   # atomic: another process sees all of it or none
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def _load() -> ctypes.CDLL:
    compiler = os.environ.get("CXX") or "c++"
    if shutil.which(compiler) is None:
        raise RuntimeError(f"no C++ compiler: {compiler!r} is not on the PATH (set $CXX)")
    return ctypes.CDLL(str(_build(compiler)))


def library() -> ctypes.CDLL | None:
    """The compiled kernels, built on the first call; None (after one warning) where they
    cannot be built."""
    if "lib" in _STATE:
        return _STATE["lib"]
    with _LOCK:
        if "lib" not in _STATE:
            try:
                _STATE["lib"] = _load()
            except Exception as exc:  # no compiler, no OpenMP, a read-only home, ...
                _STATE["lib"], _STATE["error"] = None, f"{type(exc).__name__}: {exc}"
                warnings.warn(f"omniscape_torch.native: the C++ kernels could not be built "
                              f"({_STATE['error'][:300]}); the fast sampler runs its eager "
                              "torch maths instead", UserWarning, stacklevel=3)
    return _STATE["lib"]


def failure() -> str | None:
    """Why :func:`library` is None, or None."""
    return _STATE.get("error")


def function(name: str):
    """The kernel ``name`` (e.g. ``"os_sample_grid_f32"``) with its argument types, or None."""
    lib = library()
    if lib is None:
        return None
    fn = getattr(lib, name)
    if fn.argtypes is None:
        fn.argtypes = next(sig for prefix, sig in _SIGNATURES.items()
                           if name.startswith(prefix))
        fn.restype = None
    return fn


def threads() -> int:
    """OpenMP threads per call: PyTorch's intra-op count (1 in ``DataLoader`` workers)."""
    return torch.get_num_threads()
