"""The layer and the augmentation modules on a CUDA device, with their peers, in one run.

Rows, timed round-robin (``common.measure``, ``torch.cuda.synchronize`` around every call),
batch 1 and ``--batch`` (32):

* ``layer_cached``: ``OmniProjection`` of an equidistant 190-degree fisheye, ``S x S`` (1024)
  from a ``6 x S/2 x S/2`` float32 RGB cube, its grid cached in the layer (one camera, no
  attitude): the paper's headline;
* ``layer_rebuilt``: the same with a new attitude per sample and call (``rotation (B, 3, 3)``):
  the grid rebuilt every call;
* ``six_grid_sample`` (peer): six ``grid_sample`` calls, one per face, masked and summed, on
  the same cube (habitat-lab's conversion; per-face grids precomputed, as
  ``benchmarks/harness.py`` times it);
* ``omni_camera``: ``RandomOmniCamera((A, A), A / 2)`` (A = ``--aug-size``, 512) on a float32
  cube with labels: a new lens and attitude per sample and call;
* ``reproject``: ``RandomReproject((A, A), source_fov=90 deg)`` at its defaults on ``uint8``
  ``A x 2A`` perspective images with labels (Cityscapes' aspect);
* ``kornia_fisheye`` (peer): ``kornia.augmentation.RandomFisheye`` (centre +-0.3, gamma
  0.9-1.0) on ``A x A`` float32 RGB (kornia 0.9 refuses masks for it).

Headlines: ``layer_cached`` and ``layer_rebuilt`` over ``six_grid_sample`` (time per frame, per
batch size), and ``reproject`` / ``omni_camera`` images/s over ``kornia_fisheye``'s.

Usage (a CUDA machine; ``--device cpu --quick`` is a smoke run of the script itself)::

    python benchmarks/bench_cuda.py               # S = 1024, A = 512, batches 1 and 32
    python benchmarks/bench_cuda.py --quick       # S = 256, A = 128, batches 1 and 4

Results: markdown on stdout and JSON (``--out``, default ``benchmarks/results/cuda.json``;
``--quick``: ``benchmarks/results/quick/cuda.json``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_main, run_record)
import omniscape_torch as ot  # noqa: E402
from omniscape_torch.cameras.presets import yaw_pitch_roll_to_matrix  # noqa: E402
from omniscape_torch.cubemap import ray_to_face  # noqa: E402

DEG = math.pi / 180
SEED = 20261127


def _rotations(batch: int, gen: torch.Generator) -> torch.Tensor:
    """``(batch, 3, 3)`` attitudes: yaw anywhere, roll +-25 deg, pitch +-10 deg."""
    roll, pitch, yaw = (torch.rand(3, batch, generator=gen) * 2 - 1) * torch.tensor(
        [25 * DEG, 10 * DEG, math.pi])[:, None]
    return yaw_pitch_roll_to_matrix(yaw, pitch, roll)


def _six_faces(camera: ot.Camera, face: int, device: torch.device):
    """The peer: per-face grids and masks of ``camera``'s rays (precomputed)."""
    rays, valid = camera.ray_grid()
    rays, valid = rays.reshape(*rays.shape[-3:]), valid.reshape(valid.shape[-2:])
    which, uv = ray_to_face(rays, face)
    grid = torch.stack(((2 * uv[..., 0] + 1) / face - 1, (2 * uv[..., 1] + 1) / face - 1), -1)
    masks = torch.stack([(which == k) & valid for k in range(6)]).float().unsqueeze(1)
    return grid.float().to(device), masks.to(device)


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    load_start = begin_run(args.threads)
    gen = torch.Generator().manual_seed(SEED)
    size, aug = args.size, args.aug_size
    face = size // 2
    camera = ot.Camera("equidistant", [size / (190 * DEG), size / (190 * DEG),
                                       (size - 1) / 2, (size - 1) / 2], (size, size),
                       fov=190 * DEG)
    layer = ot.OmniProjection(camera, face).to(device)
    grid, masks = _six_faces(camera, face, device)
    omni = ot.augment.RandomOmniCamera((aug, aug), aug // 2, seed=SEED)
    repro = ot.augment.RandomReproject((aug, aug), source_fov=90 * DEG, seed=SEED)
    import kornia.augmentation as K
    kfish = K.RandomFisheye(torch.tensor([-0.3, 0.3]), torch.tensor([-0.3, 0.3]),
                            torch.tensor([0.9, 1.0]), p=1.0).to(device)

    rows, headline = [], []
    for batch in args.batches:
        cube = torch.rand(batch, 6, 3, face, face, generator=gen).to(device)
        small = torch.rand(batch, 6, 3, aug // 2, aug // 2, generator=gen).to(device)
        small_labels = torch.randint(0, 13, (batch, 6, aug // 2, aug // 2),
                                     generator=gen).to(device)
        persp = (torch.rand(batch, 3, aug, 2 * aug, generator=gen) * 255).to(
            torch.uint8).to(device)
        persp_labels = torch.randint(0, 13, (batch, aug, 2 * aug), generator=gen).to(device)
        square = torch.rand(batch, 3, aug, aug, generator=gen).to(device)

        def six(x=cube):
            g = grid.expand(x.shape[0], -1, -1, -1)
            return sum(F.grid_sample(x[:, k], g, mode="bilinear", padding_mode="border",
                                     align_corners=False) * masks[k] for k in range(6))

        cases = [
            ("layer_cached", lambda: layer(cube)),
            ("layer_rebuilt", lambda: layer(cube, _rotations(batch, gen).to(device))),
            ("six_grid_sample", six),
            ("omni_camera", lambda: omni(small, small_labels)),
            ("reproject", lambda: repro(persp, persp_labels)),
            ("kornia_fisheye", lambda: kfish(square)),
        ]
        with torch.no_grad():
            times = measure([fn for _, fn in cases], args.repeats, args.warmup, device)
        by = {}
        for (name, _), t in zip(cases, times):
            row = {"name": name, "batch": batch, "median_s": t["median_s"],
                   "iqr_s": t["iqr_s"], "min_s": t["min_s"],
                   "ms_per_image": 1e3 * t["median_s"] / batch,
                   "images_per_s": batch / t["median_s"]}
            rows.append(row)
            by[name] = row
        headline.append({
            "batch": batch,
            "layer_cached_over_six_grid_sample": by["layer_cached"]["median_s"] /
            by["six_grid_sample"]["median_s"],
            "layer_rebuilt_over_six_grid_sample": by["layer_rebuilt"]["median_s"] /
            by["six_grid_sample"]["median_s"],
            "reproject_throughput_over_kornia": by["reproject"]["images_per_s"] /
            by["kornia_fisheye"]["images_per_s"],
            "omni_camera_throughput_over_kornia": by["omni_camera"]["images_per_s"] /
            by["kornia_fisheye"]["images_per_s"]})
    import kornia
    return {**run_record("cuda", device, args.threads),
            "versions_peers": {"kornia": kornia.__version__},
            "setup": {"size": size, "face": face, "aug_size": aug, "batches": args.batches,
                      "repeats": args.repeats, "warmup": args.warmup, "quick": args.quick,
                      "seed": SEED},
            "rows": rows, "headline": headline,
            "loadavg_start": load_start, "loadavg_end": loadavg()}


def markdown(result: dict) -> str:
    device = result["machine"].get("gpu") or result["device"]
    s = result["setup"]
    lines = [f"{device}: layer {s['size']} x {s['size']} from 6 x "
             f"{s['face']}, augmentation {s['aug_size']} x {s['aug_size']}; torch "
             f"{result['versions']['torch']}, commit {result['commit'][:12]}"
             f"{' (dirty)' if result['dirty'] else ''}", "",
             "| row | batch | median ms | IQR ms | ms / image | images / s |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {r['batch']} | {1e3 * r['median_s']:.3f} | "
                     f"{1e3 * r['iqr_s']:.3f} | {r['ms_per_image']:.3f} | "
                     f"{r['images_per_s']:.0f} |")
    lines.append("")
    for h in result["headline"]:
        lines.append(
            f"batch {h['batch']}: layer cached / six grid_sample "
            f"{h['layer_cached_over_six_grid_sample']:.2f}x the time, rebuilt "
            f"{h['layer_rebuilt_over_six_grid_sample']:.2f}x; images/s over kornia: "
            f"reproject {h['reproject_throughput_over_kornia']:.2f}x, omni_camera "
            f"{h['omni_camera_throughput_over_kornia']:.2f}x")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda", help="cuda (default), or cpu for a smoke run")
    parser.add_argument("--size", type=positive_int, default=None, help="layer side (1024)")
    parser.add_argument("--aug-size", type=positive_int, default=None,
                        help="augmentation output side (512)")
    parser.add_argument("--batch", type=positive_int, default=None, help="the larger batch (32)")
    parser.add_argument("--threads", type=positive_int, default=1, help="CPU threads (1)")
    parser.add_argument("--repeats", type=positive_int, default=None, help="(30; 3 quick)")
    parser.add_argument("--warmup", type=int, default=None, help="(3; 1 quick)")
    parser.add_argument("--quick", action="store_true", help="a smoke run (seconds)")
    parser.add_argument("--out", type=Path, default=None, help="JSON output")
    args = parser.parse_args(argv)
    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available in this torch build or machine")
    q = args.quick
    args.size = args.size or (256 if q else 1024)
    args.aug_size = args.aug_size or (128 if q else 512)
    args.batches = [1, args.batch or (4 if q else 32)]
    args.repeats = args.repeats or (3 if q else 30)
    args.warmup = (1 if q else 3) if args.warmup is None else args.warmup
    if args.out is None:
        args.out = results_path("cuda.json", quick=q)
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
