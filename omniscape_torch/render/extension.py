"""The fast sampler's per-pixel loops (``csrc/fastsample.cpp``) as PyTorch custom ops, built on
first use.

Why hand-written: a bilinear tap is four loads a texel apart, which a C loop does in a few
instructions; ``torch.compile`` (inductor) turns each gather into a vector of 64-bit indices
stored to a buffer and read back one by one. Measured on 2 cores, 6 x 512 -> 1024 x 1024 RGB
float32 through a lookup table, into a reused buffer: 7.0 -> 5.2 ms at batch 1 and 78 -> 36 ms
at batch 8 (``cv2.remap`` of the same images: 5.9 and 34-47 ms).

:func:`load` builds the source with ``torch.utils.cpp_extension.load`` (ninja and the C++
compiler torch uses, ``$CXX`` else ``c++``; about 40 s once per machine on 2 cores, most of it the
instantiations of the samplers per element, output and grid type; the torch headers take 5 s,
against 30 s with ``torch/extension.h``) into torch's extension cache
(``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions/<python>_<device>/``) and
loads it: the ops ``torch.ops.omniscape_torch.{build_lut, sample_lut, sample_grid,
sample_rays, camera_grid}`` (schemas in the source), with their fake implementations for
``torch.compile`` registered here. A later process finds it built (ninja checks the source and
the flags) and loads it in 0.1-0.2 s, mostly the import of ``cpp_extension``. Concurrent first uses
(processes, ``DataLoader`` workers) are serialised by ``cpp_extension``'s lock file in the
build folder: one builds, the others wait and load. (A build killed outright, SIGKILL, leaves
that file behind, and later loads wait for it forever: delete the folder's ``lock``.)

The extension's name holds a hash of the CPU's feature flags (``-march=native`` code must not
be loaded on another CPU that shares the home directory, e.g. over NFS), of the torch version
and Python ABI it links against, of the flags, of the source and of its path: each gets its
own build folder, so that no process loads, or rebuilds under another's feet, a library built
from another source (two checkouts sharing a home); an edited source leaves its old folder
behind. The path: two checkouts of the same source would otherwise share a folder whose build
file names one of them, and ninja rebuilt the library (about 60 s) each time the other was
used.
The face table is generated from ``cubemap/faces.py`` (the only one) and passed as
``-DOS_FACE_CASES=...``: a changed table is a new build.

The library is built with OpenMP, the runtime PyTorch has already loaded (``libgomp.so.1``), and
the loops run on PyTorch's intra-op threads (``at::parallel_for``). Where no compiler or ninja
is found, :func:`load` raises; :mod:`.fast` turns that into one warning and its reference path.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import shutil
import sys
import sysconfig
import threading
from pathlib import Path

import torch

__all__ = ["load", "name", "face_case_flags", "CFLAGS", "LDFLAGS", "NAMESPACE", "OPS", "SOURCE"]

SOURCE = Path(__file__).with_name("csrc") / "fastsample.cpp"
NAMESPACE = "omniscape_torch"
OPS = ("build_lut", "sample_lut", "sample_grid", "sample_rays", "camera_grid", "camera_rays",
       "sample_image")
#: ``-march=native``: the library is built for this machine's CPU (its flags are in the name);
#: ``-fno-trapping-math``: float comparisons may be evaluated speculatively, so the tap
#: computation vectorises (no result changes); ``-ffp-contract=off``: no fused multiply-adds
#: that the reference maths does not make (the results are grid_sample's to the bit where
#: they were before); ``-fopenmp``: ``at::parallel_for`` is OpenMP's in PyTorch's CPU builds.
CFLAGS = ("-O3", "-march=native", "-fno-trapping-math", "-fno-math-errno", "-ffp-contract=off",
          "-fopenmp")
LDFLAGS = ("-fopenmp",)

_LOCK = threading.Lock()
_LOADED: list[str] = []   # the path of the library once loaded in this process


def _cpu() -> str:
    """What ``-march=native`` compiles for: the CPU's feature flags where Linux lists them."""
    try:
        with open("/proc/cpuinfo") as info:
            return next((line for line in info if line.startswith(("flags", "Features"))),
                        platform.processor())
    except OSError:
        return platform.machine() + platform.processor()


