"""Draw docs/images/woodscape_rig.png: one frame of ``generate --rig woodscape``.

WoodScape's four cameras (FV, MVL, MVR, RV) on a car in the built-in town, at half WoodScape's
1280 x 966 sensor, clear noon; per camera (a row): the RGB image with its 2D boxes
(``box_2d_annotations``, WoodScape's box colours), the semantic labels in WoodScape's colours
(``semantic_annotations/rgbLabels``), the distance along each ray (``distance_maps``, log
colour map, black outside the image circle) and the previous image. Public API only. From the
repository root::

    python docs/make_woodscape_rig_figure.py
"""

import tempfile
from pathlib import Path

from omniscape_torch.data.generate import DatasetConfig, render_frame
from omniscape_torch.data.woodscape import contact_sheet

FRAME = 4
OUT = Path(__file__).resolve().parent / "images" / "woodscape_rig.png"

with tempfile.TemporaryDirectory() as folder:
    config = DatasetConfig(rig="woodscape", frames=FRAME + 1, image_size=(483, 640),
                           weather=("clear_noon",))
    render_frame(config, folder, FRAME)   # this frame only (frame k depends on k alone)
    OUT.write_bytes(contact_sheet(folder, config.cameras, FRAME))
print(f"wrote {OUT}")
