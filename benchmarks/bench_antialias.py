"""Aliasing of perspective -> fisheye augmentation, quality against speed: every setting of
``RandomReproject`` and of the peers' fisheyes (albumentations, kornia) in one run, PSNR on a
line grid against the ms of a call (issue 36, item 1; issue 47, part 3).

Setup (Cityscapes geometry): a ``uint8`` RGB source of ``--source`` (1024 x 2048) pixels,
pinhole ``fx = fy = 2262 W / 2048`` at the image centre, holding a grid of 1-px lines (255 on
every ``--period``-th row and column, 0 elsewhere: the worst case of a minifying point
sampler); output ``S x S`` for each of ``--sizes`` (512, 1024). Settings:

* ours, ``RandomReproject((S, S))`` at its defaults (equidistant lens, 160-200 deg,
  ``coverage_range`` 0.5-0.9, the default attitudes), ``--samples`` draws from a fixed seed:
  ``point, nearest`` (``interpolation="nearest"``), ``point, bilinear``
  (``antialias=False``), ``prefilter 2 x 2 taps`` (``antialias=True``, the default: the
  C++ ``mip_image``; its taps are not an option), ``supersample s x s`` (the module at
  ``sS x sS``, the same lens scaled, point samples, each ``s x s`` box averaged by
  ``cv2.resize(INTER_AREA)``; `SUPERSAMPLE`), and ``area xF first`` (the source reduced by
  ``cv2.resize(INTER_AREA)`` by ``F``, its intrinsics scaled with it, then point samples
  along the same rays: the cheaper order of albumentations' pipeline; `AREA_FACTORS`);
* albumentations 2: ``Resize(S, S)`` then ``OpticalDistortion(mode="fisheye")`` (the
  default, as ``bench_perspective.py`` calls it: both ``INTER_LINEAR``), at ``INTER_NEAREST``
  or with an ``INTER_AREA`` resize, or the distortion first at full size then the resize;
* kornia: ``Resize((S, S))`` then ``RandomFisheye`` (its docstring's ranges; the default:
  bilinear, no antialias), with a nearest or an ``antialias=True`` resize, or the fisheye
  first at full size; on float32 RGB in [0, 1] (the conversion in the call).

The peers draw ``--peer-samples`` parameter sets from their default ranges (fixed seed; their
geometry is theirs, not a lens). Reference of every setting: the area average of the source
over each output pixel under that setting's own geometry (`supersample`: closed forms written
here, ours from the equidistant and pinhole projections, the peers' from their documented
maps), ``ceil(4 Ws / S)`` samples a pixel per axis (4 a source pixel at the frame's
horizontal scale: 16 at 512, 8 at 1024), each the nearest texel, averaged. PSNR (peak 1, the
first channel) over the output pixels whose samples all see the source (the interior of the
valid region). Time: one call on the ``uint8`` frame (batch 1), ``--threads`` (1) torch and
OpenCV threads, the median of ``--repeats`` rounds over every setting of a size
(round-robin, ``common.measure``); ours and the peers draw their own parameters when timed.

Usage::

    python benchmarks/bench_antialias.py            # S = 512, 1024 (2-4 min on 2 cores)
    python benchmarks/bench_antialias.py --quick    # 256 x 512 -> 64, 128; seconds

Results: markdown on stdout, JSON (``--out``, default ``benchmarks/results/antialias.json``;
``--quick``: ``benchmarks/results/quick/``), the same table as ``antialias.md`` and the chart
(PSNR against ms an image, a panel per size, the defaults ringed) as ``antialias.png``
beside it; ``docs/speed.md`` and ``docs/augmentation.md`` show the chart
(``docs/hooks.py`` publishes ``results/*.png``).
"""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

import torch

try:
    import cv2
except ImportError:   # the supersampled and area rows, and albumentations, are skipped
    cv2 = None
try:
    import albumentations as A
except ImportError:
    A = None
try:
    import kornia
    import kornia.augmentation as KA
except ImportError:
    kornia = KA = None

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_main, run_record)
from omniscape_torch.io.atomic import atomic_path, atomic_write_text  # noqa: E402
from omniscape_torch.augment import RandomReproject  # noqa: E402
from omniscape_torch.render.reference import LabelMapWarning  # noqa: E402

SEED = 20261127
#: Factors of the ``area`` rows' source reduction.
AREA_FACTORS = (1.5, 2.0, 3.0)
#: Our supersampled settings: point samples at ``s S x s S``, each ``s x s`` box averaged.
SUPERSAMPLE = (2, 3)
#: PSNR (dB) the default must reach (issue 36).
TARGET_DB = 25.0
#: Cityscapes' source: 1024 x 2048, fx = fy = 2262.
CITYSCAPES = (1024, 2048, 2262.0)


