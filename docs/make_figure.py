"""Draw docs/images/town_fisheye_catadioptric.png: the README's and the docs' picture.

One cubemap of the built-in town, rendered at eye height on the main street, sampled through a
190-degree equidistant fisheye and a 230-degree catadioptric camera (the presets), with the
fisheye's labels in CARLA's palette. Public API only. From the repository root::

    python docs/make_figure.py
"""

from pathlib import Path

import numpy as np
import torch
from PIL import Image

import omniscape_torch as ot

SIZE = 320          # pixels of each image
FACE = 256          # cube face size

town = ot.scenes.Town(seed=0)
cube = town.render_cubemap(torch.tensor([0.0, -1.2, 0.0]), face_size=FACE, weather="clear_noon",
                           antialias=2)

fisheye = ot.presets.fisheye((SIZE, SIZE))                      # equidistant, 190 degrees
cata, cata_rotation = ot.presets.catadioptric((SIZE, SIZE))     # unified, looking down
fish_out = ot.OmniProjection(fisheye, FACE).render(rgb=cube["rgb"], labels=cube["labels"])
cata_out = ot.OmniProjection(cata, FACE).render(rgb=cube["rgb"], rotation=cata_rotation[None])


def to_uint8(rgb):
    return (rgb[0].permute(1, 2, 0).clamp(0, 1) * 255).round().to(torch.uint8).numpy()


labels = ot.io.colorize(fish_out["labels"][0])
gap = np.full((SIZE, 8, 3), 255, np.uint8)
sheet = np.concatenate([to_uint8(fish_out["rgb"]), gap, labels, gap, to_uint8(cata_out["rgb"])], 1)
out = Path(__file__).parent / "images" / "town_fisheye_catadioptric.png"
Image.fromarray(sheet).save(out, optimize=True)
print(out, out.stat().st_size // 1024, "KB")
