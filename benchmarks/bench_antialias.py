"""Aliasing of perspective -> fisheye augmentation: ``RandomReproject`` with and without its mip
prefilter, against the area average of the source over each output pixel (issue 36, item 1).

Setup (Cityscapes geometry): a source of 1024 x 2048 pixels, pinhole ``fx = fy = 2262`` at the
image centre, holding a grid of 1-px lines (value 1 on every ``--period``-th row and column,
0 elsewhere: the worst case of a minifying point sampler); ``RandomReproject((S, S))`` at its
defaults (equidistant lens, 160-200 deg, ``coverage_range`` 0.5-0.9, the default attitudes),
``S = 512``; ``--samples`` draws from a fixed seed. Reference: an independent supersampler
written here from the closed forms (equidistant unprojection ``theta = r / f``, the drawn
rotation, the pinhole projection, nearest source texel), ``16 x 16`` samples per output pixel,
averaged. PSNR (peak 1) over the output pixels whose 256 samples all see the source (the
interior of the valid region; at its rim a pixel is part source, part void).

Rows: ``off`` (``antialias=False``: one bilinear sample per pixel) and ``on``
(``antialias=True``, the default: ``fast.mip_image``), PSNR per draw and their mean, and the
time of one call (batch 1, float32 image, one thread, median of ``--repeats`` round-robin
calls) of each; and ``area xS`` for S in ``AREA_FACTORS``:
the cheaper order of albumentations' pipeline (``Resize``, then the distortion), the source
reduced by ``cv2.resize(..., INTER_AREA)`` by S (its intrinsics scaled with it: ``f / S``,
``(c + 0.5) / S - 0.5``), then point samples along the same rays (``antialias=False``), the
reduction timed in the call (skipped, and said so, without OpenCV).

Usage::

    python benchmarks/bench_antialias.py            # 1024 x 2048 -> 512 x 512, 4 draws
    python benchmarks/bench_antialias.py --quick    # 256 x 512 -> 128 x 128, 2 draws

Results: markdown on stdout, JSON (``--out``, default ``benchmarks/results/antialias.json``;
``--quick``: ``benchmarks/results/quick/``) and the same table as ``antialias.md`` beside it.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

try:
    import cv2
except ImportError:   # the area rows are skipped
    cv2 = None

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_main, run_record)
from omniscape_torch.io import atomic_write_text  # noqa: E402
from omniscape_torch.augment import RandomReproject  # noqa: E402

SEED = 20261127
#: Factors of the ``area`` rows' source reduction.
AREA_FACTORS = (1.5, 2.0, 3.0)
#: PSNR (dB) the default must reach (issue 36).
TARGET_DB = 25.0
#: Cityscapes' source: 1024 x 2048, fx = fy = 2262.
CITYSCAPES = (1024, 2048, 2262.0)


def line_grid(height: int, width: int, period: int) -> torch.Tensor:
    """``(H, W)`` float64: 1 on every ``period``-th row and column (1-px lines), else 0."""
    rows = torch.arange(height) % period == 0
    cols = torch.arange(width) % period == 0
    return (rows[:, None] | cols[None, :]).double()


def area_average(source: torch.Tensor, intrinsics: torch.Tensor, params: dict, index: int,
                 size: tuple[int, int], sub: int = 16, chunk: int = 16
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The independent reference: each output pixel of draw ``index`` of ``params`` (an
    equidistant fisheye: ``fx = fy = f``, centre ``cx, cy``, half field of view ``fov / 2``,
    rotation ``R``: ``ray_src = R @ ray``) as the mean of ``sub x sub`` samples on a regular
    subgrid, each the nearest texel of ``source (Hs, Ws)`` seen by the pinhole ``intrinsics``
    (``fx, fy, cx, cy``), 0 where a sample sees no source.

    Returns:
        ``(mean (H, W), full (H, W))``, ``full``: every sample of the pixel saw the source.
    """
    assert params["model"][index] == "equidistant"
    f, _, cx, cy = params["camera_params"][index, :4].tolist()
    half = float(params["fov"][index]) / 2
    rot = params["rotation"][index].double()
    sfx, sfy, scx, scy = (float(v) for v in intrinsics)
    hs, ws = source.shape
    h, w = size
    offsets = (torch.arange(sub, dtype=torch.float64) + 0.5) / sub - 0.5
    xs = (torch.arange(w, dtype=torch.float64)[:, None] + offsets).reshape(1, w, 1, sub)
    mean, full = torch.empty(h, w, dtype=torch.float64), torch.empty(h, w, dtype=torch.bool)
    for top in range(0, h, chunk):
        rows = torch.arange(top, min(top + chunk, h), dtype=torch.float64)
        ys = (rows[:, None] + offsets).reshape(-1, 1, sub, 1)
        dx, dy = torch.broadcast_tensors(xs - cx, ys - cy)
        r = torch.hypot(dx, dy)
        theta = r / f
        s = torch.where(r > 0, torch.sin(theta) / r.clamp_min(1e-300), torch.full_like(r, 1 / f))
        ray = torch.stack((s * dx, s * dy, torch.cos(theta)), -1) @ rot.T
        z = ray[..., 2]
        u = sfx * ray[..., 0] / z + scx
        v = sfy * ray[..., 1] / z + scy
        seen = (theta <= half) & (z > 0) & (u >= -0.5) & (u <= ws - 0.5) & (v >= -0.5) & \
            (v <= hs - 0.5)
        iu = torch.floor(u + 0.5).clamp(0, ws - 1).long()
        iv = torch.floor(v + 0.5).clamp(0, hs - 1).long()
        value = torch.where(seen, source[iv, iu], torch.zeros_like(u))
        mean[top:top + len(rows)] = value.mean((-1, -2))
        full[top:top + len(rows)] = seen.all(-1).all(-1)
    return mean, full


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
        one = {key: (value[i:i + 1] if isinstance(value, torch.Tensor) else value[i:i + 1])
               for key, value in params.items()}
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
    """A call of ``module`` (point samples) on ``source`` reduced by ``cv2.resize(...,
    INTER_AREA)`` by ``factor``, with the intrinsics of the reduced image (pixel centres at
    integers: ``f / s``, ``(c + 0.5) / s - 0.5`` per axis): ``fn(params=None) -> output``."""
    hs, ws = source.shape
    small_size = (round(ws / factor), round(hs / factor))
    sx, sy = ws / small_size[0], hs / small_size[1]
    fx, fy, cx, cy = intrinsics.tolist()
    k = torch.tensor([fx / sx, fy / sy, (cx + 0.5) / sx - 0.5, (cy + 0.5) / sy - 0.5],
                     dtype=torch.float64)
    full = source.float().numpy()

    def call(params=None):
        small = cv2.resize(full, small_size, interpolation=cv2.INTER_AREA)
        return module({"rgb": torch.from_numpy(small)[None, None], "intrinsics": k},
                      params=params)
    return call


