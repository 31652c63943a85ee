"""The correspondence file read by ``omniscape-torch fit``: plain text, one point per line.

::

    omniscape-torch correspondences 1
    # comments start with '#', blank lines are ignored
    image_size 1600 1600          # H W, pixels
    view board_000                # a view (any name without spaces); its points follow
    0.00 0.00 0.0  812.31 790.02  # X Y Z (target frame, metres) u v (pixels)
    0.05 0.00 0.0  861.70 791.44
    ...
    view board_001
    ...

The first line names the format and its version. Pixels follow DESIGN.md: ``(u, v)`` =
(column, row), integer coordinates at pixel centres, the top-left pixel's centre at (0, 0)
(OpenCV's convention: corners from ``cv2.findChessboardCorners`` go in as they are; coordinates
measured from the top-left pixel's corner need 0.5 subtracted). Every view needs at least 4
points.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..io.atomic import atomic_write_text

#: The first line of a correspondence file.
MAGIC = "omniscape-torch correspondences 1"


@dataclass
class Correspondences:
    """Target points and pixels of several views.

    Attributes:
        object_points: per view ``(N_i, 3)`` float64 target points.
        image_points: per view ``(N_i, 2)`` float64 pixels (u, v).
        image_size: ``(H, W)``.
        names: per view name.
    """

    object_points: list[Tensor]
    image_points: list[Tensor]
    image_size: tuple[int, int]
    names: list[str]


def write_correspondences(path: str | Path, data: Correspondences) -> Path:
    """Write ``data`` in the format of the module docstring (atomically; 17 significant
    digits)."""
    h, w = data.image_size
    lines = [MAGIC, f"image_size {h} {w}"]
    for name, pts, pix in zip(data.names, data.object_points, data.image_points):
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"names: a view name must be non-empty without spaces, got "
                             f"{name!r}")
        lines.append(f"view {name}")
        for p, q in zip(pts.tolist(), pix.tolist()):
            lines.append(" ".join(f"{v:.17g}" for v in (*p, *q)))
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_correspondences(path: str | Path) -> Correspondences:
    """Read a correspondence file (module docstring).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line of anything out of format.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such correspondence file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file; expected a correspondence file starting "
                         f"with {MAGIC!r}") from None
    image_size = None
    names: list[str] = []
    rows: list[list[list[float]]] = []
    seen_magic = False
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{path}, line {number}"
        if not seen_magic:
            if line != MAGIC:
                raise ValueError(f"{where}: expected the header {MAGIC!r}, got {line[:60]!r}; "
                                 f"is this a correspondence file?")
            seen_magic = True
            continue
        key, *rest = line.split()
        if key == "image_size":
            try:
                size = tuple(int(v) for v in rest)
            except ValueError:
                size = ()
            if len(size) != 2 or min(size) <= 0:
                raise ValueError(f"{where}: image_size: expected two positive integers H W, got "
                                 f"{' '.join(rest)!r}")
            image_size = size
        elif key == "view":
            if len(rest) != 1:
                raise ValueError(f"{where}: expected 'view NAME' (one word), got {line!r}")
            names.append(rest[0])
            rows.append([])
        else:
            if not rows:
                raise ValueError(f"{where}: a point before the first 'view' line")
            try:
                values = [float(v) for v in line.split()]
            except ValueError:
                raise ValueError(f"{where}: expected 5 numbers X Y Z u v, got {line!r}") from None
            if len(values) != 5 or not all(math.isfinite(v) for v in values):
                raise ValueError(f"{where}: expected 5 finite numbers X Y Z u v, got {line!r}")
            rows[-1].append(values)
    if not seen_magic:
        raise ValueError(f"{path}: empty; expected a correspondence file starting with "
                         f"{MAGIC!r}")
    if image_size is None:
        raise ValueError(f"{path}: no 'image_size H W' line")
    if not rows:
        raise ValueError(f"{path}: no 'view' section")
    for name, view in zip(names, rows):
        if len(view) < 4:
            raise ValueError(f"{path}: view {name!r} has {len(view)} points, at least 4 needed")
    tensors = [torch.tensor(v, dtype=torch.float64) for v in rows]
    return Correspondences([t[:, :3] for t in tensors], [t[:, 3:] for t in tensors],
                           image_size, names)


def save_result(camera, report: dict, key: str, path: str | Path) -> Path:
    """Write ``camera`` as Camera JSON (``Camera.load_json`` reads it) with ``report`` under
    ``key`` (e.g. ``"fit"``), atomically."""
    return atomic_write_text(path, json.dumps({**camera.to_dict(), key: report}, indent=2)
                             + "\n")
