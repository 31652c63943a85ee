"""The package's C++ kernels as PyTorch custom ops, one library built on first use: the fast
sampler's per-pixel loops (the headers ``csrc/sample_*.h``, ``camera_grid.h`` and ``op_checks.h``,
one an idea, their map in ``sample_base.h``; their ops in ``csrc/fastsample.cpp``, the cube
samplers', and ``csrc/fastimage.cpp``, the others) and the town's shading loops
(``csrc/town_shade.cpp``).

Why hand-written: a bilinear tap is four loads a texel apart, which a C loop does in a few
instructions; ``torch.compile`` (inductor) turns each gather into a vector of 64-bit indices
stored to a buffer and read back one by one. Measured on 2 cores, 6 x 512 -> 1024 x 1024 RGB
float32 through a lookup table, into a reused buffer: 7.0 -> 5.2 ms at batch 1 and 78 -> 36 ms
at batch 8 (``cv2.remap`` of the same images: 5.9 and 34-47 ms). Shading a town hit is about
150 float operations: as torch kernels over batches of rays each is a pass over memory with its
own dispatch, about 0.5 microseconds a ray in all (2 cores, batches of 16 to 64 thousand rays),
more than Embree's tracing (0.25); one C++ loop over the rays does it in registers, about 0.03.

The ops, ``torch.ops.omniscape_torch.*`` (`OPS`; schemas in the sources): the samplers
``build_lut, sample_lut, sample_grid, sample_rays, camera_grid, camera_rays, sample_image``,
its antialiasing ``mip_image``, the framing's ``framing_reach, framing_focal``
([framing][omniscape_torch.render.kernels.framing]), the detection boxes' ``box_pixels, outline_points,
outline_reduce`` (``detection``), the cube texels a layer's taps touch, ``cone_taps``
(its schema, fake and wrapper in `omniscape_torch.render.kernels.cone`) and the town's ``town_backfaces, town_prepare, town_shade,
town_store`` (their schemas, fakes and wrappers in `omniscape_torch.render.kernels.town`; the
C++ source only implements them). Each checks its arguments
(device, dtype, shape, contiguity, index ranges) before it reads any, raising a RuntimeError
that names the op and the argument; the other ops' fake implementations for ``torch.compile``
are registered here. A call through ``torch.ops`` releases the GIL while the op runs, so the town's
worker threads shade in parallel.

Build: `load` compiles the three ``.cpp`` sources with one ``torch.utils.cpp_extension.load``
call (ninja and the C++ compiler torch uses, ``$CXX`` else ``c++``; once per machine, 40-220 s on
2 cores depending on load: about 40 s idle, 85-141 s under load, 217 s on a busy machine; the
sources compiled side by side, most of it the instantiations of the samplers per element, output
and grid type, which is why the samplers' ops are two translation units, the cube's and the
image's, of about the same cost: 35 and 32 s of a 35 s build on 2 idle cores (63 s of CPU),
the town's 13 s; the one source of 2,900 lines before them took 65 s; the torch headers take 5 s a
source, against 30 s with ``torch/extension.h``) into torch's extension cache
(``$TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions/<python>_<device>/``) and loads
the library. A build says on stderr what it does as it goes: one line as it starts
(``omniscape_torch: building the C++ kernels ...``), the sources it compiles, one line as each is
compiled (read from ninja's log in the build folder), every 15 s the time so far and what is
still compiling, and one line when it is done, with its time. A process that finds the library
built (the ``.so`` of its name in its folder, and no build under way there: no ``lock``; the
name is a hash of the content, so the file is what this install would build) loads it
directly, with no compiler, ninja or build file involved, and prints nothing (on 2 cores 0.15 s
at rest, 0.25 s at a load of 3; most of it the import of ``cpp_extension``, whose function names
the folder). Concurrent first uses (processes, ``DataLoader`` workers) are serialised by
``cpp_extension``'s lock file in the build folder: one builds, the others wait (saying how the
build goes) and load. (A build killed outright, SIGKILL, leaves that file behind, and later
loads wait for it forever: delete the folder's ``lock``.)

The cache is keyed by content: the extension's name (`name`) holds a hash of the CPU's
feature flags (``-march=native`` code must not be loaded on another CPU that shares the home
directory, e.g. over NFS), of the torch version and Python ABI it links against, of the flags
and of the sources' names and bytes, never of where they lie. The sources are copied into the
build folder (each written to a temporary and renamed, once) and built from there, so the build
file names the same paths for every checkout or install of the same source: they all load the
one library (two checkouts used to rebuild each other's, about 60 s, when the build file named
the checkout's own path). An edited source is another name, another folder; the old one stays
behind.
The face table is generated from ``cubemap/faces.py`` (the only one) and passed as
``-DOS_FACE_CASES=...``: a changed table is a new build.

The library is built with OpenMP, the runtime PyTorch has already loaded (``libgomp.so.1``), and
the samplers' loops run on PyTorch's intra-op threads (``at::parallel_for``); the town's ops run
on the calling thread (the town splits its rays into tasks on threads of its own). Where the
library cannot be built (no compiler, no ninja, a read-only cache), `load` raises and `ops`
warns once and returns None: the cube samplers ([cube][omniscape_torch.render.kernels.cube])
then take their torch twin (``grid_sample`` on the padded atlas) and the town shades with
torch (the twins in `omniscape_torch.render.kernels.town`: the same labels and depths,
colours within float32 roundings, several times slower).
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
import time
import warnings
from pathlib import Path

import torch

from ...io.atomic import atomic_path
from . import layout

__all__ = ["define", "load", "ops", "unavailable_reason", "name", "face_case_flags", "CFLAGS",
           "LDFLAGS", "NAMESPACE", "OPS", "SOURCES"]

#: The sources of the one library: the samplers' kernels (headers, one an idea, in the order
#: they include each other; their map in ``sample_base.h``), their ops (the cube's, which
#: define the namespace, and the image's) and the town's. Every file is in the name's hash and
#: copied into the build folder, where the ``.cpp`` files are compiled.
SOURCES = tuple(Path(__file__).parent.parent / "csrc" / file for file in (
    "sample_base.h", "sample_taps.h", "sample_simd.h", "sample_cube.h", "sample_rays.h",
    "sample_image.h", "sample_mip.h", "camera_grid.h", "sample_reproject.h", "op_checks.h",
    "fastsample.cpp", "fastimage.cpp", "town_shade.cpp"))
NAMESPACE = "omniscape_torch"
OPS = ("build_lut", "sample_lut", "sample_grid", "sample_rays", "camera_grid", "camera_rays",
       "sample_image", "mip_image", "reproject_image", "framing_reach", "framing_focal",
       "frame_lens", "box_pixels", "outline_points", "outline_reduce", "cone_taps",
       "town_backfaces", "town_prepare", "town_shade", "town_store")
#: ``-march=native``: the library is built for this machine's CPU (its flags are in the name);
#: ``-fno-trapping-math``: float comparisons may be evaluated speculatively, so the tap
#: computation vectorises (no result changes); ``-ffp-contract=off``: no fused multiply-adds
#: that the reference maths does not make (the results are grid_sample's to the bit where
#: they were before); ``-fopenmp``: ``at::parallel_for`` is OpenMP's in PyTorch's CPU builds.
CFLAGS = ("-O3", "-march=native", "-fno-trapping-math", "-fno-math-errno", "-ffp-contract=off",
          "-fopenmp")
LDFLAGS = ("-fopenmp",)

_LOCK = threading.RLock()
_LOADED: list[str] = []   # the path of the library once loaded in this process
_STATE: dict = {}   # "ops": torch.ops.omniscape_torch, or None once they could not be built;
#                     "error": why
_LIB_EXT = ".pyd" if sys.platform == "win32" else ".so"   # cpp_extension's
#: Seconds between two of a build's lines on stderr saying what is still compiling.
_HEARTBEAT_S = 15.0


def _cpu() -> str:
    """What ``-march=native`` compiles for: the CPU's feature flags where Linux lists them."""
    try:
        with open("/proc/cpuinfo") as info:
            return next((line for line in info if line.startswith(("flags", "Features"))),
                        platform.processor())
    except OSError:
        return platform.machine() + platform.processor()