def name() -> str:
    """The extension's name: ``omniscape_torch_fastsample_`` and a hash of what the library is
    built for and from: this CPU's feature flags, the torch version and Python ABI it links
    against, the flags (the face table among them), the source and where it lies."""
    parts = [_cpu().strip(), torch.__version__, sys.implementation.cache_tag or "",
             getattr(sys, "abiflags", ""), *CFLAGS, *LDFLAGS, *face_case_flags(),
             str(SOURCE.resolve())]
    digest = hashlib.sha256("\0".join(parts).encode() + b"\0" + SOURCE.read_bytes())
    return f"omniscape_torch_fastsample_{digest.hexdigest()[:12]}"


def face_case_flags() -> list[str]:
    """``-DOS_FACE_CASES=...``: the kernel's face table, the 6 cases of
    ``cubemap.grid._CASES`` (derived from ``cubemap.faces``) and its zero-ray case, 35 integers
    (commas only: nothing a shell or ninja would rewrite)."""
    from ..cubemap import grid
    values = [int(v) for case in (*grid._CASES, grid._ZERO_CASE) for v in case]
    return ["-DOS_FACE_CASES=" + ",".join(map(str, values))]


def _ninja_folders() -> list[str]:
    """Where ninja is installed with this Python, whether or not that is on the PATH: the
    ``ninja`` package's own folder, the environment's scripts folder (a virtualenv's ``bin``)
    and the interpreter's folder."""
    folders = []
    try:
        import ninja   # the PyPI package (setup.cfg): its binary lives in the package
        folders.append(getattr(ninja, "BIN_DIR", ""))
    except ImportError:
        pass
    folders += [sysconfig.get_path("scripts"), os.path.dirname(sys.executable)]
    return [f for f in folders if f]


@contextlib.contextmanager
def _ninja_on_path():
    """``cpp_extension`` runs ``ninja`` from the PATH. The ninja installed with this Python goes
    first, whether or not its folder is on the PATH (``.venv/bin/python -m pytest`` without
    activating the virtualenv), and the PATH is restored afterwards: this is the only way to
    reach ``cpp_extension``'s subprocesses, and the lock of :func:`load` keeps this process's
    other builds out meanwhile. Always the same ninja for one Python, even where another is on
    the PATH: ninja versions keep their build logs differently (1.11 and 1.13 each took the
    other's build for out of date, a rebuild whenever they alternated). Without one installed
    with Python, the PATH's."""
    folder = next((f for f in _ninja_folders() if shutil.which("ninja", path=f)), None)
    found = shutil.which("ninja")
    if folder is None or (found is not None and os.path.samefile(
            os.path.dirname(found), folder)):
        if found is None:
            raise RuntimeError("ninja is not installed: torch.utils.cpp_extension needs it to "
                               "build the C++ kernels (pip install ninja)")
        yield
        return
    before = os.environ.get("PATH")
    os.environ["PATH"] = folder + os.pathsep + (before or "")
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PATH", None)
        else:
            os.environ["PATH"] = before


def _check_compiler() -> None:
    compiler = os.environ.get("CXX") or "c++"
    if shutil.which(compiler) is None:
        raise RuntimeError(f"no C++ compiler: {compiler!r} is not on the PATH (set $CXX)")


def _build() -> str:
    """Build (or find built) and load the library; its path."""
    from torch.utils import cpp_extension
    _check_compiler()
    with _ninja_on_path():
        return cpp_extension.load(name(), [str(SOURCE)],
                                  extra_cflags=[*CFLAGS, *face_case_flags()],
                                  extra_ldflags=list(LDFLAGS), is_python_module=False)


