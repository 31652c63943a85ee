"""Draw docs/images/framing_coverage.png: a Cityscapes-shaped frame through RandomReproject at
a few coverages, and a 1-px line grid without and with antialiasing.

Top row: a 256 x 512 pinhole frame of the built-in town (fx = fy = 2262 / 4: Cityscapes'
geometry at a quarter), then the same frame through a 180 degree equidistant fisheye (no turn)
at the inscribed image circle (``focal_scale_range=(1, 1)``, the old default: 4 % of the output
valid) and framed to 30, 60 and 90 % of the output (``coverage_range=(c, c)``). Bottom row: a
1-px line grid of period 4 (same geometry) at the inscribed circle, point samples
(``antialias=False``) against the prefilter (the default). Public API only. From the
repository root::

    python docs/make_framing_figure.py
"""

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import omniscape_torch as ot

H, W, F = 256, 512, 2262 / 4
OUT = 192
K = torch.tensor([F, F, (W - 1) / 2, (H - 1) / 2], dtype=torch.float64)

ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                        indexing="ij")
rays = torch.stack(((xs - K[2]) / F, (ys - K[3]) / F, torch.ones_like(xs)), -1)
rays = rays / rays.norm(dim=-1, keepdim=True)
town = ot.scenes.Town(seed=0)
frame = town.render_rays(torch.tensor([0.0, -1.2, 0.0]), rays)["rgb"]      # (H, W, 3)
frame = (frame * 255).round().to(torch.uint8).permute(2, 0, 1)[None]
grid = (((torch.arange(H) % 4 == 0)[:, None] | (torch.arange(W) % 4 == 0)[None, :])
        .to(torch.uint8) * 255)[None, None].expand(1, 3, H, W)

level = dict(fisheye_models=("equidistant",), fov_range=(math.pi, math.pi), roll_range=(0, 0),
             pitch_range=(0, 0), yaw_range=(0, 0), seed=0)


def fisheye(image, antialias=True, **framing):
    aug = ot.augment.RandomReproject((OUT, OUT), antialias=antialias, **level, **framing)
    out = aug({"rgb": image, "intrinsics": K})
    return out["rgb"][0].permute(1, 2, 0).numpy(), float(out["valid"].float().mean())


def pad(tile, height=H):
    return np.pad(tile, ((0, height - tile.shape[0]), (0, 8), (0, 0)), constant_values=255)


tiles, shares = [pad(frame[0].permute(1, 2, 0).numpy())], []
for framing in ({"focal_scale_range": (1.0, 1.0)},
                *({"coverage_range": (c, c)} for c in (0.3, 0.6, 0.9))):
    tile, share = fisheye(frame, **framing)
    tiles.append(pad(tile))
    shares.append(share)
top = np.concatenate(tiles, 1)
bottom = np.concatenate([pad(fisheye(grid, antialias=a, focal_scale_range=(1.0, 1.0))[0], OUT)
                         for a in (False, True)], 1)
bottom = np.pad(bottom, ((8, 0), (0, top.shape[1] - bottom.shape[1]), (0, 0)),
                constant_values=255)
sheet = np.concatenate([top, bottom], 0)
out = Path(__file__).parent / "images" / "framing_coverage.png"
Image.fromarray(sheet).save(out, optimize=True)
print(out, out.stat().st_size // 1024, "KB; valid shares", [round(s, 3) for s in shares])
