"""Draw docs/images/detection.png: boxes and keypoints through the augmentation (issue 35).

One cubemap of the built-in town. Its objects (cars, pedestrians, poles, signs: the connected
regions of those classes on a face, those a face holds whole) get instance ids, boxes and a
keypoint each (the centre of the object's pixels). Three panels:

1. the front face as a perspective image, with its boxes and keypoints;
2. that image through ``RandomReproject`` (a 120-degree equidistant fisheye, a drawn attitude):
   the boxes in outline mode and the keypoints, as the module returns them;
3. the cube through ``RandomOmniCamera(mode="catadioptric")``: the boxes from the cube's
   instance ids (a cube has no 2D boxes) and the keypoints given as ``(face, x, y)``.

Public API only; scipy labels the regions. From the repository root::

    python docs/make_detection_figure.py
"""

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from scipy import ndimage

import omniscape_torch as ot

SIZE = 320          # pixels of each panel
FACE = 256          # cube face size
THINGS = (4, 5, 10, 12)   # Pedestrian, Pole, Vehicle, TrafficSign
COLOURS = ("#ff3b30", "#ffcc00", "#34c759", "#0a84ff", "#ff9f0a", "#bf5af2")

town = ot.scenes.Town(seed=0)
cube = town.render_cubemap(torch.tensor([0.0, -1.2, 0.0]), face_size=FACE, weather="clear_noon",
                           antialias=2)

# instance ids: per face, the connected regions of the object classes held whole by the face
instances = torch.zeros(1, 6, FACE, FACE, dtype=torch.int64)
keypoints, boxes, next_id = [], [], 1
for face in range(6):
    labels = cube["labels"][0, face].numpy()
    for cls in THINGS:
        regions, count = ndimage.label(labels == cls)
        for k in range(1, count + 1):
            rows, cols = np.nonzero(regions == k)
            if len(rows) < 30 or rows.min() == 0 or cols.min() == 0 or \
                    rows.max() == FACE - 1 or cols.max() == FACE - 1:
                continue
            instances[0, face][torch.from_numpy(regions == k)] = next_id
            box = [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]   # XYXY corners
            keypoints.append((face, cols.mean() + 0.5, rows.mean() + 0.5))
            boxes.append((face, next_id, box))
            next_id += 1
front = [(i, box) for face, i, box in boxes if face == 0]
front_kp = torch.tensor([[x, y] for face, x, y in keypoints if face == 0], dtype=torch.float32)

# 2. the front face, a perspective image (fx = F / 2), through a random fisheye
fish = ot.augment.RandomReproject((SIZE, SIZE), source_fov=math.pi / 2,
                                  fov_range=(math.radians(120), math.radians(120)), seed=3)
fish_out = fish({"rgb": cube["rgb"][:, 0], "boxes": [torch.tensor([b for _, b in front],
                                                                   dtype=torch.float32)],
                 "keypoints": front_kp[None]})

# 3. the cube through a random catadioptric camera, boxes from the instance ids
cata = ot.augment.RandomOmniCamera((SIZE, SIZE), FACE, mode="catadioptric", seed=1,
                                   roll_range=(0.0, 0.0), pitch_range=(0.0, 0.0))
ids = torch.tensor([i for _, i, _ in boxes])
cata_out = cata({"rgb": cube["rgb"], "instances": instances, "box_instance_ids": [ids],
                 "keypoints": torch.tensor(keypoints, dtype=torch.float32)[None]})


def panel(rgb: torch.Tensor, boxes: torch.Tensor, points: torch.Tensor, order: list[int]):
    """``rgb (3, H, W)`` in [0, 1] with the boxes and the valid keypoints drawn over it."""
    image = Image.fromarray((rgb.permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy())
    draw = ImageDraw.Draw(image)
    for box, k in zip(boxes.tolist(), order):
        draw.rectangle(box, outline=COLOURS[k % len(COLOURS)], width=2)
    for x, y in points.tolist():
        if math.isfinite(x):
            draw.ellipse((x - 3, y - 3, x + 3, y + 3), fill="white", outline="black")
    return np.asarray(image)


scale = SIZE / FACE   # the perspective panel, drawn at the others' size
source = torch.nn.functional.interpolate(cube["rgb"][:, 0], size=(SIZE, SIZE),
                                         mode="bilinear", antialias=True)[0]
source_boxes = torch.tensor([b for _, b in front], dtype=torch.float32) * scale
panels = [
    panel(source, source_boxes, front_kp * scale, list(range(len(front)))),
    panel(fish_out["rgb"][0], fish_out["boxes"][0], fish_out["keypoints"][0],
          fish_out["box_index"][0].tolist()),
    panel(cata_out["rgb"][0], cata_out["boxes"][0], cata_out["keypoints"][0],
          [int(ids[j]) - 1 for j in cata_out["box_index"][0].tolist()]),
]
gap = np.full((SIZE, 8, 3), 255, np.uint8)
sheet = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], 1)
out = Path(__file__).parent / "images" / "detection.png"
Image.fromarray(sheet).save(out, optimize=True)
print(out, out.stat().st_size // 1024, "KB;", len(front), "front boxes,",
      len(fish_out["boxes"][0]), "in the fisheye,", len(cata_out["boxes"][0]),
      "in the catadioptric image")
