"""The camera models of other tools through the layer: each against Kannala-Brandt, same run.

Issue 34's speed target: each of ``fov``, ``division``, ``opencv``, ``thin_prism_fisheye`` and
``fisheye624`` renders a ``6 x F x F`` float32 RGB cube into a ``2F x 2F`` image through
``OmniProjection`` (the CPU fast path) within 1.3x ``kannala_brandt``'s time, with the grid
cached and rebuilt, at batch 1 and 8. The cameras (``CAMERAS``) are realistic lenses of each
model at 1024 x 1024 (scaled to ``2F`` for other sizes), every pixel seen: the three fisheyes
full-frame (196 degrees across the width), the perspective models 68-89 degrees across.

Rows per model and batch, timed round-robin with the other models' (``common.measure``):

* ``cached``: ``layer(cube)``: the camera is fixed, so the layer's lookup table is built once
  (not timed) and every call samples through it;
* ``rebuilt``: ``layer(cube, rotation)`` with a new random rotation per sample and call: the
  grid is rebuilt from the camera's rays (computed once: the camera is fixed) in the sampling
  pass;
* ``new_camera`` (batch 1, for information): a new ``OmniProjection`` of the camera and its
  first call: the model's unprojection of every pixel (closed forms, or Newton's iterations)
  plus the table; what a per-sample random camera pays.

The ratio of a row is its median over ``kannala_brandt``'s median of the same row and batch
(``min_ratio``: of the fastest calls, which a load spike cannot inflate).

Usage::

    python benchmarks/bench_models_layer.py             # F = 512 (1024 x 1024), batch 1 and 8
    python benchmarks/bench_models_layer.py --quick     # F = 64, batch 1 and 2: seconds

Results: a markdown table on stdout and JSON (``--out``, default
``benchmarks/results/models_layer.json``; ``--quick``: under ``results/quick/``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))   # benchmark the checkout this script lives in
sys.path.insert(0, str(HERE))

import omniscape_torch as ot  # noqa: E402
from common import (begin_run, loadavg, measure, results_path, run_main,  # noqa: E402
                    run_record)
from bench_projection import RotationPool  # noqa: E402

#: The reference and the five models of issue 34, at 1024 x 1024: fx, fy, cx, cy, then the
#: model's own parameters (DESIGN.md's order). The fisheyes share the reference's radial part.
CAMERAS = {
    "kannala_brandt": [309.0, 309.5, 511.7, 511.2, -0.02, 0.004, -0.001, 0.0002],
    "fisheye624": [309.0, 309.5, 511.7, 511.2, -0.02, 0.004, -0.001, 0.0002, 0.0, 0.0,
                   4e-4, -3e-4, 2e-4, 1e-5, -3e-4, 2e-5],
    "thin_prism_fisheye": [309.0, 309.5, 511.7, 511.2, -0.02, 0.004, 4e-4, -3e-4, -0.001,
                           0.0002, 5e-4, -3e-4],
    "fov": [800.0, 808.0, 511.5, 511.5, 0.9],
    "division": [640.0, 643.0, 511.5, 511.5, -0.3],
    "opencv": [800.0, 803.0, 511.5, 511.5, -0.28, 0.07, 1e-3, -5e-4] + [0.0] * 8,
}
REFERENCE = "kannala_brandt"
TARGET = 1.3


def camera(name: str, size: int) -> ot.Camera:
    """The model's lens of ``CAMERAS`` scaled from 1024 to ``size`` pixels (focal lengths by
    the ratio, the principal point about the image's corner ``-0.5``)."""
    s = size / 1024
    p = list(CAMERAS[name])
    p[0:2] = [p[0] * s, p[1] * s]
    p[2:4] = [(p[2] + 0.5) * s - 0.5, (p[3] + 0.5) * s - 0.5]
    return ot.Camera(name, torch.tensor(p, dtype=torch.float64), (size, size))


