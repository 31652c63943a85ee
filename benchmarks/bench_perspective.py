"""Perspective datasets made into fisheyes: throughput of ``RandomReproject`` (framing and
antialiasing on, its defaults) against albumentations' fisheye and kornia's (issue 36, item 4).

Source: Cityscapes-shaped ``uint8`` RGB ``1024 x 2048`` with ``uint8`` labels (``--source``),
pinhole ``fx = fy = 2262``; output ``S x S`` for each ``--sizes`` (512, 1024). Rows:

* ``ours``: ``RandomReproject((S, S))`` (defaults: equidistant 160-200 deg, ``coverage_range``
  0.5-0.9) with ``antialias=True``, with the intrinsics, RGB ``uint8`` + labels int64 + valid;
* ``ours_point``: the same with ``antialias=False`` (point samples: what the prefilter costs);
* ``albumentations``: ``A.Compose([A.Resize(S, S), A.OpticalDistortion(mode="fisheye",
  p=1)])`` on the ``(H, W, 3)`` image and its mask (numpy, as it takes them); skipped, and
  said so, where albumentations cannot be imported (it is not a dependency: run this in a
  venv that has it, see ``bench_reproject.py``);
* ``kornia``: ``Resize((S, S))`` then ``RandomFisheye`` (its docstring's ranges) on float32
  RGB in [0, 1] with the labels as a 4th channel (its fisheye has no mask path: they are
  blended), per sample.

Modes: ``process`` (one process, ``--threads`` threads, per sample, round-robin medians:
``common.measure``) and ``workers`` (a ``DataLoader`` of ``--workers`` workers, one thread each,
batch ``--batch``: the augmentation in the dataset, per sample (``sample``), or in
``collate_fn`` on the stacked batch (``collate``; ours only, the peers being per-sample
tools); images per second from the first batch to the last of ``--batches`` batches,
the median of ``--rounds`` epochs, rows interleaved).

Headline: ours / albumentations and ours / kornia images per second (targets >= 1.5 and
>= 1). Loads are recorded beside every figure (``loadavg`` at start and end).

Usage::

    python benchmarks/bench_perspective.py            # S = 512, 1024; both modes
    python benchmarks/bench_perspective.py --quick    # source 256 x 512, S = 128, seconds

Results: markdown on stdout and JSON (``--out``, default
``benchmarks/results/perspective.json``; ``--quick``: ``benchmarks/results/quick/``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, default_collate

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_main, run_record)
from omniscape_torch.augment import RandomReproject  # noqa: E402

try:
    import albumentations as A
except ImportError:
    A = None
try:
    import kornia.augmentation as KA
except ImportError:
    KA = None

SEED = 3636
TARGETS = {"albumentations": 1.5, "kornia": 1.0}


def _peers(size: int) -> dict:
    """The per-sample peers that can be imported: ``{name: fn(image_hwc, labels_hw)}``."""
    peers = {}
    if A is not None:
        album = A.Compose([A.Resize(size, size), A.OpticalDistortion(mode="fisheye", p=1.0)])
        peers["albumentations"] = lambda img, lab: album(image=img.numpy(), mask=lab.numpy())
    if KA is not None:
        resize = KA.Resize((size, size))
        fisheye = KA.RandomFisheye(torch.tensor([-0.3, 0.3]), torch.tensor([-0.3, 0.3]),
                                   torch.tensor([0.9, 1.0]), p=1.0)

        def kornia_call(img, lab):
            # RandomFisheye has no mask path (kornia 0.9 raises): the labels ride as a 4th
            # channel (blended; one call, the peer's cheapest way)
            x = torch.cat((img.permute(2, 0, 1).float() / 255, lab[None].float()))[None]
            return fisheye(resize(x))
        peers["kornia"] = kornia_call
    return peers


class Samples(Dataset):
    """``length`` samples cycling over the given images; ``apply``: a per-sample augmentation
    (``fn(image_hwc, labels)``) or None (the raw sample, for ``collate_fn``)."""

    def __init__(self, images, labels, length, apply=None):
        self.images, self.labels, self.length, self.apply = images, labels, length, apply

    def __len__(self):
        return self.length

    def __getitem__(self, i):
        img, lab = self.images[i % len(self.images)], self.labels[i % len(self.labels)]
        return self.apply(img, lab) if self.apply is not None else {"rgb": img, "labels": lab}


def _collate_ours(module: RandomReproject, intrinsics: torch.Tensor):
    def collate(samples):
        batch = default_collate(samples)
        return module({"rgb": batch["rgb"], "labels": batch["labels"],
                       "intrinsics": intrinsics})
    return collate


def _epoch(dataset, batch, workers, collate) -> float:
    """Images per second of one epoch after its first batch (fork, one thread a worker)."""
    loader = DataLoader(dataset, batch_size=batch, num_workers=workers, collate_fn=collate,
                        worker_init_fn=lambda _: torch.set_num_threads(1))
    it = iter(loader)
    next(it)
    start, n = time.perf_counter(), 0
    for _ in it:
        n += batch
    return n / (time.perf_counter() - start)


def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(args.threads)
    gen = torch.Generator().manual_seed(SEED)
    hs, ws = args.source
    focal = 2262.0 * ws / 2048
    intrinsics = torch.tensor([focal, focal, (ws - 1) / 2, (hs - 1) / 2], dtype=torch.float64)
    n_images = 4
    images = torch.randint(0, 256, (n_images, hs, ws, 3), generator=gen, dtype=torch.uint8)
    labels = torch.randint(0, 19, (n_images, hs, ws), generator=gen, dtype=torch.uint8)
    rows, skipped = [], {}
    if A is None:
        skipped["albumentations"] = "not importable (not a dependency)"
    if KA is None:
        skipped["kornia"] = "not importable"
    for size in args.sizes:
        def ours_of(module):
            return lambda img, lab: module({"rgb": img[None], "labels": lab[None],
                                            "intrinsics": intrinsics})
        fns = {"ours": ours_of(RandomReproject((size, size), seed=SEED, channels_last=True,
                                               antialias=True)),
               "ours_point": ours_of(RandomReproject((size, size), seed=SEED,
                                                     channels_last=True, antialias=False)),
               **_peers(size)}
        if "process" in args.modes:
            calls = [lambda fn=fn: [fn(images[i], labels[i]) for i in range(n_images)]
                     for fn in fns.values()]
            load = loadavg()
            with torch.no_grad():
                times = measure(calls, args.repeats, args.warmup)
            for name, t in zip(fns, times):
                rows.append({"mode": "process", "size": size, "name": name,
                             "images_per_s": n_images / t["median_s"],
                             "iqr_s": t["iqr_s"], "median_s": t["median_s"],
                             "loadavg": [load, loadavg()]})
        if "workers" in args.modes:
            cases = {f"{name}_sample": (Samples(images, labels, args.batch * args.batches, fn),
                                        lambda s: s) for name, fn in fns.items()}
            cases["ours_collate"] = (Samples(images, labels, args.batch * args.batches),
                                     _collate_ours(RandomReproject((size, size), seed=SEED,
                                                                   channels_last=True,
                                                                   antialias=True),
                                                   intrinsics))
            rates = {name: [] for name in cases}
            load = loadavg()
            for _ in range(args.rounds):
                for name, (dataset, collate) in cases.items():
                    rates[name].append(_epoch(dataset, args.batch, args.workers, collate))
            for name, values in rates.items():
                rows.append({"mode": "workers", "size": size, "name": name,
                             "images_per_s": float(np.median(values)), "epochs": values,
                             "loadavg": [load, loadavg()]})
    headline = []
    for row in rows:
        if not row["name"].startswith("ours"):
            continue
        for peer, target in TARGETS.items():
            key = peer if row["mode"] == "process" else f"{peer}_sample"
            other = [r for r in rows if r["mode"] == row["mode"] and r["size"] == row["size"]
                     and r["name"] == key]
            if other:
                ratio = row["images_per_s"] / other[0]["images_per_s"]
                headline.append({"mode": row["mode"], "size": row["size"], "ours": row["name"],
                                 "peer": peer, "ratio": ratio, "target": target,
                                 "meets_target": ratio >= target, "loadavg": row["loadavg"]})
    return {**run_record("perspective", torch.device("cpu"), args.threads),
            "versions_peers": {"albumentations": getattr(A, "__version__", None)},
            "setup": {"source": list(args.source), "focal": focal, "sizes": args.sizes,
                      "modes": args.modes, "workers": args.workers, "batch": args.batch,
                      "batches": args.batches, "rounds": args.rounds, "repeats": args.repeats,
                      "quick": args.quick, "seed": SEED},
            "rows": rows, "skipped": skipped, "headline": headline,
            "loadavg_start": load_start, "loadavg_end": loadavg()}


def markdown(result: dict) -> str:
    s = result["setup"]
    lines = [f"perspective -> fisheye: {s['source'][1]} x {s['source'][0]} uint8 RGB + labels, "
             f"commit {result['commit'][:12]}{' (dirty)' if result['dirty'] else ''}", "",
             "| mode | S | row | images/s | load (start, end) |", "|---|---:|---|---:|---|"]
    for r in result["rows"]:
        load = ", ".join(f"{v[0]:.1f}" if v else "?" for v in r["loadavg"])
        lines.append(f"| {r['mode']} | {r['size']} | {r['name']} | {r['images_per_s']:.1f} | "
                     f"{load} |")
    lines.append("")
    for name, why in result["skipped"].items():
        lines.append(f"skipped {name}: {why}")
    for h in result["headline"]:
        lines.append(f"{h['mode']} S={h['size']}: {h['ours']} / {h['peer']} {h['ratio']:.2f}x "
                     f"(target >= {h['target']}: {'ok' if h['meets_target'] else 'MISSED'})")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=positive_int, nargs="+", default=None)
    parser.add_argument("--source", type=positive_int, nargs=2, default=None,
                        metavar=("H", "W"), help="source size (1024 2048; 256 512 quick)")
    parser.add_argument("--modes", nargs="+", choices=("process", "workers"),
                        default=["process", "workers"])
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="threads of the one-process mode (1)")
    parser.add_argument("--workers", type=positive_int, default=2)
    parser.add_argument("--batch", type=positive_int, default=8)
    parser.add_argument("--batches", type=positive_int, default=None, help="per epoch (6; 3)")
    parser.add_argument("--rounds", type=positive_int, default=None, help="epochs a row (3; 1)")
    parser.add_argument("--repeats", type=positive_int, default=None, help="(5; 2)")
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="a smoke run")
    parser.add_argument("--out", type=Path, default=None, help="JSON output")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = results_path("perspective.json", quick=args.quick)
    defaults = {"sizes": ([512, 1024], [128]), "source": ([1024, 2048], [256, 512]),
                "batches": (6, 3), "rounds": (3, 1), "repeats": (5, 2)}
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
