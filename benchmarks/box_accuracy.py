"""Accuracy of `RandomReproject`'s three box modes on objects that are not rectangles.

Objects: star-shaped polygons (7-12 vertices about evenly spread, radii 0.8-1 of their size:
no tip thinner than a pixel) and ellipses (24 vertices), one per cell of a 4 x 3 grid (so none
overlap), rasterised at the source's pixel centres into one instance map (an even-odd
point-in-polygon test written here). Each image goes through the module three times with the
same drawn parameters:

* **exact**: `instances` + `box_instance_ids` (the tight box of each id's output pixels: the
  reference, which `tests/test_detection.py` shows exact);
* **outline**: `boxes` alone (the tight box of each object's source pixels, mapped by its
  outline);
* **polygons**: `boxes` + `polygons` (each object's polygon; its box the tight box of its mapped
  ring).

Figures per mode, over the objects with an output pixel: the largest amount by which a box
reaches past the exact box on any side (px), the share of boxes within 1 px of it (all, and
objects of 16 output pixels or more), the median and largest absolute side difference,
the IoU with the exact box (median, minimum), whether the box holds the exact one (to half a
pixel: a continuous box reaches the object's pixel centres, not their far edges); and for the
outline boxes, those that frame an object with no output pixel and how many of them
`box_visible` flags (False), and the flags on visible objects. Sources: a 100-degree pinhole
(the modules' default fisheye draws), a 190-degree equidistant fisheye and a catadioptric
(unified, xi 0.9, 30-degree blind cone) `source_camera`, 128 x 96 into 128 x 128.

    python benchmarks/box_accuracy.py [--images 40] [--out benchmarks/results/box_accuracy.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.io import atomic_write_text  # noqa: E402

DEG = math.pi / 180
SOURCE = (96, 128)
OUTPUT = (128, 128)


def inside(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon of ``points (Q, 2)`` against ``ring (N, 2)``."""
    a, b = ring, np.roll(ring, -1, 0)
    x, y = points[:, None, 0], points[:, None, 1]
    crosses = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    dy = np.where(b[:, 1] == a[:, 1], 1.0, b[:, 1] - a[:, 1])
    xs = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / dy[None]
    return ((crosses & (x < xs)).sum(-1) % 2) == 1


def objects(rng: np.random.Generator, centre_ok) -> list[np.ndarray]:
    """One polygon per cell of a 4 x 3 grid over the source image (corner coordinates)."""
    h, w = SOURCE
    rings = []
    for row in range(3):
        for col in range(4):
            cx, cy = (col + 0.5) * w / 4, (row + 0.5) * h / 3
            cx, cy = cx + rng.uniform(-4, 4), cy + rng.uniform(-4, 4)
            if not centre_ok(cx, cy):
                continue
            size = rng.uniform(4.0, 14.0)
            if rng.random() < 0.5:                     # a star
                n = int(rng.integers(7, 13))
                angle = (np.arange(n) + rng.uniform(-0.3, 0.3, n)) * 2 * math.pi / n
                radius = size * rng.uniform(0.8, 1.0, n)
            else:                                      # an ellipse
                angle = np.linspace(0, 2 * math.pi, 24, endpoint=False)
                a, b, turn = size, size * rng.uniform(0.3, 1.0), rng.uniform(0, math.pi)
                x, y = a * np.cos(angle), b * np.sin(angle)
                angle = np.arctan2(y, x) + turn
                radius = np.hypot(x, y)
            rings.append(np.stack((cx + radius * np.cos(angle), cy + radius * np.sin(angle)), -1))
    return rings


def instance_map(rings: list[np.ndarray]) -> torch.Tensor:
    h, w = SOURCE
    v, u = np.mgrid[0:h, 0:w]
    centres = np.stack((u.ravel() + 0.5, v.ravel() + 0.5), -1)
    ids = np.zeros(h * w, dtype=np.int64)
    for k, ring in enumerate(rings):
        ids[inside(centres, ring)] = k + 1
    return torch.from_numpy(ids.reshape(h, w))


def tight(mask: np.ndarray) -> np.ndarray | None:
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return None
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=float)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    lo, hi = np.maximum(a[:2], b[:2]), np.minimum(a[2:], b[2:])
    inter = np.prod(np.clip(hi - lo, 0, None))
    area = (lambda x: np.prod(x[2:] - x[:2]))
    return float(inter / (area(a) + area(b) - inter))