def run(args: argparse.Namespace) -> dict:
    load = begin_run(args.threads)
    gen = torch.Generator().manual_seed(0)
    size, face = 2 * args.face, args.face
    cams = {name: camera(name, size) for name in CAMERAS}
    layers = {name: ot.OmniProjection(cam, face) for name, cam in cams.items()}
    rows = []
    for batch in args.batches:
        cube = torch.rand(batch, 6, 3, face, face, generator=gen)
        cases = []
        for name, layer in layers.items():
            layer(cube)   # the table, once (not timed)
            cases.append((name, "cached", lambda layer=layer: layer(cube)))
            pool = RotationPool(batch, args.warmup + args.repeats, gen, "cpu", torch.float32)
            cases.append((name, "rebuilt", lambda layer=layer, pool=pool: layer(cube, pool())))
            if batch == args.batches[0]:
                cases.append((name, "new_camera", lambda name=name: ot.OmniProjection(
                    cams[name], face)(cube[:1])))
        timed = measure([fn for _, _, fn in cases], args.repeats, args.warmup)
        medians = {(n, r): t["median_s"] for (n, r, _), t in zip(cases, timed)}
        minima = {(n, r): t["min_s"] for (n, r, _), t in zip(cases, timed)}
        for (name, row, _), t in zip(cases, timed):
            ref = (REFERENCE, row)
            rows.append({"model": name, "row": row, "batch": batch if row != "new_camera" else 1,
                         "median_s": t["median_s"], "iqr_s": t["iqr_s"], "min_s": t["min_s"],
                         "ratio": t["median_s"] / medians[ref],
                         "min_ratio": t["min_s"] / minima[ref]})
    valid = {name: float(layer(torch.zeros(1, 6, 3, face, face))[1].float().mean())
             for name, layer in layers.items()}
    return {**run_record("models_layer", torch.device("cpu"), args.threads),
            "load_start": load, "load_end": loadavg(), "image_size": [size, size],
            "face": face, "repeats": args.repeats, "target": TARGET, "reference": REFERENCE,
            "valid_share": valid, "cameras": CAMERAS, "rows": rows}


def markdown(result: dict) -> str:
    lines = [f"# models through the layer, {result['image_size'][0]} x "
             f"{result['image_size'][1]} from 6 x {result['face']}, "
             f"{result['threads']} threads, load "
             f"{result['load_start']} -> {result['load_end']}",
             "", "| model | row | batch | ms | x kannala_brandt | x (fastest calls) | "
                 "valid share |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        over = r["row"] != "new_camera" and r["ratio"] > result["target"]
        lines.append(f"| {r['model']} | {r['row']} | {r['batch']} | "
                     f"{1e3 * r['median_s']:.2f} | {r['ratio']:.2f}{' **over**' if over else ''}"
                     f" | {r['min_ratio']:.2f} | {result['valid_share'][r['model']]:.2f} |")
    lines.append(f"\ntarget: cached and rebuilt rows within {result['target']}x "
                 f"{result['reference']}'s (new_camera: for information)")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--face", type=int, default=None,
                        help="cube face size F; the image is 2F x 2F (default 512; 64 quick)")
    parser.add_argument("--batches", type=int, nargs="+", default=None,
                        help="batch sizes (default 1 8; 1 2 with --quick)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed calls per row (default 11; 3 with --quick)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed calls per row (default 2; 1 with --quick)")
    parser.add_argument("--quick", action="store_true", help="a smoke run: F = 64, seconds")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON output (default benchmarks/results/models_layer.json)")
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("models_layer.json", quick=args.quick)
    args.face = args.face or (64 if args.quick else 512)
    args.batches = args.batches or ([1, 2] if args.quick else [1, 8])
    args.repeats = args.repeats or (3 if args.quick else 11)
    args.warmup = 1 if args.quick and args.warmup is None else (
        2 if args.warmup is None else args.warmup)
    if args.face < 8 or args.threads < 1 or args.repeats < 1 or args.warmup < 0 or \
            any(b < 1 for b in args.batches):
        parser.error("--face >= 8, --threads, --repeats, --batches >= 1, --warmup >= 0")
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
