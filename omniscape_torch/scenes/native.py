"""The town's shading loops in C (``csrc/town_shade.c``), built on first use and loaded with
ctypes.

Why C: shading a hit is about 150 float operations; as torch kernels over batches of rays each
operation is a pass over memory with its own dispatch, about 0.5 microseconds a ray in all
(measured on 2 cores, batches of 16 to 64 thousand rays), more than Embree's tracing (0.25);
one C loop over the rays does it in registers, about 0.03. The torch version,
``Town._shade_reference``, stays as the reference and the fallback.

:func:`library` compiles the source with the system C compiler (``$CC``, else ``cc``; plain C99,
no Python or torch headers: well under a second) into the user's cache
(``$XDG_CACHE_HOME/omniscape_torch``, default ``~/.cache/omniscape_torch``), under a name that
holds a hash of the source, the flags, the compiler's path and the machine, written atomically
(concurrent first uses each build and rename; the results are identical), and loads it. ctypes
releases the GIL during a call, so threads shade in parallel. Where no compiler is found or the
build fails, it warns once and returns None: the town shades with torch, slower, to the same
result (tests/test_scenes.py compares the two).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import warnings
from pathlib import Path

from ..io.atomic import atomic_path

__all__ = ["CFLAGS", "SOURCE", "library", "library_path"]

SOURCE = Path(__file__).with_name("csrc") / "town_shade.c"
#: ``-ffp-contract=off``: no fused multiply-adds (every operation rounds as torch's does);
#: ``-fno-math-errno``: ``sqrtf`` becomes one instruction (no result changes).
CFLAGS = ("-O2", "-std=c99", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno")


def _compiler() -> str | None:
    return os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") \
        or shutil.which("clang")


def library_path(compiler: str) -> Path:
    """Where the library built by ``compiler`` lives (whether or not it is built yet)."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "omniscape_torch"
    parts = [compiler, platform.machine(), platform.system(), *CFLAGS]
    digest = hashlib.sha256("\0".join(parts).encode() + b"\0" + SOURCE.read_bytes())
    suffix = ".dll" if platform.system() == "Windows" else ".so"
    return cache / f"town_shade_{digest.hexdigest()[:12]}{suffix}"


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, i64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    common = [i64, p, i64, p, p, p, p, p, p, i64, p, p, p]
    lib.town_prepare.argtypes = common + [f32, f32, p, p, p]
    lib.town_prepare.restype = None
    lib.town_shade.argtypes = common + [p, p, i64, p, p, p, p]
    lib.town_shade.restype = None
    lib.town_backfaces.argtypes = [i64, p, p, p, i64, p]
    lib.town_backfaces.restype = None
    lib.town_store.argtypes = [i64, p, i64, p, p, p, p, p, p, f32, i64, p, p, p, p]
    lib.town_store.restype = None
    return lib


@functools.lru_cache(maxsize=None)
def library() -> ctypes.CDLL | None:
    """The loaded library (built first if needed), or None (with a warning) where it cannot be
    built or loaded."""
    compiler = _compiler()
    try:
        if compiler is None:
            raise RuntimeError("no C compiler found (set $CC, or install cc)")
        path = library_path(compiler)
        if not path.is_file():
            with atomic_path(path, suffix=path.suffix) as tmp:
                done = subprocess.run([compiler, *CFLAGS, str(SOURCE), "-o", str(tmp), "-lm"],
                                      capture_output=True, text=True, timeout=300)
                if done.returncode != 0:
                    raise RuntimeError(f"{compiler} failed: {done.stderr.strip()[-2000:]}")
        return _declare(ctypes.CDLL(str(path)))
    except (OSError, RuntimeError, subprocess.SubprocessError) as err:
        warnings.warn(f"the town's C shading could not be built ({err}); shading with torch "
                      "instead (same images, several times slower)", RuntimeWarning,
                      stacklevel=2)
        return None