def name(sources: dict[str, bytes] | None = None) -> str:
    """The extension's name: ``omniscape_torch_kernels_`` and a hash of what the library is
    built for and from: this CPU's feature flags, the torch version and Python ABI it links
    against, the flags (the face table among them), and the sources' file names and bytes
    (``sources``, default `_sources`), not where they lie."""
    parts = [_cpu().strip(), torch.__version__, sys.implementation.cache_tag or "",
             getattr(sys, "abiflags", ""), *CFLAGS, *LDFLAGS, *face_case_flags()]
    digest = hashlib.sha256("\0".join(parts).encode())
    for file, data in (_sources() if sources is None else sources).items():
        digest.update(f"\0{file}\0{len(data)}\0".encode() + data)
    return f"omniscape_torch_kernels_{digest.hexdigest()[:12]}"


def _sources() -> dict[str, bytes]:
    """``{file name: bytes}`` of `SOURCES`, read once for the name and the copies, and
    of the generated header ``os_layout.h`` (the draw's stream layout and the attitude's
    rotation entries, from ``layout.layout_header``: defined once, in Python)."""
    return {**{path.name: path.read_bytes() for path in SOURCES}, "os_layout.h": layout.layout_header()}


def _copy_sources(sources: dict[str, bytes], folder: Path) -> list[str]:
    """The sources' copies in the build folder, written where missing or different (each to a
    temporary, then renamed: a concurrent build never reads half a file). A copy already there
    is left alone, its time too, so that ninja finds nothing to rebuild."""
    paths = []
    for file, data in sources.items():
        path = folder / file
        try:
            same = path.read_bytes() == data
        except FileNotFoundError:
            same = False
        if not same:
            with atomic_path(path, suffix=path.suffix) as tmp:
                tmp.write_bytes(data)
        paths.append(str(path))
    return paths


