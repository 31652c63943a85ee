"""Calibration targets: what ``--board`` names, their corners, and images of them.

A `Board` is parsed from the text of ``omniscape-torch fit --board``:

=============================================== ===============================================
``checkerboard:COLSxROWS:SQUARE``               inner corners along a row x along a column,
                                                square side in metres (``checkerboard:9x6:0.03``)
``charuco:COLSxROWS:SQUARE:MARKER[:DICT]``      OpenCV ChArUco: squares (not corners) along a
                                                row x a column, square and marker sides in
                                                metres, the ArUco dictionary (default
                                                ``6X6_250``, OpenCV's ``DICT_6X6_250``); the
                                                layout of OpenCV >= 4.6 (not ``legacy``)
=============================================== ===============================================

Kalibr's AprilGrid is not supported: OpenCV's ArUco detector (36h11 tags, 2-bit border) finds
its tags but, on fisheye renders, places their corners 1-3 px off (the black squares between
the tags merge with the tags' borders) and misses tags; detect AprilGrids with Kalibr and give
the corners to ``fit`` as a correspondence file.

Every corner of a board has an id (its row in `Board.object_points`); a detection gives
the ids it found with their pixels. The target points of a plane are fixed up to a rigid motion
of the plane (and a mirror image: seen from behind), which the poses of a fit absorb; only the
distances between corners matter to the intrinsics.

`render_board` draws a board seen by a known camera (for tests and demos where the truth
must be known): every pixel is the mean of ``supersample x supersample`` samples, each coloured
by the board's pattern where its ray meets the board's plane (rays are unprojected with the
camera on a grid of ``step`` pixels and the plane points interpolated in between, which is
exact to about ``step^2 / (8 f)`` px for a focal length of ``f`` px). The whole printed page must
be in view.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from .params import axis_angle_to_matrix
from .synthetic import checkerboard

#: Board kinds of `Board`.
BOARD_KINDS = ("checkerboard", "charuco")

#: Default ArUco dictionary of ChArUco boards (OpenCV's name without ``DICT_``).
DEFAULT_CHARUCO_DICTIONARY = "6X6_250"

#: White border drawn around a rendered board, in squares: OpenCV's
#: detectors need a light quiet zone around the pattern.
MARGIN = 1.0


def require_cv2():
    """``cv2``, or an ImportError saying how to install it (an optional dependency)."""
    try:
        import cv2
    except ImportError:
        raise ImportError("corner detection needs OpenCV: pip install -e \".[calibration]\" "
                          "(or pip install opencv-contrib-python-headless)") from None
    return cv2


def _aruco(cv2):
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "ArucoDetector"):
        raise ImportError("ChArUco and AprilGrid boards need OpenCV >= 4.7 with its aruco "
                          "module: pip install opencv-contrib-python-headless")
    return cv2.aruco


@dataclass(frozen=True)
class Board:
    """A planar calibration target (module docstring).

    Attributes:
        kind: one of ``BOARD_KINDS``.
        cols: checkerboard: inner corners along a row; charuco: squares.
        rows: checkerboard: inner corners along a column; charuco: squares.
        square: square side, metres.
        marker: charuco: marker side, metres; None for a checkerboard.
        dictionary: charuco: ArUco dictionary name (``6X6_250``); None for a checkerboard.
    """

    kind: str
    cols: int
    rows: int
    square: float
    marker: float | None = None
    dictionary: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise ValueError(f"board: unknown kind {self.kind!r}; expected one of "
                             f"{', '.join(BOARD_KINDS)}")
        for name in ("cols", "rows"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 2:
                raise ValueError(f"board: {name} must be an integer >= 2, got {value!r}")
        if not (math.isfinite(self.square) and self.square > 0):
            raise ValueError(f"board: the square side must be a positive number of metres, got "
                             f"{self.square!r}")
        if self.kind == "charuco" and not (self.marker is not None and 0 < self.marker
                                           < self.square):
            raise ValueError(f"board: a ChArUco marker side must be positive and smaller than "
                             f"the square ({self.square} m), got {self.marker!r}")

    @classmethod
    def parse(cls, text: str) -> "Board":
        """The board of ``--board`` text (module docstring).

        Raises:
            ValueError: naming what is wrong and the expected form.
        """
        forms = {"checkerboard": "checkerboard:COLSxROWS:SQUARE (inner corners, metres), e.g. "
                                 "checkerboard:9x6:0.03",
                 "charuco": "charuco:COLSxROWS:SQUARE:MARKER[:DICT] (squares, metres), e.g. "
                            "charuco:8x11:0.03:0.022:5X5_100"}
        parts = [p.strip() for p in str(text).split(":")]
        kind = parts[0].lower()
        if kind == "aprilgrid":
            raise ValueError("board: Kalibr's AprilGrid is not supported (OpenCV does not "
                             "locate its corners to a fraction of a pixel); detect it with "
                             "Kalibr and pass the corners as a correspondence file")
        if kind not in forms:
            raise ValueError(f"board: unknown kind {parts[0]!r} in {text!r}; expected "
                             + "; or ".join(forms.values()))
        form = forms[kind]
        counts = {"checkerboard": (3, 3), "charuco": (4, 5)}[kind]
        if not counts[0] <= len(parts) <= counts[1]:
            raise ValueError(f"board: expected {form}, got {text!r}")
        size = re.fullmatch(r"(\d+)[xX](\d+)", parts[1])
        if size is None:
            raise ValueError(f"board: expected COLSxROWS such as 9x6, got {parts[1]!r} in "
                             f"{text!r}; expected {form}")
        n_numbers = {"checkerboard": 1, "charuco": 2}[kind]
        try:
            numbers = [float(p) for p in parts[2:2 + n_numbers]]
        except ValueError:
            raise ValueError(f"board: expected numbers of metres in {text!r}; expected "
                             f"{form}") from None
        cols, rows = int(size[1]), int(size[2])
        if kind == "checkerboard":
            return cls(kind, cols, rows, numbers[0])
        dictionary = parts[4].upper() if len(parts) == 5 else DEFAULT_CHARUCO_DICTIONARY
        return cls(kind, cols, rows, numbers[0], numbers[1], dictionary.removeprefix("DICT_"))

    def __str__(self) -> str:
        text = f"{self.kind}:{self.cols}x{self.rows}:{self.square:g}"
        if self.kind == "charuco":
            return f"{text}:{self.marker:g}:{self.dictionary}"
        return text

    @property
    def num_corners(self) -> int:
        """Corners with an id: the rows of `object_points`."""
        if self.kind == "checkerboard":
            return self.cols * self.rows
        return (self.cols - 1) * (self.rows - 1)

    def object_points(self, dtype: torch.dtype = torch.float64) -> Tensor:
        """``(num_corners, 3)`` corners ``(X, Y, 0)`` in metres, row ``i`` the corner of id ``i``.

        checkerboard: `checkerboard` (row-major, centred),
        the order of ``cv2.findChessboardCorners`` with ``patternSize = (cols, rows)``;
        charuco: OpenCV's ``CharucoBoard.getChessboardCorners()`` (ids row-major from the
        corner at one square from the board's top-left, x along a row, y down a column).
        """
        if self.kind == "checkerboard":
            return checkerboard(self.rows, self.cols, self.square, dtype=dtype)
        y, x = torch.meshgrid(torch.arange(1, self.rows, dtype=dtype),
                              torch.arange(1, self.cols, dtype=dtype), indexing="ij")
        xy = torch.stack((x, y), -1).reshape(-1, 2) * self.square
        return torch.cat((xy, torch.zeros(len(xy), 1, dtype=dtype)), -1)

    def extent(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)``: the printed pattern with its white margin (``MARGIN``), in the
        frame of `object_points`, metres."""
        s = self.square
        if self.kind == "checkerboard":
            hx, hy = (self.cols + 1) / 2 * s + MARGIN * s, (self.rows + 1) / 2 * s + MARGIN * s
            return -hx, -hy, hx, hy
        return -MARGIN * s, -MARGIN * s, (self.cols + MARGIN) * s, (self.rows + MARGIN) * s

    def outline(self, per_side: int = 32, dtype: torch.dtype = torch.float64) -> Tensor:
        """``(4 per_side, 3)`` points along the edge of `extent`."""
        x0, y0, x1, y1 = self.extent()
        t = torch.arange(per_side, dtype=dtype) / per_side
        xs = torch.cat((x0 + (x1 - x0) * t, torch.full_like(t, x1), x1 - (x1 - x0) * t,
                        torch.full_like(t, x0)))
        ys = torch.cat((torch.full_like(t, y0), y0 + (y1 - y0) * t, torch.full_like(t, y1),
                        y1 - (y1 - y0) * t))
        return torch.stack((xs, ys, torch.zeros_like(xs)), -1)

    def texture(self, pixels_per_square: int = 64) -> tuple[np.ndarray, float]:
        """The printed board (margin included) as a float image in [0, 1] and its resolution
        in pixels per metre; texel ``(i, j)`` covers ``x0 + j / res``..., ``y0 + i / res``...
        of `extent`. ChArUco only: checkerboards are drawn analytically
        (`board_intensity`)."""
        if self.kind != "charuco":
            raise ValueError(f"board: a {self.kind} has no texture (drawn analytically)")
        res = pixels_per_square / self.square
        x0, y0, x1, y1 = self.extent()
        page = np.full((round((y1 - y0) * res), round((x1 - x0) * res)), 255, np.uint8)
        inner = charuco_board(self).generateImage(
            (self.cols * pixels_per_square, self.rows * pixels_per_square), marginSize=0)
        off = round(MARGIN * pixels_per_square)
        page[off:off + inner.shape[0], off:off + inner.shape[1]] = inner
        return page.astype(np.float64) / 255.0, res


