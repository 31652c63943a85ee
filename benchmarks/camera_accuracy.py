"""Round-trip accuracy of every camera model, over its whole valid domain.

For each parameter set of ``tests/conftest.py`` (realistic lenses, xi > 1, lenses that fold
before 180 degrees, the real OCamCalib calibration): directions on a Fibonacci sphere inside
the model's limit (1e-4 rad from a fold), projected and unprojected (angular error), and the
pixels of the image unprojected and projected back (pixel error), in float64 and float32.

    python benchmarks/camera_accuracy.py [--out benchmarks/results/camera_accuracy.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import omniscape_torch as ot  # noqa: E402
from conftest import CASES, fibonacci_sphere  # noqa: E402
from omniscape_torch.io import atomic_write_text  # noqa: E402

FOLD_MARGIN, FOLD_MARGIN_32 = 1e-4, 1e-2


def theta_of(p):
    return torch.atan2(torch.linalg.vector_norm(p[..., :2], dim=-1), p[..., 2])


def angle(a, b):
    return torch.atan2(torch.linalg.vector_norm(torch.cross(a, b, dim=-1), dim=-1),
                       (a * b).sum(-1))


def measure(name, params, size):
    model = ot.cameras.get_model(name)
    p = torch.tensor(params, dtype=torch.float64)
    limit = float(model.max_angle(p))
    dirs = fibonacci_sphere(20000)
    dirs = dirs[theta_of(dirs) < limit - FOLD_MARGIN]
    px, valid = model.project(dirs, p)
    centre, _ = model.project(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), p)
    near = valid & (torch.linalg.vector_norm(px - centre, dim=-1) < 4 * max(size))
    rays, v2 = model.unproject(px[near], p)
    rad64 = float(angle(rays[v2], dirs[near][v2]).max())

    h, w = size
    lo = -0.49 if name == "equirectangular" else -0.5
    v, u = torch.meshgrid(torch.linspace(lo, h - 1 - lo, 201, dtype=torch.float64),
                          torch.linspace(-0.5, w - 0.5, 201, dtype=torch.float64), indexing="ij")
    pix = torch.stack((u, v), -1).reshape(-1, 2)
    r, ok = model.unproject(pix, p)
    ok = ok & (theta_of(r) < limit - FOLD_MARGIN)
    back, ok2 = model.project(r[ok], p)
    err = (back - pix[ok]).abs()
    if name == "equirectangular":
        err[:, 0] = torch.remainder(err[:, 0] + 1, w) - 1
    px64 = float(err.abs()[ok2].max())

    keep = ok & (theta_of(r) < limit - FOLD_MARGIN_32)
    r32, a = model.unproject(pix[keep].float(), p.float())
    b32, b = model.project(r32, p.float())
    err32 = (b32.double() - pix[keep]).abs()[a & b]
    if name == "equirectangular":
        err32[:, 0] = torch.remainder(err32[:, 0] + 1, w) - 1
    return {"model": name, "params": params, "limit_deg": limit * 180 / torch.pi,
            "directions": int(near.sum()), "pixels": int(ok.sum()),
            "rays_rad_f64": rad64, "pixels_px_f64": px64,
            "pixels_px_f32": float(err32.abs().max())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/camera_accuracy.json")
    args = parser.parse_args(argv)
    rows = [measure(name, params, size) for name, cases in CASES.items()
            for params, size in cases]
    print("| model | limit (deg) | directions | max ray error f64 (rad) | pixels | "
          "max px error f64 | max px error f32 |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['model']} | {r['limit_deg']:.2f} | {r['directions']} | "
              f"{r['rays_rad_f64']:.1e} | {r['pixels']} | {r['pixels_px_f64']:.1e} | "
              f"{r['pixels_px_f32']:.1e} |")
    atomic_write_text(args.out, json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
