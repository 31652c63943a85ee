"""The contact sheet of a generated dataset (``contact_sheet.png``): one frame of every camera
at a glance, its RGB, depth (on a log colour map), labels and valid area, and with several
weathers the first camera's RGB in each; written by ``generate`` (`omniscape_torch.data.generate`)
and drawn with numpy and Pillow only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import read_image
from ..io.images import encode_image
from . import format as fmt

__all__ = ["SHEET_CELL", "SHEET_COLUMNS", "contact_sheet"]


#: The size of one of the contact sheet's cells (pixels), and its columns.
SHEET_CELL = 200
SHEET_COLUMNS = ("rgb", "depth", "labels_color", "valid")


#: OpenCV's ``COLORMAP_TURBO`` (Google's Turbo), 256 RGB colours as hex: the depth column's
#: colour map, without OpenCV.
_TURBO = np.frombuffer(bytes.fromhex(
    "30123b32154333184a341b51351e5836215f37246638276d392a733a2d793b2f803c32863d358b3e38913f3b"
    "973f3e9c4040a24143a74146ac4249b1424bb5434eba4451bf4454c34456c74559cb455ccf455ed34661d646"
    "64da4666dd4669e0466be3476ee64771e94773eb4776ee4778f0477bf2467df44680f64682f84685fa4687fb"
    "458afc458cfd448ffe4391fe4294ff4196ff4099ff3e9bfe3d9efe3ba0fd3aa3fc38a5fb37a8fa35abf833ad"
    "f731aff52fb2f42eb4f22cb7f02ab9ee28bceb27bee925c0e723c3e422c5e220c7df1fc9dd1ecbda1ccdd81b"
    "d0d51ad2d21ad4d019d5cd18d7ca18d9c818dbc518ddc218dec018e0bd19e2bb19e3b91ae4b61ce6b41de7b2"
    "1fe9af20eaac22ebaa25eca727eea42aefa12cf09e2ff19b32f29835f39438f4913cf58e3ff68a43f78746f8"
    "844af8804ef97d52fa7a55fa7659fb735dfc6f61fc6c65fd6969fd666dfe6271fe5f75fe5c79fe597dff5680"
    "ff5384ff5188ff4e8bff4b8fff4992ff4796fe4499fe429cfe409ffd3fa1fd3da4fc3ca7fc3aa9fb39acfb38"
    "affa37b1f936b4f836b7f735b9f635bcf534bef434c1f334c3f134c6f034c8ef34cbed34cdec34d0ea34d2e9"
    "35d4e735d7e535d9e436dbe236dde037dfdf37e1dd37e3db38e5d938e7d739e9d539ebd339ecd13aeecf3aef"
    "cd3af1cb3af2c93af4c73af5c53af6c33af7c13af8be39f9bc39faba39fbb838fbb637fcb336fcb136fdae35"
    "fdac34fea933fea732fea431fea130fe9e2ffe9b2dfe992cfe962bfe932afe9029fd8d27fd8a26fc8725fc84"
    "23fb8122fb7e21fa7b1ff9781ef9751df8721cf76f1af66c19f56918f46617f36315f26014f15d13f05b12ef"
    "5811ed5510ec530feb500eea4e0de84b0ce7490ce5470be4450ae2430ae14109df3f08dd3d08dc3b07da3907"
    "d83706d63506d43305d23105d02f05ce2d04cc2b04ca2a04c82803c52603c32503c12302be2102bc2002b91e"
    "02b71d02b41b01b21a01af1801ac1701a91601a71401a41301a112019e10019b0f01980e01950d01920b018e"
    "0a018b09028808028507028106027e05027a0403"), np.uint8).reshape(256, 3)


def _resize_weights(src: int, dst: int) -> np.ndarray:
    """``(dst, src)`` weights of an area resampling from ``src`` to ``dst < src`` samples: the
    overlap of each source pixel with each output pixel's footprint (OpenCV's INTER_AREA)."""
    scale = src / dst
    lo = np.arange(dst)[:, None] * scale
    s = np.arange(src)[None, :]
    return np.clip(np.minimum(lo + scale, s + 1) - np.maximum(lo, s), 0, None) / scale


def _resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``image (H, W, C)`` uint8 resampled to ``height x width``: by area going down, nearest
    going up (OpenCV's INTER_AREA and INTER_NEAREST, in numpy)."""
    h, w = image.shape[:2]
    if height < h or width < w:
        out = np.tensordot(_resize_weights(h, height), image.astype(np.float64), axes=(1, 0))
        out = np.tensordot(out, _resize_weights(w, width), axes=(1, 1))   # (height, C, width)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8).transpose(0, 2, 1)
    rows = np.minimum(np.floor(np.arange(height) * (1.0 / (height / h))).astype(int), h - 1)
    cols = np.minimum(np.floor(np.arange(width) * (1.0 / (width / w))).astype(int), w - 1)
    return image[rows][:, cols]