def charuco_board(board: Board):
    """The OpenCV ``CharucoBoard`` of a ``charuco`` `Board`."""
    cv2 = require_cv2()
    aruco = _aruco(cv2)
    name = f"DICT_{board.dictionary}"
    if not hasattr(aruco, name):
        known = sorted(n[5:] for n in dir(aruco) if n.startswith("DICT_") and "APRIL" not in n
                       and n[5:] != "ARUCO_MIP_36h12" and not n[5:].endswith("ORIGINAL"))
        raise ValueError(f"board: unknown ArUco dictionary {board.dictionary!r}; expected one "
                         f"of {', '.join(known)}")
    dictionary = aruco.getPredefinedDictionary(getattr(aruco, name))
    needed = (board.cols * board.rows) // 2
    if needed > dictionary.bytesList.shape[0]:
        raise ValueError(f"board: a {board.cols}x{board.rows} ChArUco board needs {needed} "
                         f"markers; {board.dictionary} has {dictionary.bytesList.shape[0]}")
    return aruco.CharucoBoard((board.cols, board.rows), board.square, board.marker, dictionary)


def board_intensity(board: Board, xy: Tensor, texture=None) -> tuple[Tensor, Tensor]:
    """Reflectance of ``board`` at target points ``xy (..., 2)`` (metres) and whether they are
    on the printed page (pattern and margin).

    Checkerboard: black (0) and white (1) squares, the square at the top-left corner black;
    others: nearest texel of ``texture`` (``board.texture()`` when None).
    """
    x0, y0, x1, y1 = board.extent()
    x, y = xy[..., 0], xy[..., 1]
    on_page = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    if board.kind == "checkerboard":
        s = board.square
        i = torch.floor(x / s + (board.cols + 1) / 2).int()
        j = torch.floor(y / s + (board.rows + 1) / 2).int()
        inside = (i >= 0) & (i <= board.cols) & (j >= 0) & (j <= board.rows)
        black = inside & (((i + j) & 1) == 0)
        return (~black).to(xy.dtype), on_page
    page, res = board.texture() if texture is None else texture
    h, w = page.shape
    col = ((x - x0) * res).floor().long().clamp(0, w - 1)
    row = ((y - y0) * res).floor().long().clamp(0, h - 1)
    values = torch.from_numpy(page).to(xy.dtype)[row, col]
    return values, on_page