def line_grid(height: int, width: int, period: int) -> torch.Tensor:
    """``(H, W)`` float64: 1 on every ``period``-th row and column (1-px lines), else 0."""
    rows = torch.arange(height) % period == 0
    cols = torch.arange(width) % period == 0
    return (rows[:, None] | cols[None, :]).double()


def supersample(source: torch.Tensor, mapping, size: tuple[int, int], sub: int = 16,
                chunk: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """The independent reference of a resampling: each output pixel the mean of ``sub x sub``
    samples on a regular subgrid, each the nearest texel of ``source (Hs, Ws)`` at the source
    position that ``mapping`` gives it, 0 where a sample sees no source.

    Args:
        source: ``(Hs, Ws)`` float64.
        mapping: ``fn(x, y) -> (u, v, seen)``: output positions (pixel centres at integers,
            float64, broadcast shapes) to source positions (the same convention) and the
            samples that see the source (within the field of view and every intermediate
            image); it need not check the source's bounds (done here).
        size: ``(H, W)`` of the output.
        sub: samples per axis a pixel.
        chunk: output rows a pass.

    Returns:
        ``(mean (H, W), full (H, W))``, ``full``: every sample of the pixel saw the source.
    """
    hs, ws = source.shape
    h, w = size
    offsets = (torch.arange(sub, dtype=torch.float64) + 0.5) / sub - 0.5
    xs = (torch.arange(w, dtype=torch.float64)[:, None] + offsets).reshape(1, w, 1, sub)
    mean, full = torch.empty(h, w, dtype=torch.float64), torch.empty(h, w, dtype=torch.bool)
    for top in range(0, h, chunk):
        rows = torch.arange(top, min(top + chunk, h), dtype=torch.float64)
        ys = (rows[:, None] + offsets).reshape(-1, 1, sub, 1)
        x, y = torch.broadcast_tensors(xs, ys)
        u, v, seen = mapping(x, y)
        seen = seen & (u >= -0.5) & (u <= ws - 0.5) & (v >= -0.5) & (v <= hs - 0.5)
        iu = torch.floor(u + 0.5).clamp(0, ws - 1).long()
        iv = torch.floor(v + 0.5).clamp(0, hs - 1).long()
        value = torch.where(seen, source[iv, iu], torch.zeros_like(u))
        mean[top:top + len(rows)] = value.mean((-1, -2))
        full[top:top + len(rows)] = seen.all(-1).all(-1)
    return mean, full


def fisheye_mapping(intrinsics: torch.Tensor, params: dict, index: int):
    """Draw ``index`` of ``params`` (an equidistant fisheye: ``fx = fy = f``, centre ``cx,
    cy``, half field of view ``fov / 2``, rotation ``R``: ``ray_src = R @ ray``) into the
    pinhole ``intrinsics`` (``fx, fy, cx, cy``), in closed form: `supersample`'s mapping."""
    assert params["model"][index] == "equidistant"
    f, _, cx, cy = params["camera_params"][index, :4].tolist()
    half = float(params["fov"][index]) / 2
    rot = params["rotation"][index].double()
    sfx, sfy, scx, scy = (float(v) for v in intrinsics)

    def mapping(x, y):
        dx, dy = x - cx, y - cy
        r = torch.hypot(dx, dy)
        theta = r / f
        s = torch.where(r > 0, torch.sin(theta) / r.clamp_min(1e-300), torch.full_like(r, 1 / f))
        ray = torch.stack((s * dx, s * dy, torch.cos(theta)), -1) @ rot.T
        z = ray[..., 2]
        return (sfx * ray[..., 0] / z + scx, sfy * ray[..., 1] / z + scy,
                (theta <= half) & (z > 0))
    return mapping


def area_average(source: torch.Tensor, intrinsics: torch.Tensor, params: dict, index: int,
                 size: tuple[int, int], sub: int = 16, chunk: int = 16
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """`supersample` of draw ``index`` of ``params`` seen from a pinhole source of
    ``intrinsics`` (`fisheye_mapping`): ``(mean (H, W), full (H, W))``."""
    return supersample(source, fisheye_mapping(intrinsics, params, index), size, sub, chunk)


def psnr(image: torch.Tensor, reference: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB, peak 1) of ``image`` against ``reference`` over ``mask``."""
    mse = float(((image.double() - reference) ** 2)[mask].mean())
    return math.inf if mse == 0 else 10 * math.log10(1 / mse)


def compare(size: tuple[int, int], source_shape: tuple[int, int, float], period: int,
            samples: int, seed: int, **module_kwargs) -> dict:
    """PSNR of each row for ``samples`` draws of ``RandomReproject(size, **module_kwargs)``
    (its defaults otherwise) on the line grid: ``{"off": [...], "on": [...], "area x1.5":
    [...], ..., "coverage": [...], "valid": [...]}`` per draw, the rows' ``calls`` (``fn(params
    =None)``, for timing) and the ``modules`` ``off`` and ``on``."""
    hs, ws, focal = source_shape
    source = line_grid(hs, ws, period)
    intrinsics = torch.tensor([focal, focal, (ws - 1) / 2, (hs - 1) / 2], dtype=torch.float64)
    image = source.float()[None, None]
    modules = {name: RandomReproject(size, seed=seed, antialias=name == "on", **module_kwargs)
               for name in ("off", "on")}
    calls = {name: (lambda module: lambda params=None: module(
        {"rgb": image, "intrinsics": intrinsics}, params=params))(module)
        for name, module in modules.items()}
    if cv2 is not None:
        for factor in AREA_FACTORS:
            calls[f"area x{factor:g}"] = area_call(modules["off"], source, intrinsics, factor)
    params = modules["on"].forward_parameters(samples, intrinsics=intrinsics,
                                              source_size=(hs, ws))
    out = {**{name: [] for name in calls}, "coverage": [], "valid": []}
    for i in range(samples):
        one = {key: value[i:i + 1] for key, value in params.items()}
        reference, full = area_average(source, intrinsics, params, i, size)
        for name, call in calls.items():
            rendered = call(one)
            out[name].append(psnr(rendered["rgb"][0, 0], reference, full))
            if name == "on":
                out["valid"].append(float(rendered["valid"].float().mean()))
        out["coverage"].append(float(params["coverage"][i]))
    out["calls"], out["modules"] = calls, modules
    return out


def area_call(module: RandomReproject, source: torch.Tensor, intrinsics: torch.Tensor,
              factor: float):
    """A call of ``module`` (point samples) on ``source`` (``(Hs, Ws)`` floating, or the
    ``(Hs, Ws, C)`` frame of a ``channels_last`` module) reduced by ``cv2.resize(...,
    INTER_AREA)`` by ``factor``, with the intrinsics of the reduced image (pixel centres at
    integers: ``f / s``, ``(c + 0.5) / s - 0.5`` per axis): ``fn(params=None) -> output``."""
    hs, ws = source.shape[:2]
    small_size = (round(ws / factor), round(hs / factor))
    sx, sy = ws / small_size[0], hs / small_size[1]
    fx, fy, cx, cy = intrinsics.tolist()
    k = torch.tensor([fx / sx, fy / sy, (cx + 0.5) / sx - 0.5, (cy + 0.5) / sy - 0.5],
                     dtype=torch.float64)
    full = (source.float() if source.dim() == 2 else source).numpy()

    def call(params=None):
        small = torch.from_numpy(cv2.resize(full, small_size, interpolation=cv2.INTER_AREA))
        return module({"rgb": small[None, None] if small.dim() == 2 else small[None],
                       "intrinsics": k}, params=params)
    return call


# --------------------------------------------------------------------------------------------
# The chart: every setting of ours and of the peers, PSNR against ms an image
# --------------------------------------------------------------------------------------------

def resize_mapping(inner: tuple[int, int], outer: tuple[int, int], corners: bool = False):
    """A resize's source position of an output position: ``outer (H, W)`` read from ``inner
    (h, w)`` pixels, pixel centres matched (OpenCV's ``resize``: ``(x + 0.5) W / w - 0.5``)
    or, ``corners``, corner pixels matched (kornia's ``align_corners=True``: ``x (W - 1) /
    (w - 1)``): ``fn(x, y) -> (u, v)``."""
    (h, w), (hs, ws) = inner, outer
    if corners:
        return lambda x, y: (x * (ws - 1) / (w - 1), y * (hs - 1) / (h - 1))
    return lambda x, y: ((x + 0.5) * ws / w - 0.5, (y + 0.5) * hs / h - 0.5)


def album_fisheye(k: float, size: tuple[int, int]):
    """albumentations' fisheye (``OpticalDistortion(mode="fisheye")``, 2.0) on an image of
    ``size (h, w)``, from its closed form (``functional.get_fisheye_distortion_maps``): the
    position ``c + (p - c) (1 + k |p - c|^2 / R^2)``, ``c = (w / 2, h / 2)``, ``R = |c|``,
    read by ``cv2.remap``: ``fn(x, y) -> (u, v)``."""
    h, w = size
    cx, cy = w / 2, h / 2
    r2 = cx * cx + cy * cy

    def mapping(x, y):
        dx, dy = x - cx, y - cy
        scale = 1 + k * (dx * dx + dy * dy) / r2
        return cx + dx * scale, cy + dy * scale
    return mapping


def kornia_fisheye(cx: float, cy: float, gamma: float, size: tuple[int, int]):
    """kornia's ``RandomFisheye`` (0.9) on an image of ``size (h, w)``, from its closed form:
    normalised positions ``n = 2 p / (size - 1) - 1`` (``align_corners=True``), ``n + n
    d^gamma`` with ``d`` the distance of ``n`` from ``(cx, cy)``, back to pixels: ``fn(x, y)
    -> (u, v)``."""
    h, w = size

    def mapping(x, y):
        nx, ny = 2 * x / (w - 1) - 1, 2 * y / (h - 1) - 1
        d = torch.hypot(cx - nx, cy - ny) ** gamma
        return (nx + nx * d + 1) * (w - 1) / 2, (ny + ny * d + 1) * (h - 1) / 2
    return mapping


def chain(*steps: tuple):
    """`supersample`'s mapping of output positions through ``steps``, each ``(fn, size)``:
    ``fn(x, y) -> (u, v)`` into an image of ``size (h, w)``, the output's step first; a sample
    sees the source where every intermediate image holds it (the last one's bounds are
    `supersample`'s)."""
    def mapping(x, y):
        seen = torch.ones_like(x, dtype=torch.bool)
        for i, (fn, (h, w)) in enumerate(steps):
            x, y = fn(x, y)
            if i < len(steps) - 1:
                seen &= (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
        return x, y, seen
    return mapping


def _scaled(params: dict, s: int) -> dict:
    """``params`` of a fisheye drawn for ``S x S`` as the same lens at ``sS x sS``."""
    cam = params["camera_params"].clone()
    cam[:, :2] *= s
    cam[:, 2:4] = (cam[:, 2:4] + 0.5) * s - 0.5
    return dict(params, camera_params=cam)


def _ours(size: int, frame: torch.Tensor, k: torch.Tensor, draws: dict) -> list[dict]:
    """Our settings: ``{name, family, default, geometry, call(draw or None) -> (S, S) float
    in [0, 1]}``; ``draw``: an index into ``draws`` (``forward_parameters``), None: drawn by
    the module (timing)."""
    def setting(name, short, fn, scale=1, default=False):
        """``fn(params) -> output`` as a row; ``scale``: ``fn`` renders at ``scale S``."""
        def call(i=None):
            params = None if i is None else {key: v[i:i + 1] for key, v in draws.items()}
            rgb = fn(params if params is None or scale == 1 else _scaled(params, scale))["rgb"]
            if scale > 1:   # each scale x scale box: OpenCV's area reduction
                rgb = torch.from_numpy(cv2.resize(rgb[0].numpy(), (size, size),
                                                  interpolation=cv2.INTER_AREA))[None]
            return rgb[0, ..., 0].float() / 255
        return {"name": name, "short": short, "family": "ours", "default": default,
                "geometry": "ours", "call": call}

    def plain(module):
        return lambda params: module({"rgb": frame[None], "intrinsics": k}, params=params)

    def module(side=size, **kwargs):
        return RandomReproject((side, side), seed=SEED, channels_last=True, **kwargs)

    rows = [setting("point, nearest", "nearest",
                    plain(module(interpolation="nearest", antialias=False))),
            setting("point, bilinear", "bilinear", plain(module(antialias=False))),
            setting("prefilter 2 x 2 taps", "prefilter", plain(module(antialias=True)),
                    default=True)]
    if cv2 is not None:   # (the box averages and the area reductions are OpenCV's)
        rows += [setting(f"supersample {s} x {s}, bilinear", f"supersample {s}x{s}",
                         plain(module(s * size, antialias=False)), scale=s)
                 for s in SUPERSAMPLE]
        point = module(antialias=False)
        rows += [setting(f"area x{factor:g} first, bilinear",
                         f"area x{factor:g} \u2192 bilinear",
                         area_call(point, frame, k, factor)) for factor in AREA_FACTORS]
    return rows


def _albumentations(size: int, frame: torch.Tensor) -> list[dict]:
    """albumentations' settings (``Resize`` and ``OpticalDistortion(mode="fisheye")``, in
    either order, at their interpolations); ``call(k or None)``: the distortion coefficient
    of a draw, None: drawn by the peer from its default range (timing)."""
    image = frame.numpy()
    inter = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR,
             "area": cv2.INTER_AREA}
    rows = []
    for first, resize, distort in (("resize", "linear", "linear"),
                                   ("resize", "nearest", "nearest"),
                                   ("resize", "area", "linear"),
                                   ("distort", "area", "linear"),
                                   ("distort", "linear", "linear")):
        def build(k=None, first=first, resize=resize, distort=distort):
            limit = {} if k is None else {"distort_limit": (k, k)}
            steps = [A.Resize(size, size, interpolation=inter[resize]),
                     A.OpticalDistortion(mode="fisheye", interpolation=inter[distort], p=1.0,
                                         **limit)]
            return A.Compose(steps if first == "resize" else steps[::-1], seed=SEED)

        timed = build()   # (built once, as a user does; the fixed draws' untimed)

        def call(k=None, build=build, timed=timed):
            pipeline = timed if k is None else build(k)
            return torch.from_numpy(pipeline(image=image)["image"][..., 0]).float() / 255
        steps = (f"resize {resize}", f"fisheye {distort}")
        if first == "resize":
            name = f"Resize {resize}, then fisheye {distort}"
        else:
            name, steps = f"fisheye {distort} at full size, then Resize {resize}", steps[::-1]
        rows.append({"name": name, "short": " \u2192 ".join(steps),
                     "family": "albumentations", "geometry": f"album {first}",
                     "default": (first, resize, distort) == ("resize", "linear", "linear"),
                     "call": call})
    return rows


def _kornia(size: int, frame: torch.Tensor) -> list[dict]:
    """kornia's settings (``Resize`` and ``RandomFisheye``, in either order, its resampling
    and ``antialias``), on float32 RGB in [0, 1] (converted in the call); ``call(draw or
    None)``: ``(cx, cy, gamma)``, None: drawn by the peer (its docstring's ranges)."""
    x = frame.permute(2, 0, 1)[None]
    rows = []
    ranges = (torch.tensor([-0.3, 0.3]), torch.tensor([-0.3, 0.3]), torch.tensor([0.9, 1.0]))
    for first, resample, smooth in (("resize", "BILINEAR", False), ("resize", "NEAREST", False),
                                    ("resize", "BILINEAR", True), ("fisheye", "BILINEAR", True),
                                    ("fisheye", "BILINEAR", False)):
        resize = KA.Resize((size, size), resample=resample, antialias=smooth)
        timed = KA.RandomFisheye(*ranges, p=1.0)

        def call(draw=None, first=first, resize=resize, timed=timed):
            fisheye = timed if draw is None else KA.RandomFisheye(
                *(torch.tensor([v, v]) for v in draw), p=1.0)
            image = x.float() / 255
            out = fisheye(resize(image)) if first == "resize" else resize(fisheye(image))
            return out[0, 0]
        aa = ", antialias" if smooth else ""
        name = (f"Resize {resample.lower()}{aa}, then RandomFisheye" if first == "resize" else
                f"RandomFisheye at full size, then Resize {resample.lower()}{aa}")
        steps = (f"resize {resample.lower()}{'+aa' if smooth else ''}", "fisheye")
        short = " \u2192 ".join(steps if first == "resize" else steps[::-1])
        rows.append({"name": name, "short": short, "family": "kornia",
                     "geometry": f"kornia {first}",
                     "default": (first, resample, smooth) == ("resize", "BILINEAR", False),
                     "call": call})
    return rows


def _references(source: torch.Tensor, k: torch.Tensor, size: int, draws: dict,
                sub: int) -> dict:
    """``{geometry: [(mean, full) per draw]}``: `supersample` of every geometry the settings
    take, for their draws (``draws``: ``ours`` the module's parameters, ``albumentations``
    the coefficients, ``kornia`` the ``(cx, cy, gamma)``)."""
    hs, ws = source.shape
    out_size, src = (size, size), (hs, ws)
    to_src = resize_mapping(out_size, src)
    to_src_corners = resize_mapping(out_size, src, corners=True)
    maps = {"ours": [fisheye_mapping(k, draws["ours"], i)
                     for i in range(len(draws["ours"]["model"]))]}
    if "albumentations" in draws:
        maps["album resize"] = [chain((album_fisheye(c, out_size), out_size), (to_src, src))
                                for c in draws["albumentations"]]
        maps["album distort"] = [chain((to_src, src), (album_fisheye(c, src), src))
                                 for c in draws["albumentations"]]
    if "kornia" in draws:
        maps["kornia resize"] = [chain((kornia_fisheye(*d, out_size), out_size),
                                       (to_src_corners, src)) for d in draws["kornia"]]
        maps["kornia fisheye"] = [chain((to_src_corners, src), (kornia_fisheye(*d, src), src))
                                  for d in draws["kornia"]]
    return {name: [supersample(source, m, out_size, sub) for m in ms]
            for name, ms in maps.items()}


def run_size(size: int, source_shape: tuple[int, int, float], args: argparse.Namespace
             ) -> dict:
    """Every setting at output ``size``: PSNR per draw against `supersample` of its own
    geometry, and ms an image (one call, ``uint8`` RGB ``(Hs, Ws, 3)``, round-robin medians
    over all the settings)."""
    hs, ws, focal = source_shape
    source = line_grid(hs, ws, args.period)
    frame = (source * 255).to(torch.uint8)[..., None].expand(hs, ws, 3).contiguous()
    k = torch.tensor([focal, focal, (ws - 1) / 2, (hs - 1) / 2], dtype=torch.float64)
    gen = torch.Generator().manual_seed(SEED + size)
    draws = {"ours": RandomReproject((size, size), seed=SEED).forward_parameters(
        args.samples, intrinsics=k, source_size=(hs, ws), generator=gen)}
    rows = _ours(size, frame, k, draws["ours"])
    skipped = {}
    n = args.peer_samples
    if A is not None:
        draws["albumentations"] = (torch.rand(n, generator=gen, dtype=torch.float64) * 0.1
                                   - 0.05).tolist()
        rows += _albumentations(size, frame)
    else:
        skipped["albumentations"] = "not importable"
    if KA is not None:
        u = torch.rand(n, 3, generator=gen, dtype=torch.float64)
        draws["kornia"] = [(0.6 * a - 0.3, 0.6 * b - 0.3, 0.9 + 0.1 * g)
                           for a, b, g in u.tolist()]
        rows += _kornia(size, frame)
    else:
        skipped["kornia"] = "not importable"
    sub = max(1, math.ceil(4 * ws / size))   # 4 samples a source pixel at the frame's scale
    refs = _references(source, k, size, draws, sub)
    family_draws = {"ours": list(range(args.samples)),
                    "albumentations": draws.get("albumentations"), "kornia": draws.get("kornia")}
    with torch.no_grad():
        for row in rows:
            row["psnr_db"] = [psnr(row["call"](d), *ref) for d, ref in
                              zip(family_draws[row["family"]], refs[row["geometry"]])]
        times = measure([row["call"] for row in rows], args.repeats, args.warmup)
    out = []
    for row, t in zip(rows, times):
        values = row["psnr_db"]
        out.append({"size": size, "name": row["name"], "short": row["short"],
                    "family": row["family"],
                    "default": row["default"], "geometry": row["geometry"], "psnr_db": values,
                    "mean_psnr_db": sum(values) / len(values), "min_psnr_db": min(values),
                    "median_s": t["median_s"], "iqr_s": t["iqr_s"], "times_s": t["times_s"]})
    return {"rows": out, "skipped": skipped, "subsamples": sub,
            "draws": {"ours_coverage": draws["ours"]["coverage"].tolist(),
                      "albumentations_k": draws.get("albumentations"),
                      "kornia_cx_cy_gamma": draws.get("kornia")}}


def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(args.threads, cv2)
    hs, ws = args.source
    source_shape = (hs, ws, CITYSCAPES[2] * ws / CITYSCAPES[1])
    with warnings.catch_warnings():
        # (an image of two levels in three equal channels: no label map, as it looks)
        warnings.simplefilter("ignore", LabelMapWarning)
        sizes = [run_size(size, source_shape, args) for size in args.sizes]
    rows = [row for res in sizes for row in res["rows"]]
    headline = []
    for size in args.sizes:
        here = [r for r in rows if r["size"] == size]
        ours = next(r for r in here if r["family"] == "ours" and r["default"])
        point = next(r for r in here if r["name"] == "point, bilinear")
        line = {"size": size, "min_psnr_default_db": ours["min_psnr_db"],
                "target_db": TARGET_DB, "meets_target": ours["min_psnr_db"] >= TARGET_DB,
                "cost_ratio_default_point": ours["median_s"] / point["median_s"]}
        for r in here:
            if r["family"] != "ours" and r["default"]:
                line[f"time_ratio_default_{r['family']}"] = ours["median_s"] / r["median_s"]
        headline.append(line)
    return {
        **run_record("antialias", torch.device("cpu"), args.threads, cv2),
        "versions_peers": {"albumentations": getattr(A, "__version__", None),
                           "kornia": getattr(kornia, "__version__", None)},
        "setup": {"source": list(source_shape), "sizes": args.sizes, "period": args.period,
                  "samples": args.samples, "peer_samples": args.peer_samples, "seed": SEED,
                  "subsamples": {str(r["rows"][0]["size"]): r["subsamples"] for r in sizes},
                  "repeats": args.repeats, "warmup": args.warmup, "quick": args.quick},
        "draws": {str(size): res["draws"] for size, res in zip(args.sizes, sizes)},
        "rows": rows, "skipped": {k: v for res in sizes for k, v in res["skipped"].items()},
        "headline": headline, "loadavg_start": load_start, "loadavg_end": loadavg(),
    }


def markdown(result: dict) -> str:
    s = result["setup"]
    src = s["source"]
    lines = [(f"antialias: line grid (period {s['period']}) {src[1]} x {src[0]} uint8 RGB "
             f"(fx {src[2]:g}) -> S x S; ours: RandomReproject's default lens range, "
             f"{s['samples']} draws; peers: {s['peer_samples']} draws of their default "
             f"ranges; reference: the area average of each setting's own geometry "
             f"({', '.join(f'S={k}: {v}^2' for k, v in s['subsamples'].items())} samples a "
             f"pixel); {result['threads']} thread(s), load {_load(result['loadavg_start'])} "
             f"-> {_load(result['loadavg_end'])}, commit {result['commit'][:12]}"
             f"{' (dirty)' if result['dirty'] else ''}"), "",
             ("| S | family | setting | PSNR per draw (dB) | mean dB | min dB | median ms | "
              "IQR ms |"), "|---:|---|---|---|---:|---:|---:|---:|"]
    for r in result["rows"]:
        name = f"**{r['name']}** (default)" if r["default"] else r["name"]
        lines.append(f"| {r['size']} | {r['family']} | {name} | "
                     f"{', '.join(f'{v:.1f}' for v in r['psnr_db'])} | "
                     f"{r['mean_psnr_db']:.1f} | {r['min_psnr_db']:.1f} | "
                     f"{1e3 * r['median_s']:.1f} | {1e3 * r['iqr_s']:.1f} |")
    lines.append("")
    for name, why in result["skipped"].items():
        lines.append(f"skipped {name}: {why}")
    for h in result["headline"]:
        peers = "".join(f"; time / {key.rsplit('_', 1)[1]}'s default {v:.2f}x"
                        for key, v in h.items() if key.startswith("time_ratio"))
        lines.append(f"S={h['size']}: our default's min PSNR {h['min_psnr_default_db']:.1f} dB "
                     f"(target >= {h['target_db']:.0f}: "
                     f"{'ok' if h['meets_target'] else 'MISSED'}); cost / point "
                     f"{h['cost_ratio_default_point']:.2f}x{peers}")
    return "\n".join(lines)


def _load(load) -> str:
    return "?" if load is None else ", ".join(f"{v:.2f}" for v in load)


_STYLE = {"ours": ("o", "tab:blue"), "albumentations": ("s", "tab:red"),
          "kornia": ("^", "tab:green")}


def frontier(rows: list[dict]) -> list[dict]:
    """The rows no other row beats in both time and mean PSNR, fastest first."""
    best, out = -math.inf, []
    for r in sorted(rows, key=lambda r: (r["median_s"], -r["mean_psnr_db"])):
        if r["mean_psnr_db"] > best:
            best = r["mean_psnr_db"]
            out.append(r)
    return out


def _place_labels(ax, labels: list) -> None:
    """Each point's short name to its right, moved down past the names already placed that it
    would overlap (top to bottom; display units, the axes' limits set)."""
    placed = []   # (x, y, width) of the names placed, display pixels
    for xi, yi, r, colour in sorted(labels, key=lambda t: -t[1]):
        px, py = ax.transData.transform((xi, yi))
        text = r["short"] + (" (default)" if r["default"] else "")
        width = 4.3 * len(text)   # ~pixels of a 7.5-point name
        dy = 0.0
        while any(abs(px - qx) < max(width, qw) and abs(py - dy - qy) < 10
                  for qx, qy, qw in placed):
            dy += 10
        placed.append((px, py - dy, width))
        ax.annotate(text, (xi, yi), textcoords="offset pixels",
                    xytext=(14 if r["default"] else 8, 2 - dy),
                    fontsize=7.5, color=colour, va="center",
                    fontweight="bold" if r["default"] else "normal",
                    arrowprops=dict(arrowstyle="-", color=colour, lw=0.5, alpha=0.6)
                    if dy else None)


def chart(result: dict, path: Path) -> None:
    """``path`` (PNG): mean PSNR (the draws' range as a bar) against ms an image (log), one
    panel per output size (a shared PSNR axis), one marker and colour per family, each point
    named, the defaults ringed, the frontier of all settings drawn."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    sizes = result["setup"]["sizes"]
    fig = Figure(figsize=(7.5 * len(sizes), 7.5), layout="constrained")
    axes = fig.subplots(1, len(sizes), squeeze=False, sharey=True)[0]
    top = max(v for r in result["rows"] for v in r["psnr_db"] if math.isfinite(v)) + 3
    for ax, size in zip(axes, sizes):
        rows = [r for r in result["rows"] if r["size"] == size]
        front, labels = frontier(rows), []
        ax.step([1e3 * r["median_s"] for r in front], [r["mean_psnr_db"] for r in front],
                where="post", color="black", linewidth=0.8, alpha=0.6,
                label="frontier (no setting faster and better)", zorder=2)
        for family, (marker, colour) in _STYLE.items():
            mine = [r for r in rows if r["family"] == family]
            if not mine:
                continue
            x = [1e3 * r["median_s"] for r in mine]
            y = [r["mean_psnr_db"] for r in mine]
            err = [[r["mean_psnr_db"] - r["min_psnr_db"] for r in mine],
                   [max(r["psnr_db"]) - r["mean_psnr_db"] for r in mine]]
            ax.errorbar(x, y, yerr=err, fmt=marker, color=colour, ms=7, capsize=2,
                        elinewidth=0.8, label=family, zorder=3)
            for r, xi, yi in zip(mine, x, y):
                if r["default"]:
                    ax.scatter([xi], [yi], s=260, facecolors="none", edgecolors="black",
                               linewidths=1.5, zorder=4,
                               label="a default" if family == "ours" else None)
                labels.append((xi, yi, r, colour))
        ax.axhline(TARGET_DB, color="gray", linestyle=":", linewidth=1,
                   label=f"{TARGET_DB:g} dB (issue 36's target)")
        ax.set_xscale("log")
        lo, hi = ax.get_xlim()
        ax.set_xlim(lo, hi * 3)   # room for the labels of the slowest points
        ax.set_ylim(0, top)
        _place_labels(ax, labels)
        threads = f"{result['threads']} thread{'s' if result['threads'] > 1 else ''}"
        ax.set_xlabel(f"ms an image (median; {threads}; uint8 RGB in, batch 1; log scale)")
        src = result["setup"]["source"]
        ax.set_title(f"{src[1]} x {src[0]} line grid -> {size} x {size} "
                     "(upper left is better)", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    axes[0].set_ylabel("PSNR on the line grid (dB; mean of the draws, bar: min to max)")
    fig.suptitle("Perspective -> fisheye, quality against speed: every setting of "
                 "RandomReproject, albumentations and kornia in one run "
                 f"(commit {result['commit'][:8]}, load {_load(result['loadavg_start'])})",
                 fontsize=11)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=100)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=positive_int, nargs="+", default=None,
                        help="output sides S (512 1024; 64 128 quick)")
    parser.add_argument("--source", type=positive_int, nargs=2, default=None,
                        metavar=("H", "W"), help="source size (1024 2048; 256 512 quick); "
                        "fx = fy = 2262 W / 2048")
    parser.add_argument("--period", type=positive_int, default=8, help="line spacing (8)")
    parser.add_argument("--samples", type=positive_int, default=None,
                        help="our draws (4; 2 quick)")
    parser.add_argument("--peer-samples", type=positive_int, default=None,
                        help="each peer's draws (2; 1 quick)")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="torch and OpenCV threads (1)")
    parser.add_argument("--repeats", type=positive_int, default=None, help="timed rounds (7; 3)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed rounds (1)")
    parser.add_argument("--quick", action="store_true", help="a smoke run (seconds)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON output (.md and .png beside it)")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = results_path("antialias.json", quick=args.quick)
    defaults = {"sizes": ([512, 1024], [64, 128]), "source": ([1024, 2048], [256, 512]),
                "samples": (4, 2), "peer_samples": (2, 1), "repeats": (7, 3)}
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    return args


def main(argv=None) -> int:
    args_holder: list = []

    def parse(argv):
        args_holder.append(parse_args(argv))
        return args_holder[0]

    def write(result: dict) -> str:
        text = markdown(result)
        out = args_holder[0].out
        atomic_write_text(out.with_suffix(".md"), text + "\n")
        chart(result, out.with_suffix(".png"))
        return text
    return run_main(parse, run, write, argv)


if __name__ == "__main__":
    sys.exit(main())
