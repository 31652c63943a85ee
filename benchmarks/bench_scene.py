"""Render time of the procedural town (``omniscape_torch.scenes.Town``).

Rows:

* ``cubemap``: one ``render_cubemap`` of 6 x F x F texels (RGB, planar depth, labels) from the
  default pose (the centre line at eye height, looking along the road), per weather preset
  given (``night`` adds the street lamps' lighting);
* ``rays``: ``render_rays`` of N x N arbitrary unit rays (a fisheye-sized ground-truth image) from
  the same pose, the exact path that culls nothing.

Timing: ``--warmup`` untimed calls, then ``--repeats`` timed calls, round-robin over the rows
(``benchmarks/common.py``), median and IQR reported. Target: a 6 x 256 cubemap well under 1 s
on 2 CPU cores.

Usage::

    python benchmarks/bench_scene.py               # 6 x 256, 2 threads
    python benchmarks/bench_scene.py --quick       # fewer repeats

Results: a table on stdout and JSON (``--out``, default ``benchmarks/results/scene.json``,
written atomically with ``omniscape_torch.io.atomic_write_text``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import git_commit, machine_info, measure, results_path, write_json_atomic  # noqa: E402
from omniscape_torch.scenes import Town  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--face-size", type=int, default=256)
    ap.add_argument("--rays", type=int, default=256, help="N: render_rays of N x N rays")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--weathers", default="clear_noon,night")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="3 repeats, 1 warm-up")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("scene.json", quick=args.quick)
    if args.quick:
        args.repeats, args.warmup = 3, 1
    torch.set_num_threads(args.threads)
    device = torch.device("cpu")

    t0 = time.perf_counter()
    town = Town(args.seed)
    build_s = time.perf_counter() - t0
    pose = torch.tensor([0.0, -1.2, 0.0])
    F, N = args.face_size, args.rays
    # N x N unit rays over a hemisphere-and-a-bit (an equidistant fisheye's rays, 200 degrees)
    g = (torch.arange(N, dtype=torch.float32) + 0.5) / N * 2 - 1
    v, u = torch.meshgrid(g, g, indexing="ij")
    theta = torch.sqrt(u * u + v * v).clamp(max=1) * torch.deg2rad(torch.tensor(100.0))
    phi = torch.atan2(v, u)
    dirs = torch.stack([torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi),
                        torch.cos(theta)], -1)

    rows, fns = [], []
    for w in args.weathers.split(","):
        rows.append({"name": "cubemap", "weather": w, "face_size": F, "texels": 6 * F * F})
        fns.append(lambda w=w: town.render_cubemap(pose, face_size=F, weather=w))
    rows.append({"name": "rays", "weather": "clear_noon", "rays": N * N})
    fns.append(lambda: town.render_rays(pose, dirs))
    stats = measure(fns, args.repeats, args.warmup, device)
    for r, s in zip(rows, stats):
        r.update(s)

    print(f"town seed {args.seed}: {town.boxes_lo.shape[0]} boxes, {town.cyl.shape[0]} "
          f"cylinders, {town.sph.shape[0]} spheres; built in {build_s * 1e3:.1f} ms; "
          f"{args.threads} threads")
    print("| render | weather | size | median ms | IQR ms |")
    print("|---|---|---|---|---|")
    for r in rows:
        size = f"6 x {F}" if r["name"] == "cubemap" else f"{N} x {N} rays"
        print(f"| {r['name']} | {r['weather']} | {size} | {r['median_s'] * 1e3:.1f} | "
              f"{r['iqr_s'] * 1e3:.1f} |")
    commit, dirty = git_commit()
    data = {
        "benchmark": "scene",
        "machine": machine_info(device),
        "torch": torch.__version__,
        "commit": commit,
        "dirty": dirty,
        "threads": args.threads,
        "repeats": args.repeats,
        "warmup": args.warmup,
        "seed": args.seed,
        "primitives": {"boxes": town.boxes_lo.shape[0], "cylinders": town.cyl.shape[0],
                       "spheres": town.sph.shape[0]},
        "build_s": build_s,
        "rows": rows,
    }
    write_json_atomic(data, args.out)
    print(f"wrote {args.out}")
    return data


if __name__ == "__main__":
    main()
