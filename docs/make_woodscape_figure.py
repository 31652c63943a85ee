"""Draw docs/images/woodscape_fv.png: a Cityscapes-shaped frame through WoodScape's front camera.

Left: a 256 x 512 pinhole frame of the built-in town (fx = fy = 2262 / 4: Cityscapes' geometry
at a quarter) and its labels. Then the same frame through WoodScape's FV lens (its `front.json`,
the `woodscape` model, on a quarter of its 1280 x 966 sensor) with
`RandomReproject(None, camera=FV)`: without jitter (what `ot.reproject` gives, bit for bit), and
two draws with `focal_jitter=0.05`, `center_jitter=4` and the module's default attitude ranges.
The Cityscapes frame sees about 48 degrees, the lens about 190: the frame fills the middle of
the lens's image circle. WoodScape's own `front.jpg` is not reproduced here (its files are not
part of this repository). Public API only. From the repository root::

    python docs/make_woodscape_figure.py
"""

import json
import tempfile
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import omniscape_torch as ot

H, W, F = 256, 512, 2262 / 4
K = torch.tensor([F, F, (W - 1) / 2, (H - 1) / 2], dtype=torch.float64)
#: WoodScape's FV calibration (valeoai/WoodScape, scripts/calibration/front.json, MIT licence):
#: the intrinsic part, as its file gives it.
FRONT = {"intrinsic": {"aspect_ratio": 1.0, "cx_offset": 3.942, "cy_offset": -3.093,
                       "height": 966.0, "k1": 339.749, "k2": -31.988, "k3": 48.275,
                       "k4": -7.201, "model": "radial_poly", "poly_order": 4, "width": 1280.0},
         "extrinsic": {"quaternion": [0.5941767906169857, -0.5878843193897473,
                                      0.3873184109007999, -0.3890121040340926],
                       "translation": [3.7484, 0.0, 0.6601699999999999]},
         "name": "FV"}

with tempfile.TemporaryDirectory() as folder:
    path = Path(folder) / "front.json"
    path.write_text(json.dumps(FRONT))
    full = ot.Camera.load(path)
p = full.params.detach().double().clone()
p[:2] = (p[:2] + 0.5) / 4 - 0.5          # a quarter of the sensor: the centre ...
p[3:] = p[3:] / 4                        # ... and rho (pixels)
fv = ot.Camera("woodscape", p, (full.image_size[0] // 4, full.image_size[1] // 4))

ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                        indexing="ij")
rays = torch.stack(((xs - K[2]) / F, (ys - K[3]) / F, torch.ones_like(xs)), -1)
rays = rays / rays.norm(dim=-1, keepdim=True)
view = ot.scenes.Town(seed=0).render_rays(torch.tensor([0.0, -1.2, 0.0]), rays)
frame = (view["rgb"] * 255).round().to(torch.uint8).permute(2, 0, 1)[None]
labels = view["labels"].long()[None]
sample = {"rgb": frame, "labels": labels, "intrinsics": K}

zero = dict(roll_range=(0.0, 0.0), pitch_range=(0.0, 0.0), yaw_range=(0.0, 0.0))
still = ot.augment.RandomReproject(None, camera=fv, seed=0, **zero)(sample)
jittered = ot.augment.RandomReproject(None, camera=fv, focal_jitter=0.05, center_jitter=4.0,
                                      seed=3)
draws = [jittered(sample) for _ in range(2)]


def tile(rgb: torch.Tensor) -> np.ndarray:
    return rgb[0].permute(1, 2, 0).numpy()


def pad(image: np.ndarray, height: int) -> np.ndarray:
    return np.pad(image, ((0, height - image.shape[0]), (0, 8), (0, 0)), constant_values=255)


height = max(2 * H + 8, fv.image_size[0])
source = np.concatenate([tile(frame), np.full((8, W, 3), 255, np.uint8),
                         ot.io.colorize(labels[0])], 0)
outputs = [tile(still["rgb"]), ot.io.colorize(still["labels"][0])]
outputs += [tile(d["rgb"]) for d in draws]
top = np.concatenate([pad(t, fv.image_size[0]) for t in outputs[:2]], 1)
bottom = np.concatenate([pad(t, fv.image_size[0]) for t in outputs[2:]], 1)
right = np.concatenate([top, np.full((8, top.shape[1], 3), 255, np.uint8), bottom], 0)
sheet = np.concatenate([pad(source, max(source.shape[0], right.shape[0])),
                        np.pad(right, ((0, max(source.shape[0], right.shape[0])
                                        - right.shape[0]), (0, 0), (0, 0)),
                               constant_values=255)], 1)
out = Path(__file__).parent / "images" / "woodscape_fv.png"
Image.fromarray(sheet).save(out, optimize=True)
valid = float(still["valid"].float().mean())
print(out, out.stat().st_size // 1024, "KB; the frame fills", round(100 * valid, 1), "% of FV")