def load() -> torch._ops._OpNamespace:
    """The ops ``torch.ops.omniscape_torch``, built and loaded on the first call (once per
    process; a forked child inherits them).

    Raises:
        RuntimeError: no C++ compiler, no ninja, or the build failed (its output).
    """
    with _LOCK:
        if not _LOADED:
            _LOADED.append(_build())
            _register_fakes()
    return getattr(torch.ops, NAMESPACE)


# ------------------------------------------------------------------------------------------
# Fake (meta) implementations: the ops only write into their mutated argument, so tracing
# (torch.compile, FakeTensor) needs no output, only the checks that shapes and dtypes allow.
# ------------------------------------------------------------------------------------------

def _check(cond: bool, message: str) -> None:
    torch._check(cond, lambda: f"{NAMESPACE}: {message}")


def _fake_build_lut(grid, face, pad, strides, bilinear, table) -> None:
    _check(grid.dim() == 3 and grid.shape[-1] == 2, "build_lut: grid: expected (B, P, 2)")
    _check(table.shape == (*grid.shape[:2], 3), "build_lut: table: expected (B, P, 3)")


def _fake_sample(cube, out, points, last: int, what: str) -> None:
    _check(cube.dim() == 5 and cube.shape[1] == 6, f"{what}: cube: expected (B, 6, C, F, F)")
    _check(points.shape[-1] == last, f"{what}: expected a last dimension of {last}")
    _check(out.dim() == 4 and out.shape[:2] == (cube.shape[0], cube.shape[2])
           and (out.dtype in (cube.dtype, torch.float32)
                or (out.dtype == torch.int64 and cube.dtype == torch.uint8)),
           f"{what}: out: expected (B, C, H, W) in the cube's dtype, float32 or int64")


def _fake_sample_lut(cube, table, grid, ring_src, ring_weight, pad, strides, bilinear, fill,
                     out) -> None:
    _fake_sample(cube, out, grid, 2, "sample_lut")


def _fake_sample_grid(cube, grid, valid, ring_src, ring_weight, pad, bilinear, fill,
                      out) -> None:
    _fake_sample(cube, out, grid, 2, "sample_grid")


def _fake_sample_rays(cube, rays, rotation, valid, ring_src, ring_weight, pad, bilinear, fill,
                      out) -> None:
    _fake_sample(cube, out, rays, 3, "sample_rays")


def _fake_camera_grid(affine, limits, table, rotation, face, pad, grid, valid) -> None:
    _check(grid.dim() == 4 and grid.shape[-1] == 2 and valid.shape == grid.shape[:3],
           "camera_grid: expected grid (B, H, W, 2) and valid (B, H, W)")


def _fake_camera_rays(affine, limits, table, rays, valid) -> None:
    _check(rays.dim() == 4 and rays.shape[-1] == 3 and valid.shape == rays.shape[:3],
           "camera_rays: expected rays (B, H, W, 3) and valid (B, H, W)")


def _fake_sample_image(image, rays, rotation, intrinsics, valid, bilinear, fill, out,
                       valid_out) -> None:
    _check(image.dim() == 4 and rays.dim() == 4 and rays.shape[-1] == 3
           and out.shape == (image.shape[0], image.shape[1], *rays.shape[1:3]),
           "sample_image: expected image (B, C, H, W), rays (B, h, w, 3), out (B, C, h, w)")


_FAKES = {"build_lut": _fake_build_lut, "sample_lut": _fake_sample_lut,
          "sample_grid": _fake_sample_grid, "sample_rays": _fake_sample_rays,
          "camera_grid": _fake_camera_grid, "camera_rays": _fake_camera_rays,
          "sample_image": _fake_sample_image}


def _register_fakes() -> None:
    for op, fake in _FAKES.items():
        torch.library.register_fake(f"{NAMESPACE}::{op}", fake)
