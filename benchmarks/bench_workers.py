"""Augmentation where models are trained: ``RandomOmniCamera`` inside ``DataLoader`` workers.

Issue 17's throughput benchmark: images per second out of a ``torch.utils.data.DataLoader`` with
``--workers`` workers (default 2, one thread each, as PyTorch sets them), batch ``B`` (default
8), cubemaps ``6 x F x F`` (default F = 256: RGB + ``uint8`` labels) rendered to ``S x S``
fisheyes (default S = 512), a new random camera and attitude per sample, for each fisheye model
alone (``FISHEYE_MODELS``) and for their mix, with float32 and with ``uint8`` cubes. Rows, timed
round-robin (every row once per round, ``--rounds`` rounds):

* ``ours_collate``: the dataset returns cubes; ``collate_fn`` stacks a batch and applies
  ``RandomOmniCamera((S, S), F, fisheye_models=...)`` (``seed`` fixed: a different draw per
  worker and epoch);
* ``ours_sample``: the dataset applies the module to each sample (a batch of 1);
* ``peer``: what a user would write without this package, per sample in the dataset: numpy
  draws a camera of the model (fov uniform in 160-200 deg, image circle inscribed, Kannala-
  Brandt ``k1..k4`` uniform in +-0.02 with Newton's inverse in numpy; the unified, EUCM and
  double sphere lenses in RandomOmniCamera's ranges with their papers' closed-form
  unprojections, ``rays_of``), an attitude (roll +-25,
  pitch +-10 deg, any yaw), builds the maps (``bench_augment.atlas_maps``: face picking into
  the edge-padded atlas) and ``cv2.remap``s RGB (bilinear) and labels (nearest); OpenCV on one
  thread per worker (set in the parent before the workers fork).

Each epoch builds a fresh ``DataLoader`` (non-persistent workers, fork) over ``--batches``
batches; the throughput of an epoch is its images after the first batch over the time from the
first batch to the last (the steady state), and ``first_batch_s`` the time from creating the
iterator to the first batch (worker start included). Medians over the rounds.

Targets (issue 17): every model, and the mix, at least 1.5x the peer's images/s (``TARGET``);
Kannala-Brandt within 1.3x of equidistant's time (``KB_TARGET``).

Usage::

    python benchmarks/bench_workers.py            # 2 workers, B = 8, 6 x 256 -> 512 x 512
    python benchmarks/bench_workers.py --quick    # seconds: 6 x 32 -> 64 x 64, 2 rounds

Results: a markdown table on stdout and JSON (``--out``, default
``benchmarks/results/workers.json``, written atomically).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_augment import FOV_RANGE, atlas_maps, peer_atlas, peer_draw, SEED  # noqa: E402
from common import (begin_run, loadavg, positive_int, results_path, run_main,  # noqa: E402
                    run_record)
from omniscape_torch.augment import FISHEYE_MODELS, RandomOmniCamera  # noqa: E402

try:
    import cv2
except ImportError:   # the peer is skipped, our rows still run
    cv2 = None

TARGET = 1.5      # ours / peer images per second
KB_TARGET = 1.3   # Kannala-Brandt / equidistant time per image
KB_DISTORTION = 0.02   # RandomOmniCamera's default bound of k1..k4
MIX = "mix"


# --------------------------------------------------------------------------------------------
# The peer: numpy maps of every fisheye model + cv2.remap, per sample
# --------------------------------------------------------------------------------------------

#: The peer's lens parameters beyond the focal: RandomOmniCamera's default ranges.
LENS = {"unified": ((0.5, 1.0),), "eucm": ((0.55, 0.7), (0.9, 1.2)),
        "double_sphere": ((-0.3, 0.0), (0.5, 0.7))}


def radius_of(model: str, theta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The normalised image radius of a ray ``theta`` off the axis (``k``: the Kannala-Brandt
    coefficients, or the lens parameters of :data:`LENS`)."""
    if model == "equidistant":
        return theta
    if model == "equisolid":
        return 2 * np.sin(theta / 2)
    if model == "stereographic":
        return 2 * np.tan(theta / 2)
    s, c = np.sin(theta), np.cos(theta)
    if model == "unified":   # Mei, no distortion: x / (z + xi |p|)
        return s / (c + k[0])
    if model == "eucm":      # Khomenko et al.: x / (alpha d + (1 - alpha) z)
        alpha, beta = k[0], k[1]
        return s / (alpha * np.sqrt(beta * s * s + c * c) + (1 - alpha) * c)
    if model == "double_sphere":   # Usenko et al.: z' = xi + z, x / (alpha d2 + (1 - alpha) z')
        xi, alpha = k[0], k[1]
        z = xi + c
        return s / (alpha * np.sqrt(s * s + z * z) + (1 - alpha) * z)
    t2 = theta * theta
    return theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))