def face_case_flags() -> list[str]:
    """``-DOS_FACE_CASES=...``: the kernel's face table, the 6 cases of
    ``cubemap.grid._CASES`` (derived from ``cubemap.faces``) and its zero-ray case, 35 integers
    (commas only: nothing a shell or ninja would rewrite)."""
    from ...cubemap import grid
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
    reach ``cpp_extension``'s subprocesses, and the lock of `load` keeps this process's
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


def _say(message: str) -> None:
    print(f"omniscape_torch: {message}", file=sys.stderr, flush=True)


def _log_entries(log: Path) -> set[str]:
    """The whole lines of ninja's log (``start end mtime output hash``, times in ms), none
    where there is no log yet."""
    try:
        text = log.read_text(errors="replace")
    except FileNotFoundError:
        return set()
    return set(text.split("\n")[:-1])   # the last: empty, or a line being written


def _report(folder: Path, pending: dict[str, str], start: float, stop: threading.Event) -> None:
    """Say on stderr what the build in ``folder`` compiles as it goes, until ``stop``: a line
    as each source of ``pending`` (``{object: source}``) is compiled, as ninja's log records it
    (the log is the build's, also where another process builds and this one waits for it), and
    every `_HEARTBEAT_S` the time so far and what is still compiling (or linking); once more
    after ``stop``, so that a source compiled in the last moments is said too."""
    log = folder / ".ninja_log"
    seen, total = _log_entries(log), len(pending)
    beat = start + _HEARTBEAT_S

    def compiled() -> None:
        for entry in sorted(_log_entries(log) - seen):
            seen.add(entry)
            fields = entry.split("\t")
            if len(fields) >= 4 and fields[3] in pending:
                took = ""
                with contextlib.suppress(ValueError):
                    took = f" in {(int(fields[1]) - int(fields[0])) / 1000:.0f} s"
                _say(f"compiled {pending.pop(fields[3])}{took} ({total - len(pending)} of "
                     f"{total})")

    while not stop.wait(min(1.0, _HEARTBEAT_S / 4)):
        compiled()
        now = time.perf_counter()
        if now >= beat:
            beat = now + _HEARTBEAT_S
            doing = f"still compiling {', '.join(pending.values())}" if pending else "linking"
            _say(f"{now - start:.0f} s: {doing} ...")
    compiled()