def _board_coordinates(camera: Camera, params: Tensor, rotation: Tensor, t: Tensor,
                       u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Target points ``(len(v), len(u), 2)`` seen through the pixels ``u x v`` and whether each
    ray meets the board's plane in front of the camera."""
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    rays, ok = camera.model.unproject(torch.stack((uu, vv), -1), params)
    normal = rotation[:, 2]
    denom = rays @ normal
    facing = denom.abs() > 1e-12
    depth = torch.dot(normal, t) / torch.where(facing, denom, torch.ones_like(denom))
    hit = ok & facing & (depth > 0)
    target = (depth[..., None] * rays - t) @ rotation   # R^T (X_cam - t)
    return target[..., :2], hit


def _interpolate(values: Tensor, u0: float, v0: float, step: float, u: Tensor, v: Tensor
                 ) -> Tensor:
    """Bilinear interpolation of ``values (C, h, w)`` given at pixels ``(u0 + step j,
    v0 + step i)``, at the pixels ``(u, v)`` (same shape ``S``): ``(C, *S)``."""
    c, h, w = values.shape
    x = (u - u0) / (step * max(w - 1, 1)) * 2 - 1
    y = (v - v0) / (step * max(h - 1, 1)) * 2 - 1
    grid = torch.stack((x, y), -1).reshape(1, -1, 1, 2)
    out = torch.nn.functional.grid_sample(values[None], grid, mode="bilinear",
                                          align_corners=True)
    return out.reshape((c,) + tuple(u.shape))


@torch.no_grad()
def image_circle_mask(camera: Camera, step: int = 4) -> Tensor:
    """``(H, W)`` True where the pixel centre's ray is valid and within ``camera.fov``: the
    angle off axis unprojected every ``step`` pixels and interpolated (the edge may move by a
    small fraction of a pixel)."""
    h, w = camera.image_size
    dtype = torch.float64
    params = camera.params.detach().to(dtype)
    gu = -0.5 + step * torch.arange(-(-w // step) + 1, dtype=dtype)
    gv = -0.5 + step * torch.arange(-(-h // step) + 1, dtype=dtype)
    vv, uu = torch.meshgrid(gv, gu, indexing="ij")
    rays, ok = camera.model.unproject(torch.stack((uu, vv), -1), params)
    theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
    limit = math.pi if camera.fov is None else 0.5 * camera.fov
    values = torch.stack((theta, ok.to(dtype)))
    pixel = camera.pixel_grid().to(dtype)
    sampled = _interpolate(values, -0.5, -0.5, step, pixel[..., 0], pixel[..., 1])
    return (sampled[0] <= limit) & (sampled[1] > 1 - 1e-9)


@torch.no_grad()
def render_board(camera: Camera, board: Board, pose: Tensor, *, supersample: int = 4,
                 background: float = 0.45, dark: float = 0.08, light: float = 0.92,
                 noise: float = 0.0, generator: torch.Generator | None = None,
                 texture=None, circle: Tensor | None = None, step: int = 2) -> Tensor:
    """An 8-bit grey image of ``board`` at ``pose`` seen by ``camera`` (module docstring).

    Args:
        camera: one camera; its ``image_size`` is the image's; with a ``fov``, the pixels
            past it are black (a fisheye's image circle).
        board: the target.
        pose: ``(6,)`` axis-angle (radians) and translation (metres), ``X_cam = R X + t``.
        supersample: rays per pixel side (anti-aliasing); sample ``(i, j)`` of pixel ``(u, v)``
            is at ``(u - 0.5 + (j + 0.5) / s, v - 0.5 + (i + 0.5) / s)`` (pixel centres at
            integers).
        background: grey level in [0, 1] of the scene behind the board.
        dark: grey level in [0, 1] of the board's black.
        light: grey level in [0, 1] of the board's white.
        noise: standard deviation of Gaussian noise added to the levels (needs ``generator``).
        texture: ``board.texture()``, to reuse it over several views.
        circle: ``image_circle_mask(camera)``, likewise.
        step: pixels between the rays actually unprojected (the others are interpolated).

    Returns:
        ``(H, W)`` uint8.
    """
    h, w = camera.image_size
    dtype = torch.float64
    params = camera.params.detach().to(dtype)
    pose = pose.detach().to(dtype)
    rotation = axis_angle_to_matrix(pose[:3])
    t = pose[3:]
    image = torch.full((h, w), background, dtype=dtype)
    # the board's projection lies inside its outline's (the camera sees the whole page)
    edge = board.outline(64, dtype) @ rotation.T + t
    pixels, valid = camera.model.project(edge, params)
    if bool(valid.any()):
        lo = pixels[valid].amin(0).floor() - 2
        hi = pixels[valid].amax(0).ceil() + 2
        u0, v0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        u1, v1 = min(int(hi[0]), w - 1), min(int(hi[1]), h - 1)
        if u1 >= u0 and v1 >= v0 and texture is None and board.kind != "checkerboard":
            texture = board.texture()
        if u1 >= u0 and v1 >= v0:
            # the target point of every sample, bilinear between those of a grid of
            # ``step`` pixels (the map is smooth on that scale: for a fisheye of focal f
            # its curvature error is about step^2 / (8 f) pixels, 2e-3 px for step 2 and
            # f = 200), and whether the ray meets the board (all four grid rays must)
            nu, nv = -(-(u1 - u0 + 1) // step) + 1, -(-(v1 - v0 + 1) // step) + 1
            gu = u0 - 0.5 + step * torch.arange(nu, dtype=dtype)
            gv = v0 - 0.5 + step * torch.arange(nv, dtype=dtype)
            target, hit = _board_coordinates(camera, params, rotation, t, gu, gv)
            s = supersample
            offsets = (torch.arange(s, dtype=dtype) + 0.5) / s - 0.5
            pv, pu = torch.meshgrid(torch.arange(v0, v1 + 1, dtype=dtype),
                                    torch.arange(u0, u1 + 1, dtype=dtype), indexing="ij")
            su = pu[..., None, None] + offsets.view(1, s)       # [h', w', s, s]
            sv = pv[..., None, None] + offsets.view(s, 1)
            su, sv = torch.broadcast_tensors(su, sv)
            # float32 from here: 1e-7 of the board's size is far below a pixel's footprint
            values = torch.cat((target.permute(2, 0, 1), hit[None].to(dtype))).float()
            sampled = _interpolate(values, u0 - 0.5, v0 - 0.5, step, su.float(), sv.float())
            xy = sampled[:2].permute(1, 2, 3, 4, 0)
            ok = sampled[2] > 1 - 1e-4
            level, on_page = board_intensity(board, xy, texture)
            level = dark + (light - dark) * level
            value = torch.where(ok & on_page, level, torch.full_like(level, background))
            image[v0:v1 + 1, u0:u1 + 1] = value.mean((-1, -2)).to(dtype)
    if camera.fov is not None:
        # a fisheye's image circle: nothing lit past the field of view
        inside = image_circle_mask(camera) if circle is None else circle
        image = torch.where(inside, image, torch.zeros_like(image))
    if noise > 0:
        image = image + noise * torch.randn(image.shape, generator=generator, dtype=dtype)
    return (image * 255).round().clamp(0, 255).to(torch.uint8)