def rays_of(model: str, x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Unit rays ``(H, W, 3)`` of the normalised image points ``(x, y)``: each model's closed
    form unprojection (the papers'), or the radius -> angle inverse of :func:`theta_of`."""
    r2 = x * x + y * y
    if model in ("unified", "eucm", "double_sphere"):
        if model == "unified":
            xi = k[0]
            factor = (xi + np.sqrt(np.maximum(1 + (1 - xi * xi) * r2, 0))) / (r2 + 1)
            mx, my, mz = factor * x, factor * y, factor - xi
        else:
            alpha, beta = (k[0], k[1]) if model == "eucm" else (k[1], 1.0)
            mz = (1 - beta * alpha * alpha * r2) / (
                alpha * np.sqrt(np.maximum(1 - (2 * alpha - 1) * beta * r2, 0)) + 1 - alpha)
            mx, my = x, y
            if model == "double_sphere":
                xi = k[0]
                factor = (mz * xi + np.sqrt(np.maximum(mz * mz + (1 - xi * xi) * r2, 0))) / (
                    mz * mz + r2)
                mx, my, mz = factor * x, factor * y, factor * mz - xi
        rays = np.stack((mx, my, mz), axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    r = np.sqrt(r2)
    theta = theta_of(model, r, k.astype(np.float32)).astype(np.float32)
    scale = np.where(r > 0, np.sin(theta) / np.maximum(r, 1e-12), 1).astype(np.float32)
    return np.stack((x * scale, y * scale, np.cos(theta)), axis=-1)


def theta_of(model: str, r: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Inverse of :func:`radius_of`: closed forms, Newton's method (10 steps) for
    Kannala-Brandt, as a numpy user would write them."""
    if model == "equidistant":
        return r
    if model == "equisolid":
        return 2 * np.arcsin(np.minimum(r / 2, 1))
    if model == "stereographic":
        return 2 * np.arctan(r / 2)
    theta = r.copy()
    for _ in range(10):
        t2 = theta * theta
        f = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - r
        df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        theta = theta - f / df
    return theta


def peer_maps(model: str, rng: np.random.Generator, size: int, face: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (float32, atlas pixels) of a random ``size x size`` fisheye of
    ``model`` (image circle inscribed), randomly rotated; invalid pixels map outside."""
    fov, rotation = peer_draw(rng)
    if model == "kannala_brandt":
        k = rng.uniform(-KB_DISTORTION, KB_DISTORTION, 4)
    elif model in LENS:
        k = np.array([rng.uniform(*bounds) for bounds in LENS[model]] + [0.0] * 2)[:4]
    else:
        k = np.zeros(4)
    focal = (size / 2 - 0.5) / radius_of(model, np.array(fov / 2), k)
    centre = (size - 1) / 2
    coords = ((np.arange(size, dtype=np.float32) - centre) / focal).astype(np.float32)
    x, y = np.meshgrid(coords, coords)
    rays = rays_of(model, x, y, k).astype(np.float32)
    outside = ~(rays[..., 2] >= np.cos(fov / 2))   # the cone (and rays the model has not)
    return atlas_maps(rays @ rotation.astype(np.float32).T, outside, face)


# --------------------------------------------------------------------------------------------
# Datasets and collate functions (module level: the workers pickle them)
# --------------------------------------------------------------------------------------------

class Cubes(Dataset):
    """``length`` samples cycling through a pool of cubes: ``{"rgb": (6, 3, F, F), "labels":
    (6, F, F) uint8}`` (``mode="cube"``), the same rendered by ``module`` (``"ours"``), or by
    the peer (``"peer"``: numpy HWC faces, rendered per sample)."""

    def __init__(self, rgb: torch.Tensor, labels: torch.Tensor, length: int, mode: str,
                 module: RandomOmniCamera | None = None, model: str = "equidistant",
                 size: int = 0) -> None:
        self.rgb, self.labels, self.length, self.mode = rgb, labels, length, mode
        self.module, self.model, self.size = module, model, size
        if mode == "peer":
            self.rgb_np = [np.ascontiguousarray(c.permute(0, 2, 3, 1).numpy()) for c in rgb]
            self.labels_np = [np.ascontiguousarray(lab.numpy()) for lab in labels]
            self.models = FISHEYE_MODELS if model == MIX else (model,)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int) -> dict:
        j = i % len(self.rgb)
        if self.mode == "cube":
            return {"rgb": self.rgb[j], "labels": self.labels[j]}
        if self.mode == "ours":
            out = self.module(self.rgb[j:j + 1], labels=self.labels[j:j + 1])
            return {"rgb": out["rgb"][0], "labels": out["labels"][0], "valid": out["valid"][0]}
        rng = np.random.default_rng([SEED, torch.initial_seed() % 2**32, i])
        model = self.models[int(rng.integers(len(self.models)))]
        face = self.rgb_np[j].shape[1]
        map_x, map_y = peer_maps(model, rng, self.size, face)
        rgb = cv2.remap(peer_atlas(self.rgb_np[j]), map_x, map_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
        labels = cv2.remap(peer_atlas(self.labels_np[j]), map_x, map_y, cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=255)
        return {"rgb": torch.from_numpy(rgb).permute(2, 0, 1), "labels": torch.from_numpy(labels),
                "valid": torch.from_numpy(map_x >= 0)}


class Augment:
    """``collate_fn``: the default collate, then the module on the batch."""

    def __init__(self, module: RandomOmniCamera) -> None:
        self.module = module

    def __call__(self, samples: list[dict]) -> dict:
        batch = torch.utils.data.default_collate(samples)
        return self.module(batch["rgb"], labels=batch["labels"])


def epoch(dataset: Dataset, batch: int, workers: int, collate=None) -> tuple[float, float]:
    """(seconds to the first batch, images per second after it) of one epoch."""
    loader = DataLoader(dataset, batch_size=batch, num_workers=workers, collate_fn=collate,
                        multiprocessing_context="fork" if workers else None)
    start = time.perf_counter()
    first = end = None
    images = 0
    for out in loader:
        end = time.perf_counter()
        if first is None:
            first = end
        else:
            images += out["rgb"].shape[0]
    return first - start, images / (end - first)


# --------------------------------------------------------------------------------------------
# The benchmark
# --------------------------------------------------------------------------------------------

def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(args.threads)
    if cv2 is not None:
        # the peer runs in forked workers on one thread each: set before forking (OpenCV's
        # thread pool does not survive a fork; changing it in a child deadlocked)
        cv2.setNumThreads(1)
    gen = torch.Generator().manual_seed(SEED)
    pool = 4
    cube = torch.rand(pool, 6, 3, args.face, args.face, generator=gen)
    cubes = {"float32": cube, "uint8": (cube * 255).round().to(torch.uint8)}
    labels = torch.randint(0, 13, (pool, 6, args.face, args.face), generator=gen,
                           dtype=torch.uint8)
    length = args.batch * args.batches
    size = (args.size, args.size)
    rows: list[tuple[dict, Dataset, object]] = []
    for model in (*FISHEYE_MODELS, MIX):
        models = FISHEYE_MODELS if model == MIX else (model,)
        for dtype, rgb in cubes.items():
            def module() -> RandomOmniCamera:
                return RandomOmniCamera(size, args.face, mode="fisheye", fisheye_models=models,
                                        seed=SEED)

            head = {"model": model, "dtype": dtype}
            rows.append(({**head, "row": "ours_collate"},
                         Cubes(rgb, labels, length, "cube"), Augment(module())))
            rows.append(({**head, "row": "ours_sample"},
                         Cubes(rgb, labels, length, "ours", module()), None))
            if cv2 is not None:
                rows.append(({**head, "row": "peer"},
                             Cubes(rgb, labels, length, "peer", model=model, size=args.size),
                             None))
    firsts: list[list[float]] = [[] for _ in rows]
    rates: list[list[float]] = [[] for _ in rows]
    from tqdm import tqdm
    for _ in tqdm(range(args.rounds), desc="rounds", unit="round", file=sys.stderr):
        for k, (_, dataset, collate) in enumerate(rows):
            first, rate = epoch(dataset, args.batch, args.workers, collate)
            firsts[k].append(first)
            rates[k].append(rate)
    results = []
    for (head, _, _), first, rate in zip(rows, firsts, rates):
        results.append({**head, "images_per_s": float(np.median(rate)),
                        "images_per_s_all": rate, "first_batch_s": float(np.median(first))})
    by = {(r["model"], r["dtype"], r["row"]): r for r in results}
    ratios = []
    for model in (*FISHEYE_MODELS, MIX):
        for dtype in cubes:
            peer = by.get((model, dtype, "peer"))
            for row in ("ours_collate", "ours_sample"):
                if peer is not None:
                    value = by[model, dtype, row]["images_per_s"] / peer["images_per_s"]
                    ratios.append({"model": model, "dtype": dtype, "ours": row, "peer": "peer",
                                   "ratio": value, "target": TARGET,
                                   "meets_target": value >= TARGET})
    for dtype in cubes:
        for row in ("ours_collate", "ours_sample"):
            value = by["equidistant", dtype, row]["images_per_s"] / by[
                "kannala_brandt", dtype, row]["images_per_s"]
            ratios.append({"model": "kannala_brandt / equidistant (time)", "dtype": dtype,
                           "ours": row, "peer": row, "ratio": value, "target": KB_TARGET,
                           "meets_target": value <= KB_TARGET})
    record = run_record("workers", torch.device("cpu"), args.threads, cv2)
    record.update({"setup": {"workers": args.workers, "batch": args.batch, "face": args.face,
                             "size": args.size, "batches": args.batches, "rounds": args.rounds,
                             "fov_deg": [math.degrees(v) for v in FOV_RANGE]},
                   "loadavg_start": load_start, "loadavg_end": loadavg(), "rows": results,
                   "ratios": ratios})
    return record


def markdown(result: dict) -> str:
    s = result["setup"]
    lines = [f"DataLoader, {s['workers']} workers, batch {s['batch']}, 6 x {s['face']} -> "
             f"{s['size']} x {s['size']}, medians of {s['rounds']} epochs of {s['batches']} "
             f"batches; load {result['loadavg_start']} -> {result['loadavg_end']}", "",
             "| model | cube | row | images/s | first batch |", "|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['model']} | {r['dtype']} | {r['row']} | {r['images_per_s']:.1f} | "
                     f"{r['first_batch_s']:.2f} s |")
    lines += ["", "| model | cube | ours / peer | ratio | target |", "|---|---|---|---|---|"]
    for q in result["ratios"]:
        mark = "met" if q["meets_target"] else "missed"
        sign = ">=" if q["peer"] == "peer" else "<="
        lines.append(f"| {q['model']} | {q['dtype']} | {q['ours']} / {q['peer']} | "
                     f"{q['ratio']:.2f} | {sign} {q['target']} ({mark}) |")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=positive_int, default=2)
    p.add_argument("--batch", type=positive_int, default=8)
    p.add_argument("--face", type=positive_int, default=256)
    p.add_argument("--size", type=positive_int, default=512)
    p.add_argument("--batches", type=positive_int, default=16, help="batches per epoch")
    p.add_argument("--rounds", type=positive_int, default=5)
    p.add_argument("--threads", type=positive_int, default=2,
                   help="torch threads of the main process (workers use one each)")
    p.add_argument("--quick", action="store_true", help="6 x 32 -> 64 x 64, 2 rounds")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("workers.json", quick=args.quick)
    if args.quick:
        args.face, args.size, args.rounds, args.batches = 32, 64, 2, 3
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