def scenario(name: str, aug, source_camera, centre_ok, images: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    rows = {"outline": [], "polygons": []}
    hidden = flagged_hidden = flagged_seen = outline_boxes = 0
    compared_objects = 0
    extra = {} if source_camera is None else {"source_camera": source_camera}
    for _ in range(images):
        rings = objects(rng, centre_ok)
        inst = instance_map(rings)
        ids = torch.unique(inst[inst > 0])
        keep = [k for k in range(len(rings)) if bool((inst == k + 1).any())]
        rings = [rings[k] for k in keep]
        ids = torch.tensor([k + 1 for k in keep])
        boxes = torch.stack([torch.from_numpy(tight((inst == i).numpy())) for i in ids.tolist()])
        rgb = torch.zeros(1, 1, *SOURCE)
        exact = aug({"rgb": rgb, "instances": inst[None], "boxes": [boxes],
                     "box_instance_ids": [ids]}, **extra)
        params = exact["params"]
        out_inst = exact["instances"][0].numpy()
        outline = aug({"rgb": rgb, "boxes": [boxes]}, params=params, **extra)
        poly = aug({"rgb": rgb, "boxes": [boxes],
                    "polygons": [[torch.from_numpy(r) for r in rings]]}, params=params, **extra)
        for mode, out in (("outline", outline), ("polygons", poly)):
            got = {int(j): b.double().numpy() for b, j in zip(out["boxes"][0], out["box_index"][0])}
            visible = {int(j): bool(v) for v, j in zip(out["box_visible"][0], out["box_index"][0])}
            for j, i in enumerate(ids.tolist()):
                truth = tight(out_inst == i)
                if mode == "outline" and j in got:
                    outline_boxes += 1
                    if truth is None:
                        hidden += 1
                        flagged_hidden += not visible[j]
                    else:
                        flagged_seen += not visible[j]
                if truth is None or j not in got:
                    continue
                box = got[j]
                past = max(*(truth[:2] - box[:2]), *(box[2:] - truth[2:]))
                rows[mode].append(dict(past=float(past), diff=float(np.abs(box - truth).max()),
                                       pixels=int((out_inst == i).sum()),
                                       iou=iou(box, truth),
                                       holds=bool(
                                           (box[:2] <= truth[:2] + 0.5 + 1e-6).all()
                                           and (box[2:] >= truth[2:] - 0.5 - 1e-6).all())))
        compared_objects += sum(tight(out_inst == i) is not None for i in ids.tolist())

    def summary(r: list[dict]) -> dict:
        past = np.array([x["past"] for x in r])
        diff = np.array([x["diff"] for x in r])
        ious = np.array([x["iou"] for x in r])
        return dict(objects=len(r), past_max=float(past.max()), past_median=float(np.median(past)),
                    diff_median=float(np.median(diff)), diff_max=float(diff.max()),
                    iou_median=float(np.median(ious)), iou_min=float(ious.min()),
                    holds=float(np.mean([x["holds"] for x in r])),
                    within_1px_of_exact=float(np.mean(past <= 1.0)),
                    within_1px_16=float(np.mean(past[np.array([x["pixels"] for x in r]) >= 16]
                                                <= 1.0)))
    return dict(name=name, images=images, seed=seed, objects_seen=compared_objects,
                outline=summary(rows["outline"]), polygons=summary(rows["polygons"]),
                outline_boxes=outline_boxes, hidden=hidden, hidden_flagged=flagged_hidden,
                visible_flagged=flagged_seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/box_accuracy.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    h, w = SOURCE
    fisheye = ot.Camera("equidistant", [38.0, 38.0, w / 2 - 0.5, h / 2 - 0.5], SOURCE,
                        fov=190 * DEG)
    cata = ot.Camera("unified", [30.0, 30.0, w / 2 - 0.5, h / 2 - 0.5, 0.9, 0, 0, 0, 0], SOURCE,
                     fov=200 * DEG, blind_fov=30 * DEG)
    in_circle = (lambda cx, cy: math.hypot(cx - w / 2, cy - h / 2) < 60)
    cases = [
        ("pinhole 100 deg", ot.augment.RandomReproject(OUTPUT, source_fov=100 * DEG, seed=1,
                                                       interpolation="nearest"), None,
         lambda cx, cy: True),
        ("fisheye source (equidistant 190 deg)", ot.augment.RandomReproject(
            OUTPUT, seed=2, interpolation="nearest", yaw_range=(-40 * DEG, 40 * DEG),
            pitch_range=(-40 * DEG, 40 * DEG)), fisheye, in_circle),
        ("catadioptric source (unified, xi 0.9)", ot.augment.RandomReproject(
            OUTPUT, seed=3, interpolation="nearest", yaw_range=(-40 * DEG, 40 * DEG),
            pitch_range=(-40 * DEG, 40 * DEG)), cata, in_circle),
    ]
    results = [scenario(name, aug, cam, ok, args.images, args.seed + k)
               for k, (name, aug, cam, ok) in enumerate(cases)]
    lines = ["| source | mode | objects | past the exact box: max (median) px | within 1 px of "
             "it (objects of 16 px or more) | side difference: median (max) px | IoU median (min) "
             "| holds it (to 0.5 px) |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        for mode in ("outline", "polygons"):
            s = r[mode]
            lines.append(f"| {r['name']} | {mode} | {s['objects']} | {s['past_max']:.2f} "
                         f"({s['past_median']:.2f}) | {100 * s['within_1px_of_exact']:.1f} % "
                         f"({100 * s['within_1px_16']:.1f} %) | "
                         f"{s['diff_median']:.2f} ({s['diff_max']:.2f}) "
                         f"| {s['iou_median']:.3f} ({s['iou_min']:.3f}) "
                         f"| {100 * s['holds']:.0f} % |")
    lines.append("")
    lines.append("| source | outline boxes | of an object with no output pixel | of those flagged "
                 "`box_visible` False | visible objects flagged |")
    lines.append("|---|---:|---:|---:|---:|")
    for r in results:
        lines.append(f"| {r['name']} | {r['outline_boxes']} | {r['hidden']} | "
                     f"{r['hidden_flagged']} | {r['visible_flagged']} |")
    table = "\n".join(lines)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(dict(results=results, torch=torch.__version__),
                                           indent=1) + "\n")
    atomic_write_text(args.out.with_suffix(".md"), table + "\n")


if __name__ == "__main__":
    main()