def _sheet_cell(image: np.ndarray, title: str) -> np.ndarray:
    """``image (H, W, 3)`` uint8 RGB fitted into a ``SHEET_CELL`` square (aspect kept, black
    margins), ``title`` written in its top-left corner (Pillow's default font)."""
    from PIL import Image, ImageDraw, ImageFont

    h, w = image.shape[:2]
    scale = SHEET_CELL / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = _resize(image, size[1], size[0]) if scale != 1 else image
    cell = np.zeros((SHEET_CELL, SHEET_CELL, 3), np.uint8)
    y0, x0 = (SHEET_CELL - size[1]) // 2, (SHEET_CELL - size[0]) // 2
    cell[y0:y0 + size[1], x0:x0 + size[0]] = small
    font = ImageFont.load_default()
    _, _, right, bottom = ImageDraw.Draw(Image.new("L", (1, 1))).textbbox((4, 3), title,
                                                                          font=font)
    cell[:bottom + 3, :right + 4] //= 3          # a dark band under the title
    canvas = Image.fromarray(cell)
    ImageDraw.Draw(canvas).text((4, 3), title, fill=(255, 255, 255), font=font)
    return np.asarray(canvas).copy()


def contact_sheet(root: str | Path, cameras, frame: int,
                  weathers: dict[str, int] | None = None) -> bytes:
    """PNG bytes of frame ``frame`` of the dataset in ``root``: one row per camera of
    ``cameras``, columns ``SHEET_COLUMNS`` (depth on a log colour map, black where not valid),
    then, when ``weathers`` (weather name -> a finished frame in it) holds more than one, rows
    of the first camera's RGB in each of them (``len(SHEET_COLUMNS)`` a row): the dataset's
    variety at a glance. ``SHEET_CELL`` pixels square per cell, each titled."""
    from ..io import read_exr

    root = Path(root)

    def image(name: str, modality: str, k: int) -> np.ndarray:
        return read_image(root / fmt.frame_file(name, modality, k)).numpy()

    rows = []
    for name in cameras:
        valid = image(name, "valid", frame) > 0
        depth = read_exr(root / fmt.frame_file(name, "depth", frame)).numpy()
        log_depth = np.log10(np.maximum(depth, 1e-3))
        lo, hi = (float(log_depth[valid].min()), float(log_depth[valid].max())) \
            if valid.any() else (0.0, 1.0)
        scaled = np.clip((log_depth - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
        turbo = _TURBO[scaled]
        cells = {"rgb": image(name, "rgb", frame),
                 "depth": np.where(valid[..., None], turbo, 0).astype(np.uint8),
                 "labels_color": image(name, "labels_color", frame),
                 "valid": np.repeat(valid[..., None].astype(np.uint8) * 255, 3, -1)}
        titles = {"rgb": f"{name} {fmt.frame_name(frame)}", "depth": "depth (log)",
                  "labels_color": "labels", "valid": "valid"}
        rows.append(np.hstack([_sheet_cell(cells[m], titles[m]) for m in SHEET_COLUMNS]))
    if weathers is not None and len(weathers) > 1:
        cells = [_sheet_cell(image(cameras[0], "rgb", k), weather)
                 for weather, k in weathers.items()]
        per_row = len(SHEET_COLUMNS)
        cells += [np.zeros_like(cells[0])] * (-len(cells) % per_row)
        rows += [np.hstack(cells[i:i + per_row]) for i in range(0, len(cells), per_row)]
    return encode_image(np.vstack(rows))