def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(args.threads)
    size = (args.size, args.size)
    scale = args.size / 512
    hs, ws, focal = CITYSCAPES
    source_shape = (round(hs * scale), round(ws * scale), focal * scale)
    res = compare(size, source_shape, args.period, args.samples, SEED)
    calls = res.pop("calls")
    res.pop("modules")
    with torch.no_grad():
        times = measure(list(calls.values()), args.repeats, args.warmup)
    rows = []
    for name, t in zip(calls, times):
        values = res[name]
        rows.append({"name": name, "psnr_db": values, "mean_psnr_db": sum(values) / len(values),
                     "min_psnr_db": min(values), "median_s": t["median_s"], "iqr_s": t["iqr_s"],
                     "times_s": t["times_s"]})
    on = rows[1]
    return {
        **run_record("antialias", torch.device("cpu"), args.threads),
        "setup": {"source": list(source_shape), "output": list(size), "period": args.period,
                  "samples": args.samples, "seed": SEED, "subsamples": 16,
                  "repeats": args.repeats, "quick": args.quick},
        "coverage_drawn": res["coverage"], "valid_fraction": res["valid"],
        "rows": rows, "skipped": {} if cv2 is not None else {"area": "OpenCV not importable"},
        "headline": {"min_psnr_on_db": on["min_psnr_db"], "target_db": TARGET_DB,
                     "meets_target": on["min_psnr_db"] >= TARGET_DB,
                     "cost_ratio_on_off": on["median_s"] / rows[0]["median_s"]},
        "loadavg_start": load_start, "loadavg_end": loadavg(),
    }


def markdown(result: dict) -> str:
    s = result["setup"]
    lines = [f"antialias: line grid (period {s['period']}) {s['source'][1]} x {s['source'][0]} "
             f"(fx {s['source'][2]:g}) -> {s['output'][1]} x {s['output'][0]} fisheye, "
             f"RandomReproject defaults, {s['samples']} draws, reference {s['subsamples']}^2 "
             f"samples per pixel; {result['threads']} thread(s), load "
             f"{result['loadavg_start']} -> {result['loadavg_end']}, commit "
             f"{result['commit'][:12]}{' (dirty)' if result['dirty'] else ''}", "",
             "| filter | PSNR per draw (dB) | mean dB | min dB | median ms / call | IQR ms |",
             "|---|---|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {', '.join(f'{v:.1f}' for v in r['psnr_db'])} | "
                     f"{r['mean_psnr_db']:.1f} | {r['min_psnr_db']:.1f} | "
                     f"{1e3 * r['median_s']:.1f} | {1e3 * r['iqr_s']:.1f} |")
    h = result["headline"]
    shares = ", ".join(f"{v:.2f}" for v in result["valid_fraction"])
    lines += ["", f"valid share per draw: {shares}",
              f"min PSNR on {h['min_psnr_on_db']:.1f} dB (target >= {h['target_db']:.0f}: "
              f"{'ok' if h['meets_target'] else 'MISSED'}); cost on / off "
              f"{h['cost_ratio_on_off']:.2f}x"]
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=positive_int, default=None,
                        help="output side S (512; 128 quick); the source scales with it")
    parser.add_argument("--period", type=positive_int, default=8, help="line spacing (8)")
    parser.add_argument("--samples", type=positive_int, default=None, help="draws (4; 2 quick)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (1)")
    parser.add_argument("--repeats", type=positive_int, default=None, help="timed calls (10; 3)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed calls (1)")
    parser.add_argument("--quick", action="store_true", help="a smoke run (seconds)")
    parser.add_argument("--out", type=Path, default=None, help="JSON output")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = results_path("antialias.json", quick=args.quick)
    for name, (full, quick) in {"size": (512, 128), "samples": (4, 2),
                                "repeats": (10, 3)}.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    return args


def main(argv=None) -> int:
    def write(result: dict) -> str:
        text = markdown(result)
        atomic_write_text(args_holder[0].out.with_suffix(".md"), text + "\n")
        return text

    args_holder: list = []

    def parse(argv):
        args_holder.append(parse_args(argv))
        return args_holder[0]
    return run_main(parse, run, write, argv)


if __name__ == "__main__":
    sys.exit(main())
