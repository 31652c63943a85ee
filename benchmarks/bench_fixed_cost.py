"""Fixed cost per call of perspective -> fisheye augmentation (issue 36, item 3).

Tiny images, so that the time is the call's overhead (drawing the parameters, checks, dispatch),
not its pixels: ``--batch`` (1 and 8) ``32 x 32`` RGB images into ``32 x 32`` outputs, one
thread (``torch.set_num_threads(1)``), in one run, round-robin (``common.measure``):

* ``ours``: ``RandomReproject((32, 32), source_fov=90 deg)`` at its defaults: framed to the
  source by the default ``coverage_range`` and antialiased (``antialias=True``, the default
  since the prefilter became one rule on every path), float32 images in [0, 1] (as kornia
  takes them), RGB only. The output minifies here: the fisheye squeezes its periphery, so
  with the source filling 50-90 % of the output about half of the output's pixels (three
  quarters of the valid ones) have a footprint longer than a source pixel and are filtered
  (``render.fast.mip_image``, all at level 0: footprints under 4 source pixels);
* ``ours_no_aa``: the same with ``antialias=False`` (point samples: the prefilter's share);
* ``ours_params``: its ``forward_parameters`` alone (the draw, framed to the source);
* ``ours_render``: its ``render`` of drawn parameters alone (the checks, the rays, sampling,
  the prefilter);
* ``ours_ops``: the floor of that sampling: the three C++ passes on prepared inputs
  (``render.fast.camera_rays`` of the drawn cameras' radius tables, ``render.fast.
  sample_image``, then ``render.fast.mip_image``), wrappers included;
* ``kornia``: ``kornia.augmentation.RandomFisheye`` (centre +-0.3, gamma 0.9-1.0: its
  docstring's example) on the same batch.

Headline: ours / kornia median time per call, per batch size (target <= 1).

Usage::

    python benchmarks/bench_fixed_cost.py            # batches 1 and 8, 200 calls each
    python benchmarks/bench_fixed_cost.py --quick    # 20 calls

Results: markdown on stdout and JSON (``--out``, default
``benchmarks/results/fixed_cost.json``; ``--quick``: ``benchmarks/results/quick/``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_main, run_record)
from omniscape_torch.render.kernels import camera as kernels, image as fast  # noqa: E402
from omniscape_torch.augment import RandomReproject  # noqa: E402

SEED = 36
SIZE = (32, 32)


def sampling_floor(params: dict, images: torch.Tensor):
    """The C++ passes of ``RandomReproject``'s fast path on prepared inputs: the rays of the
    drawn (equidistant) cameras from their radius tables, the images sampled along them
    (float32, as the module samples float32 images), then the antialiasing filter of the
    pixels that minify."""
    batch = images.shape[0]
    cams = params["camera_params"][:, :4]
    affine, limits, table = kernels.radial_table("equidistant", cams, SIZE)
    limits[:, 3] = torch.cos(0.5 * params["fov"])
    affine, limits, table = (t.float().contiguous() for t in (affine, limits, table))
    rotation = params["rotation"].float()
    k = RandomReproject(SIZE, source_fov=math.radians(90)).source_intrinsics(SIZE, batch).float()
    out = torch.empty(batch, 3, *SIZE)

    def call():
        rays, valid = fast.camera_rays(affine, limits, table, SIZE, torch.float32)
        _, seen = fast.sample_image(images, rays, rotation, k, "bilinear", valid=valid, out=out)
        fast.mip_image(images, rays, rotation, k, seen, out)

    return call


def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(1)
    import kornia.augmentation as K

    gen = torch.Generator().manual_seed(SEED)
    rows, headline, minified = [], [], []
    for batch in args.batches:
        images = torch.rand(batch, 3, *SIZE, generator=gen)
        ours = RandomReproject(SIZE, source_fov=math.radians(90), seed=SEED)
        point = RandomReproject(SIZE, source_fov=math.radians(90), seed=SEED, antialias=False)
        fisheye = K.RandomFisheye(torch.tensor([-0.3, 0.3]), torch.tensor([-0.3, 0.3]),
                                  torch.tensor([0.9, 1.0]), p=1.0)
        drawn = ours.forward_parameters(batch, intrinsics=ours.source_intrinsics(SIZE, batch),
                                        source_size=SIZE)
        filtered = ours.render(images, drawn)
        minified.append({"batch": batch, "share": float(
            (filtered["rgb"] != point.render(images, drawn)["rgb"]).any(1).float().mean()),
            "valid": float(filtered["valid"].float().mean())})
        cases = [("ours", lambda: ours(images)),
                 ("ours_no_aa", lambda: point(images)),
                 ("ours_params", lambda: ours.forward_parameters(
                     batch, intrinsics=ours.source_intrinsics(SIZE, batch), source_size=SIZE)),
                 ("ours_render", lambda: ours.render(images, drawn)),
                 ("ours_ops", sampling_floor(drawn, images)),
                 ("kornia", lambda: fisheye(images))]
        with torch.no_grad():
            times = measure([fn for _, fn in cases], args.repeats, args.warmup, settle_s=0.0)
        by_name = {}
        for (name, _), t in zip(cases, times):
            row = {"name": name, "batch": batch, "median_s": t["median_s"], "iqr_s": t["iqr_s"],
                   "min_s": t["min_s"]}
            rows.append(row)
            by_name[name] = row
        ratio = by_name["ours"]["median_s"] / by_name["kornia"]["median_s"]
        headline.append({"batch": batch, "ours_over_kornia": ratio, "meets_target": ratio <= 1})
    return {**run_record("fixed_cost", torch.device("cpu"), 1),
            "setup": {"size": list(SIZE), "batches": args.batches, "repeats": args.repeats,
                      "warmup": args.warmup, "quick": args.quick, "seed": SEED},
            "rows": rows, "headline": headline, "minified": minified,
            "loadavg_start": load_start, "loadavg_end": loadavg()}


def markdown(result: dict) -> str:
    lines = [f"fixed cost per call, 32 x 32 -> 32 x 32, 1 thread, load "
             f"{result['loadavg_start']} -> {result['loadavg_end']}, commit "
             f"{result['commit'][:12]}{' (dirty)' if result['dirty'] else ''}", "",
             "| row | batch | median ms | IQR ms | min ms |", "|---|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {r['batch']} | {1e3 * r['median_s']:.3f} | "
                     f"{1e3 * r['iqr_s']:.3f} | {1e3 * r['min_s']:.3f} |")
    lines.append("")
    for m in result.get("minified", []):
        lines.append(f"batch {m['batch']}: the prefilter changes {100 * m['share']:.0f} % of "
                     f"the output's pixels ({100 * m['valid']:.0f} % valid)")
    for h in result["headline"]:
        lines.append(f"batch {h['batch']}: ours / kornia {h['ours_over_kornia']:.2f}x "
                     f"(target <= 1: {'ok' if h['meets_target'] else 'MISSED'})")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", type=positive_int, nargs="+", default=[1, 8])
    parser.add_argument("--repeats", type=positive_int, default=None,
                        help="timed calls per row (200; 20 quick)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed calls (5)")
    parser.add_argument("--quick", action="store_true", help="a smoke run (seconds)")
    parser.add_argument("--out", type=Path, default=None, help="JSON output")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = results_path("fixed_cost.json", quick=args.quick)
    if args.repeats is None:
        args.repeats = 20 if args.quick else 200
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
