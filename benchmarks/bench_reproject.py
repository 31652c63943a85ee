"""Perspective -> fisheye augmentation: ``RandomReproject`` against albumentations and kornia.

Issue 17's target: at 1024 x 512, ``uint8`` RGB + labels, at least 1.5x the throughput of
albumentations' ``OpticalDistortion(mode="fisheye")``, with labels exact (never blended) and the
valid mask returned. Times, round-robin in one run (``common.measure``), on ``--batch`` images
(default 8) of ``--width x --height`` (1024 x 512) ``uint8`` RGB with ``uint8`` labels:

* ``ours_batch``: ``RandomReproject((H, W), source_fov=90 deg)`` on the batch (a new lens,
  fov 160-200 deg, and attitude per sample; RGB ``uint8`` out, labels int64 out, valid mask);
* ``ours_sample``: the same module called once per image (batch 1), as in a ``Dataset``'s
  ``__getitem__``;
* ``ours_sample_hwc``: per image, the ``(H, W, 3)`` arrays as image files give them
  (``channels_last=True``: read and written channels-last, no copy);
* ``albumentations``: ``A.OpticalDistortion(mode="fisheye", p=1)`` (its defaults: distort
  limit +-0.05) on each image and its mask, ``(H, W, 3)`` ``uint8`` numpy arrays (as it takes
  them): a mild barrel distortion through ``cv2.remap`` (no lens model, no valid mask, labels
  nearest); skipped, and said so, where albumentations cannot be imported;
* ``kornia``: ``kornia.augmentation.RandomFisheye`` (centre +-0.3, gamma 0.9-1.0: its
  docstring's example) on the batch as float32 in [0, 1], RGB only (kornia 0.9 refuses masks
  for it; ``bench_training.py`` adds them);
* ``ours_batch_detection``: ``ours_batch`` with detection targets (issue 35): 20 boxes per
  image (outline mode: mapped through the drawn camera, ``box_index``) and 17 keypoints per
  image; the headline ``detection overhead`` is its median over ``ours_batch``'s (target
  <= 1.10, ``DETECTION_TARGET``);
* ``ours_batch_instances``: ``ours_batch`` with an ``int64`` instance map and the exact box
  mode (the 20 boxes from their instances' output pixels): one more labels pass, timed apart;
* ``exact``: ``RandomReproject`` on the exact chain (``ot.reproject``: ``Camera.ray_grid``,
  ``grid_sample``), what a call with gradients or off the CPU runs, on float32 images.

albumentations is not a dependency: its requirements pull ``opencv-python-headless``, whose
``cv2`` would overwrite ``opencv-contrib-python-headless``'s (``cv2.omnidir``, which the tests
need). Installed without its requirements it runs on the contrib ``cv2``::

    pip install --no-deps albumentations==2.0.8 albucore==0.0.24
    pip install "pydantic>=2.9.2" PyYAML "stringzilla>=3.10.4" "simsimd>=5.9.2"

Our rows run the module's defaults, antialiasing on (``fast.mip_image`` where the fisheye
minifies the image; the exact chain ``antialias.mip_sample``).

Headline: ``ours_sample`` and ``ours_batch`` images/s over ``albumentations`` images/s (target
>= 1.5, ``TARGET``). Checks in the same run: ours against the exact chain on the same draws,
framed to the source and antialiased (one filter rule on both paths; validity equal, RGB within
the rounding of the C++ path's 8-bit pyramid levels, a level or two, of the float image
rounded, but for the rare pixel whose footprint is a power of two within rounding, where the
paths read neighbouring levels: the share beyond 2 levels is reported; label agreement on the
pixels both call valid) and the valid fraction of our images.

Usage::

    python benchmarks/bench_reproject.py            # 8 x 1024 x 512, 2 threads
    python benchmarks/bench_reproject.py --quick    # 2 x 128 x 64, a smoke run

Results: a markdown table on stdout and JSON (``--out``, default
``benchmarks/results/reproject.json``, written atomically).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
# Benchmark the checkout this script lives in, not whatever copy is installed.
sys.path.insert(0, str(ROOT))

from common import begin_run, loadavg, measure, results_path, run_main, run_record  # noqa: E402
import omniscape_torch as ot  # noqa: E402

try:
    import cv2
except ImportError:
    cv2 = None
try:
    import albumentations
except ImportError:   # not a dependency (module docstring): its row is skipped
    albumentations = None

SEED = 20261125
#: ours / albumentations images per second, at least (issue 17).
TARGET = 1.5
#: ours_batch_detection / ours_batch median time, at most (issue 35).
DETECTION_TARGET = 1.10
BOXES, KEYPOINTS = 20, 17
SOURCE_FOV = math.radians(90)


def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(args.threads, cv2)
    gen = torch.Generator().manual_seed(SEED)
    b, h, w = args.batch, args.height, args.width
    images = torch.randint(0, 256, (b, 3, h, w), generator=gen, dtype=torch.uint8)
    labels = torch.randint(0, 13, (b, h, w), generator=gen, dtype=torch.uint8)
    images_hwc = images.permute(0, 2, 3, 1).contiguous()
    numpy_images = [x.numpy() for x in images_hwc]
    numpy_labels = [x.numpy() for x in labels]

    def module(**kwargs) -> ot.augment.RandomReproject:
        return ot.augment.RandomReproject((h, w), source_fov=SOURCE_FOV, seed=SEED, **kwargs)

    batched, single, single_hwc, exact = module(), module(), module(channels_last=True), module()

    def per_image(aug, batch) -> list:
        return [aug({"rgb": batch[i:i + 1], "labels": labels[i:i + 1]}) for i in range(b)]

    floats = images.float() / 255
    # detection targets: boxes of 10-160 px in the image, keypoints anywhere in it
    centre = torch.rand(b, BOXES, 2, generator=gen) * torch.tensor([w, h])
    half = (torch.rand(b, BOXES, 2, generator=gen) * 150 + 10) / 2
    boxes = torch.cat((centre - half, centre + half), -1).round()
    boxes = torch.cat((boxes[..., :2].clamp(min=0),
                       torch.minimum(boxes[..., 2:], torch.tensor([w, h]))), -1)
    keypoints = torch.rand(b, KEYPOINTS, 2, generator=gen) * torch.tensor([w, h])
    instances = torch.zeros(b, h, w, dtype=torch.int64)
    for i in range(b):   # box j painted with id 1000 + j (later boxes over earlier ones)
        for j, (x0, y0, x1, y1) in enumerate(boxes[i].long().tolist()):
            instances[i, y0:y1, x0:x1] = 1000 + j
    ids = [torch.tensor([int(t) for t in instances[i].unique() if t > 0]) for i in range(b)]
    detecting, instancing = module(), module()

    def exact_chain():
        with torch.enable_grad():   # a gradient asked for: the exact chain
            return exact({"rgb": floats.requires_grad_(), "labels": labels.long()})

    cases = [("ours_batch", "ours", lambda: batched({"rgb": images, "labels": labels})),
             ("ours_batch_detection", "ours", lambda: detecting(
                 {"rgb": images, "labels": labels, "boxes": list(boxes),
                  "keypoints": keypoints})),
             ("ours_batch_instances", "ours", lambda: instancing(
                 {"rgb": images, "labels": labels, "instances": instances,
                  "box_instance_ids": ids})),
             ("ours_sample", "ours", lambda: per_image(single, images)),
             ("ours_sample_hwc", "ours", lambda: per_image(single_hwc, images_hwc)),
             ("exact", "ours", exact_chain)]
    skipped = {}
    if albumentations is not None:
        distort = albumentations.OpticalDistortion(mode="fisheye", p=1.0)
        cases.append(("albumentations", "peer", lambda: [
            distort(image=img, mask=lab) for img, lab in zip(numpy_images, numpy_labels)]))
    else:
        skipped["albumentations"] = ("albumentations is not installed (not a dependency: see "
                                     "the module docstring for the command)")
    try:
        import kornia.augmentation as K
        fisheye = K.RandomFisheye(torch.tensor([-0.3, 0.3]), torch.tensor([-0.3, 0.3]),
                                  torch.tensor([0.9, 1.0]), p=1.0)
        cases.append(("kornia", "peer", lambda: fisheye(floats)))
    except ImportError:
        skipped["kornia"] = "kornia is not installed"

    # Agreement on the same draws (framed to the source, as a call draws them): ours (uint8,
    # fast path) against the exact chain, both antialiased (one rule: fast.mip_image in C++,
    # antialias.mip_sample in torch; the C++ keeps 8-bit pyramid levels)
    ours_aug, exact_aug = module(), module()
    params = ours_aug.forward_parameters(b, generator=torch.Generator().manual_seed(SEED + 1),
                                         source_size=(h, w))
    with torch.no_grad():
        ours = ours_aug({"rgb": images, "labels": labels}, params=params)
    with torch.enable_grad():
        reference = exact_aug({"rgb": floats.requires_grad_(), "labels": labels.long()},
                              params=params)
    both = ours["valid"] & reference["valid"]
    rounded = (reference["rgb"].detach() * 255 + 0.5).floor()
    diff = (ours["rgb"].double() - rounded).abs()[both.expand_as(ours["rgb"])]
    agreement = {
        "valid_mismatch_fraction": float((ours["valid"] != reference["valid"]).float().mean()),
        "rgb_max_abs_diff_levels": float(diff.max()) if diff.numel() else 0.0,
        # pixels whose footprint is a power of two within rounding: neighbouring mip levels
        "rgb_over_2_levels_fraction": float((diff > 2).double().mean()) if diff.numel() else 0.0,
        "label_agreement": float((ours["labels"] == reference["labels"])[both[:, 0]]
                                 .float().mean()),
        "valid_fraction": float(ours["valid"].float().mean()),
    }

    with torch.no_grad():
        results = measure([fn for _, _, fn in cases], args.repeats, args.warmup)
    rows, by_name = [], {}
    for (name, kind, _), res in zip(cases, results):
        row = {"name": name, "kind": kind, "batch": b, **res,
               "images_per_s": b / res["median_s"], "fastest_images_per_s": b / res["min_s"]}
        rows.append(row)
        by_name[name] = row
    headline = []
    if "albumentations" in by_name:
        peer = by_name["albumentations"]
        for name in ("ours_sample", "ours_sample_hwc", "ours_batch"):
            ratio = by_name[name]["images_per_s"] / peer["images_per_s"]
            headline.append({"ours": name, "peer": "albumentations", "throughput_ratio": ratio,
                             "min_ratio": peer["min_s"] / by_name[name]["min_s"],
                             "target": TARGET, "meets_target": ratio >= TARGET})
    base = by_name["ours_batch"]["median_s"]
    detection = {name: by_name[name]["median_s"] / base
                 for name in ("ours_batch_detection", "ours_batch_instances")}
    detection.update(target=DETECTION_TARGET,
                     meets_target=detection["ours_batch_detection"] <= DETECTION_TARGET,
                     boxes_per_image=BOXES, keypoints_per_image=KEYPOINTS)
    return {
        **run_record("reproject", torch.device("cpu"), args.threads, cv2),
        "versions_peers": {"albumentations": getattr(albumentations, "__version__", None)},
        "setup": {"batch": b, "image_size": [h, w], "source_fov_deg": math.degrees(SOURCE_FOV),
                  "seed": SEED, "repeats": args.repeats, "warmup": args.warmup,
                  "quick": args.quick},
        "rows": rows,
        "skipped": skipped,
        "headline": headline,
        "detection_overhead": detection,
        "agreement": agreement,
        "loadavg_start": load_start,
        "loadavg_end": loadavg(),
    }


def markdown(result: dict) -> str:
    s = result["setup"]
    lines = [f"reproject: {s['batch']} perspective images {s['image_size'][1]} x "
             f"{s['image_size'][0]} (uint8 RGB + labels) -> fisheye of the same size, "
             f"{result['threads']} threads, commit {result['commit'][:12]}"
             f"{' (dirty)' if result['dirty'] else ''}", "",
             "| row | kind | median ms / batch | IQR ms | min ms | images/s |",
             "|---|---|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {r['kind']} | {1e3 * r['median_s']:.1f} | "
                     f"{1e3 * r['iqr_s']:.1f} | {1e3 * r['min_s']:.1f} | "
                     f"{r['images_per_s']:.1f} |")
    lines.append("")
    for name, why in result["skipped"].items():
        lines.append(f"skipped {name}: {why}")
    for h in result["headline"]:
        lines.append(f"throughput {h['ours']} / {h['peer']}: {h['throughput_ratio']:.2f}x "
                     f"(fastest calls {h['min_ratio']:.2f}x; target >= {h['target']:.1f}x: "
                     f"{'ok' if h['meets_target'] else 'MISSED'})")
    d = result["detection_overhead"]
    lines.append(f"detection overhead ({d['boxes_per_image']} boxes, outline mode, and "
                 f"{d['keypoints_per_image']} keypoints per image): "
                 f"{d['ours_batch_detection']:.3f}x ours_batch (target <= {d['target']:.2f}: "
                 f"{'ok' if d['meets_target'] else 'MISSED'}); exact instance mode "
                 f"{d['ours_batch_instances']:.3f}x")
    lines.append("agreement with the exact chain (same draws): " + ", ".join(
        f"{k} {v:.4g}" for k, v in result["agreement"].items()))
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    from omniscape_torch.cli import positive_int
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=positive_int, default=None, help="images (8; 2 quick)")
    parser.add_argument("--width", type=positive_int, default=None, help="1024 (128 quick)")
    parser.add_argument("--height", type=positive_int, default=None, help="512 (64 quick)")
    parser.add_argument("--threads", type=positive_int, default=2,
                        help="torch and OpenCV threads (default 2)")
    parser.add_argument("--repeats", type=positive_int, default=None,
                        help="timed calls per row (default 10; 2 with --quick)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed calls before timing (default 2; 1 with --quick)")
    parser.add_argument("--quick", action="store_true", help="a smoke run (seconds)")
    parser.add_argument("--out", type=Path,
                        default=None,
                        help="JSON output (default benchmarks/results/reproject.json)")
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("reproject.json", quick=args.quick)
    defaults = {"batch": (8, 2), "width": (1024, 128), "height": (512, 64),
                "repeats": (10, 2), "warmup": (2, 1)}
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    if args.warmup < 0:
        parser.error("--warmup must be >= 0")
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