@contextlib.contextmanager
def _progress(folder: Path, sources: list[str], paths: list[str], start: float):
    """`_report` on a thread of its own while the block builds the ``.cpp`` files ``paths``
    in ``folder`` (where the files ``sources`` lie), after a line naming those to compile: not
    those whose object is newer than every source (compiled before a build was interrupted),
    which ninja does not compile again."""
    newest = max(os.stat(folder / file).st_mtime_ns for file in sources)
    pending = {}
    for path in map(Path, paths):
        try:
            done = (folder / f"{path.stem}.o").stat().st_mtime_ns > newest
        except FileNotFoundError:
            done = False
        if not done:
            pending[f"{path.stem}.o"] = path.name
    if pending:
        _say(f"compiling {', '.join(pending.values())}")
    stop = threading.Event()
    thread = threading.Thread(target=_report, args=(folder, pending, start, stop),
                              name="omniscape_torch build progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _build() -> str:
    """Load the library, built first where its folder holds none; its path."""
    from torch.utils import cpp_extension
    sources = _sources()
    ext = name(sources)
    folder = Path(cpp_extension._get_build_directory(ext, False))
    library = folder / f"{ext}{_LIB_EXT}"
    # built: the library is there and no build is under way (the lock is taken before the
    # build starts and given back once the library is whole: look for the library first)
    if library.is_file() and not (folder / "lock").exists():
        torch.ops.load_library(str(library))
        return str(library)
    _check_compiler()
    paths = [p for p in _copy_sources(sources, folder) if p.endswith(".cpp")]   # not the .h
    with _ninja_on_path():
        _say("building the C++ kernels for this install (once; 40-220 s on 2 cores, depending "
             f"on load) in {folder} ...")
        start = time.perf_counter()
        with _progress(folder, list(sources), paths, start):
            path = cpp_extension.load(ext, paths, extra_cflags=[*CFLAGS, *face_case_flags()],
                                      extra_ldflags=list(LDFLAGS), build_directory=str(folder),
                                      is_python_module=False)
        _say(f"the C++ kernels built in {time.perf_counter() - start:.1f} s")
    return path


def load() -> torch._ops._OpNamespace:
    """The ops ``torch.ops.omniscape_torch``, built and loaded on the first call (once per
    process; a forked child inherits them).

    Raises:
        RuntimeError: no C++ compiler, no ninja, or the build failed (its output).
        OSError: the cache folder cannot be written.
    """
    with _LOCK:
        if not _LOADED:
            _LOADED.append(_build())
            _register_fakes()
    return getattr(torch.ops, NAMESPACE)


def ops() -> torch._ops._OpNamespace | None:
    """The ops (`load`), or None where they cannot be built, after one ``UserWarning`` in
    the process that says why (`unavailable_reason`): the fast sampler and the town both
    take their torch paths then, and the one build is tried once."""
    if "ops" in _STATE:
        return _STATE["ops"]
    with _LOCK:
        if "ops" not in _STATE:
            try:
                _STATE["ops"] = load()
            except Exception as exc:  # no compiler, no ninja, a read-only cache, ...
                hint = ("; set $TORCH_EXTENSIONS_DIR to a writable folder"
                        if isinstance(exc, OSError) else "")
                _STATE["ops"], _STATE["error"] = None, f"{type(exc).__name__}: {exc}{hint}"
                warnings.warn(f"omniscape_torch: the C++ kernels could not be built "
                              f"({_STATE['error'][:500]}): the fast sampler is unavailable "
                              "(OmniProjection samples with grid_sample on the padded atlas) "
                              "and the town shades with torch (the same labels and depths, "
                              "colours to float32 rounding, several times slower)",
                              UserWarning, stacklevel=3)
    return _STATE["ops"]


def unavailable_reason() -> str | None:
    """Why `ops` is None (``"Error: message"``), else None."""
    return _STATE.get("error")


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


def _fake_box_pixels(rays, rotation, intrinsics, valid, sample, windows, rects, out) -> None:
    _check(rays.dim() == 4 and rays.shape[-1] == 3 and sample.dim() == 1
           and windows.shape == rects.shape == out.shape == (sample.shape[0], 4),
           "box_pixels: expected rays (n, h, w, 3), sample (M,), windows, rects and out (M, 4)")


def _fake_outline_points(rects, counts, owner, offset, points) -> None:
    _check(rects.shape == (counts.shape[0], 4) and owner.shape == counts.shape
           and points.dim() == 3 and points.shape[-1] == 2,
           "outline_points: expected rects (M, 4), counts, owner (M,), points (n, columns, 2)")


def _fake_outline_reduce(pix, ok, through, counts, owner, offset, width, height, near,
                         extents, longest, flags) -> None:
    _check(pix.dim() == 3 and pix.shape[-1] == 2 and ok.shape == through.shape == pix.shape[:2]
           and owner.shape == counts.shape and extents.shape == (counts.shape[0], 8)
           and longest.shape == flags.shape == (counts.shape[0],),
           "outline_reduce: expected pix (n, columns, 2), ok, through (n, columns), counts, "
           "owner (M,), extents (M, 8), longest and flags (M,)")


def _fake_mip_image(image, rays, rotation, intrinsics, valid, minifies, out) -> None:
    _check(image.dim() == 4 and rays.dim() == 4 and rays.shape[-1] == 3
           and out.shape == (image.shape[0], image.shape[1], *rays.shape[1:3]),
           "mip_image: expected image (B, C, H, W), rays (B, h, w, 3), out (B, C, h, w)")


def _fake_framing_reach(rotation, intrinsics, half, cos, sin, height, width, theta) -> None:
    _check(theta.dim() == 2 and theta.shape == (half.shape[0], cos.shape[0]),
           "framing_reach: expected theta (n, D)")


def _fake_framing_focal(radius, to_edge, coverage, height, width, focal) -> None:
    _check(radius.dim() == 2 and focal.shape == coverage.shape == radius.shape[:1],
           "framing_focal: expected radius (n, D), coverage and focal (n,)")


def _fake_reproject_image(image, labels, affine, limits, table, rotation, intrinsics, bilinear,
                          minifies, fill, out, out_labels, valid) -> None:
    _check(valid.dim() == 3 and affine.shape == (valid.shape[0], 6)
           and (out is None or out.shape[:1] + out.shape[2:] == valid.shape)
           and (out_labels is None or out_labels.shape == valid.shape),
           "reproject_image: expected valid (B, h, w), affine (B, 6), out (B, C, h, w), "
           "out_labels (B, h, w)")


def _fake_frame_lens(u, spec, intrinsics, centre, cos, sin, src_height, src_width, radius,
                     slope, per_angle, to_edge, height, width, params, fov, attitude, applied,
                     rotation, coverage) -> None:
    n = fov.shape[0]
    _check(u.shape == (layout.STREAM_WIDTH * n,) and params.shape[0] == n and attitude.shape == (3, n)
           and applied.shape == coverage.shape == (n,) and rotation.shape == (n, 3, 3),
           "frame_lens: expected u (STREAM_WIDTH n,), params (n, P), fov, applied, coverage (n,), "
           "attitude (3, n), rotation (n, 3, 3)")


_FAKES = {"build_lut": _fake_build_lut, "sample_lut": _fake_sample_lut,
          "sample_grid": _fake_sample_grid, "sample_rays": _fake_sample_rays,
          "camera_grid": _fake_camera_grid, "camera_rays": _fake_camera_rays,
          "sample_image": _fake_sample_image, "mip_image": _fake_mip_image,
          "reproject_image": _fake_reproject_image, "frame_lens": _fake_frame_lens,
          "framing_reach": _fake_framing_reach, "framing_focal": _fake_framing_focal,
          "box_pixels": _fake_box_pixels, "outline_points": _fake_outline_points,
          "outline_reduce": _fake_outline_reduce}


def define(schemas: dict[str, str], fakes: dict) -> torch.library.Library:
    """Ops whose schemas live in Python beside their wrappers (the town's, the cone's): each
    ``name + schema`` of ``schemas`` defined in the package's namespace with its fake
    implementation ``fakes[name]`` (for ``torch.compile``), once, at their module's import;
    the C++ library implements them for the CPU when it is loaded. Returns the registration's
    handle: the ops live while it does."""
    lib = torch.library.Library(NAMESPACE, "FRAGMENT")
    for name, schema in schemas.items():
        lib.define(name + schema)
        torch.library.register_fake(f"{NAMESPACE}::{name}", fakes[name], lib=lib)
    return lib


def _register_fakes() -> None:
    for op, fake in _FAKES.items():
        torch.library.register_fake(f"{NAMESPACE}::{op}", fake)
