"""Corners of calibration boards in images, with OpenCV (an optional dependency:
``pip install opencv-contrib-python-headless``).

`detect_corners` reads the images, finds the board of ``--board``
(`Board`) in each and returns the correspondences
of ``omniscape-torch fit``: per image where the board was found, its target points and their
pixels; the images where it was not are listed with the reason.

* checkerboard: the classic ``cv2.findChessboardCorners`` (fast), else
  ``cv2.findChessboardCornersSB`` (the sector-based detector, robust to strong distortion, in
  its exhaustive mode); the corners are then refined with ``cv2.cornerSubPix`` in a window per
  corner that follows the corners' spacing about it (`refine_windows`: up to 11 x 11, as
  OpenCV's calibration samples use, stopping short of the next grid lines). On
  boards rendered through a fisheye (``tests/test_calibration_images.py``) the refined corners
  lie 0.064 px RMS from the truth (0.26 px at worst); the sector-based detector's own corners,
  even in its accuracy mode, are up to three times farther on some views.
* charuco: ``cv2.aruco.CharucoDetector`` (OpenCV >= 4.7); only views with at least
  ``min_corners`` corners are kept; corners are refined likewise.

Pixels follow DESIGN.md: pixel centres at integers, the top-left pixel's centre at (0, 0). That
is OpenCV's convention for corner coordinates (a corner at the meeting point of four pixels
``(u, u + 1) x (v, v + 1)`` is reported at ``(u + 0.5, v + 0.5)``), so they are taken as they
are; the tests check it on rendered boards against the truth's projections.
"""

from __future__ import annotations

import contextlib
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from .files import Correspondences
from .targets import Board, _aruco, charuco_board, require_cv2

#: Image files `detect_corners` reads from a folder.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")

#: Fewest views `detect_corners` accepts (the fit accepts fewer; Zhang's planar
#: calibration needs three for a general pinhole camera, and a lens has more parameters).
MIN_VIEWS = 3

#: Largest ``cornerSubPix`` half window, pixels (a 11 x 11 window).
MAX_REFINE_WINDOW = 5


@dataclass
class Detection(Correspondences):
    """`Correspondences` of the images where the board was found, and the others.

    Attributes:
        skipped: image name -> why it was not used (board not found, too few corners).
        ids: per view, the ``(N_i,)`` int64 ids of the corners (rows of
            ``board.object_points()``).
    """

    skipped: dict[str, str] = field(default_factory=dict)
    ids: list[Tensor] = field(default_factory=list)


def image_files(folder: str | Path) -> list[Path]:
    """The image files of ``folder`` (``IMAGE_SUFFIXES``, any case), sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder of images")
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    return files


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND"


@contextlib.contextmanager
def _quiet(cv2):
    """OpenCV's log silenced (its `[ WARN:0@0.043] ...` and `[ERROR:0@...]` lines on stderr
    for a file it cannot decode): every skipped image's reason is in the `Detection`. The level
    is OpenCV's process-wide setting, restored on leaving."""
    log = getattr(getattr(cv2, "utils", None), "logging", None)
    if log is None:
        yield
        return
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        log.setLogLevel(level)


def _read(cv2, path: Path) -> np.ndarray | str:
    """The grey image of a file, or why it cannot be used: unreadable, empty, or not
    decodable (``cv2.imdecode`` refuses a truncated JPEG, whose top part ``cv2.imread``
    returns with only a warning)."""
    try:
        raw = np.fromfile(path, dtype=np.uint8)
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    if raw.size == 0:
        return "an empty file (0 bytes)"
    if raw[:8].tobytes() == _PNG_SIGNATURE and _PNG_END not in raw[-4096:].tobytes():
        # libpng would print its own error on stderr before OpenCV returns None
        return "a truncated PNG (its end is missing)"
    grey = cv2.imdecode(raw, cv2.IMREAD_GRAYSCALE)
    return "not an image OpenCV can decode (corrupt or truncated?)" if grey is None else grey


def _grey(cv2, image, name: str) -> np.ndarray | str:
    if isinstance(image, (str, Path)):
        return _read(cv2, Path(image))
    if isinstance(image, Tensor):
        image = image.detach().cpu().numpy()
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_RGBA2GRAY if image.shape[2] == 4
                             else cv2.COLOR_RGB2GRAY)
    if image.ndim != 2:
        raise ValueError(f"{name}: expected an (H, W) or (H, W, 3) image, got {image.shape}")
    if image.dtype != np.uint8:
        if image.dtype == np.uint16:
            image = (image / 257).round().astype(np.uint8)
        else:
            raise TypeError(f"{name}: expected uint8 or uint16 pixels, got {image.dtype}")
    return image


#: ``cornerSubPix``'s half window as a share of the distance to the corner's closest neighbour
#: (`refine_windows`).
REFINE_SHARE = 0.6


def refine_windows(pixels: np.ndarray, ids: np.ndarray, board: Board) -> np.ndarray:
    """``cornerSubPix``'s half window of each corner, following the corners' spacing about it:
    ``REFINE_SHARE`` of the distance ``d`` to its closest neighbour on the board's grid (the 8
    about it: a board seen obliquely brings diagonal neighbours closest), so that the window
    stops ``0.4 d`` short of any other corner; between 2 and ``MAX_REFINE_WINDOW`` pixels.

    Measured (leave-one-view-out RMS of the held-out views' corners, pixels): on the real
    catadioptric set (``tests/data/ocamcalib_catadioptric``, squares of 4-20 px) 0.73 against
    0.78 with ``cornerSubPix``'s 11 x 11 for every corner and 0.74 with one window per view
    below half the closest corners' distance (the rule before issue 33); on
    ``tests/data/ocamcalib_fisheye2`` every window is 11 x 11 (0.11, the same); on the rendered
    fisheye boards of ``tests/test_calibration_images.py`` 0.064 px RMS from the truth
    against 0.077 and 0.142 (11 x 11 moves corners near the image circle's edge by up to 2.8
    px)."""
    cols = board.cols if board.kind == "checkerboard" else board.cols - 1
    lookup = {int(i): k for k, i in enumerate(ids)}
    closest = np.full(len(ids), np.inf)
    for k, i in enumerate(ids):
        row, col = divmod(int(i), cols)
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):   # each pair once
            m = lookup.get((row + dr) * cols + col + dc) if 0 <= col + dc < cols else None
            if m is not None:
                d = float(np.linalg.norm(pixels[m] - pixels[k]))
                closest[k], closest[m] = min(closest[k], d), min(closest[m], d)
    windows = np.where(np.isfinite(closest), np.floor(REFINE_SHARE * closest), 2)
    return np.clip(windows, 2, MAX_REFINE_WINDOW).astype(np.int64)


def _refine(cv2, grey: np.ndarray, pixels: np.ndarray, ids: np.ndarray, board: Board
            ) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    windows = refine_windows(pixels, ids, board)
    refined = pixels.copy()
    for win in np.unique(windows):   # one call per window size
        rows = windows == win
        corners = np.ascontiguousarray(pixels[rows].reshape(-1, 1, 2), dtype=np.float32)
        refined[rows] = cv2.cornerSubPix(grey, corners, (int(win), int(win)), (-1, -1),
                                         criteria).reshape(-1, 2)
    return refined


def _checkerboard(cv2, grey: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray] | str:
    size = (board.cols, board.rows)
    # the classic detector is the fastest when it succeeds; the sector-based one finds boards
    # it misses under strong distortion (its exhaustive mode is often faster than its default
    # one on fisheye images, which fails first)
    found, corners = cv2.findChessboardCorners(
        grey, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        found, corners = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        return (f"no {board.cols}x{board.rows} checkerboard found (inner corners; is the "
                f"whole board in the image, with a white border?)")
    return corners.reshape(-1, 2).astype(np.float64), np.arange(board.num_corners)


def _charuco(cv2, grey: np.ndarray, board: Board, detector) -> tuple[np.ndarray, np.ndarray] | str:
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) == 0:
        return f"no ChArUco corner of {board} found"
    return corners.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(np.int64)


def _detector(cv2, board: Board):
    if board.kind == "checkerboard":
        return None
    aruco = _aruco(cv2)
    return aruco.CharucoDetector(charuco_board(board), aruco.CharucoParameters())


def detect_corners(images: str | Path | Sequence, board: Board | str, *,
                   names: Sequence[str] | None = None, min_views: int = MIN_VIEWS,
                   min_corners: int = 8, refine: bool = True,
                   workers: int | None = None) -> Detection:
    """Find ``board`` in every image (module docstring).

    Args:
        images: a folder (its ``IMAGE_SUFFIXES`` files, by name), or a sequence of image paths
            or of ``(H, W)`` / ``(H, W, 3)`` uint8 arrays or tensors (RGB).
        board: a `Board` or its ``--board`` text (``checkerboard:9x6:0.03``).
        names: view names (default: file names without suffix, or ``image_000``, ...); names
            are made unique and space-free for the correspondence file.
        min_views: fewest images with the board, else ValueError.
        min_corners: fewest corners in a ChArUco view (partial views are kept).
        refine: refine the corners with ``cv2.cornerSubPix`` (module docstring).
        workers: threads (OpenCV releases the GIL; default: up to 4, the CPU count).

    Returns:
        A `Detection`: per view ``(N_i, 3)`` target points (``board.object_points()``
        rows) and ``(N_i, 2)`` pixels, float64; the image size ``(H, W)``; view names; the
        skipped images and why.

    Raises:
        ImportError: OpenCV is missing (the message says what to install).
        ValueError: an unreadable image, images of different sizes, or fewer than
            ``min_views`` images where the board was found (the message lists why each was
            skipped).
    """
    cv2 = require_cv2()
    board = Board.parse(board) if isinstance(board, str) else board
    if isinstance(images, (str, Path)):
        images = image_files(images)
    images = list(images)
    if not images:
        raise ValueError("images: expected at least one image, got none")
    if names is None:
        names = [Path(i).stem if isinstance(i, (str, Path)) else f"image_{k:03d}"
                 for k, i in enumerate(images)]
    names = _unique([("_".join(str(n).split()) or f"image_{k:03d}") for k, n in
                     enumerate(names)])
    if len(names) != len(images):
        raise ValueError(f"names: {len(names)} names for {len(images)} images")
    detector = _detector(cv2, board)
    points = board.object_points()

    def one(k: int):
        grey = _grey(cv2, images[k], names[k])
        if isinstance(grey, str):   # an unusable file: skipped, the run goes on
            return None, grey
        if board.kind == "checkerboard":
            found = _checkerboard(cv2, grey, board)
        else:
            found = _charuco(cv2, grey, board, detector)
        if (isinstance(found, tuple) and board.kind != "checkerboard"
                and len(found[1]) < min_corners):
            found = f"only {len(found[1])} corners found, fewer than min_corners {min_corners}"
        if isinstance(found, tuple) and refine:
            found = (_refine(cv2, grey, found[0], found[1], board), found[1])
        return grey.shape, found

    workers = workers or min(4, os.cpu_count() or 1)
    # detector objects are not documented as thread-safe: one thread for the aruco boards
    with _quiet(cv2):
        if workers > 1 and board.kind == "checkerboard" and len(images) > 1:
            with ThreadPoolExecutor(workers) as pool:
                results = list(pool.map(one, range(len(images))))
        else:
            results = [one(k) for k in range(len(images))]

    read = [(n, shape) for n, (shape, _) in zip(names, results) if shape is not None]
    if not read:
        raise ValueError(f"images: none of the {len(images)} images can be read ("
                         + "; ".join(f"{n}: {r}" for n, (_, r) in zip(names, results)) + ")")
    first_name, first = read[0]
    odd = next(((n, s) for n, s in read if s != first), None)
    if odd is not None:
        raise ValueError(f"images: all images must have one size; {first_name} is "
                         f"{first[1]} x {first[0]} but {odd[0]} is {odd[1][1]} x {odd[1][0]} "
                         f"(W x H)")
    image_size = tuple(int(v) for v in first)
    object_points, image_points, kept, ids, skipped = [], [], [], [], {}
    for name, (_, found) in zip(names, results):
        if isinstance(found, str):
            skipped[name] = found
            continue
        pixels, corner_ids = found
        index = torch.from_numpy(corner_ids)
        object_points.append(points[index])
        image_points.append(torch.from_numpy(pixels))
        ids.append(index)
        kept.append(name)
    if len(kept) < min_views:
        unread = [f"{n}: {r}" for n, r in skipped.items() if not _board_missing(r)]
        missing = [k for k, n in enumerate(names) if _board_missing(skipped.get(n, ""))]
        why = "; ".join(unread + ([_seen_instead(cv2, [images[k] for k in missing], board,
                                                 workers)] if missing else []))
        raise ValueError(f"images: the board {board} was found in {len(kept)} of "
                         f"{len(images)} images, fewer than the {min_views} needed"
                         + (f"; {why}" if why else ""))
    return Detection(object_points, image_points, image_size, kept, skipped=skipped, ids=ids)


def _board_missing(reason: str) -> bool:
    """Whether a skip ``reason`` is the board not found (rather than an unusable file)."""
    return reason.startswith(("no ", "only "))


def nearby_boards(board: Board) -> list[Board]:
    """The checkerboards a wrong ``--board`` most often means: one corner more or fewer along
    either side, or both (squares counted instead of inner corners, or the reverse). A
    transposed size is the same board turned (OpenCV finds either)."""
    sizes = [(board.cols + 1, board.rows), (board.cols - 1, board.rows),
             (board.cols, board.rows + 1), (board.cols, board.rows - 1),
             (board.cols - 1, board.rows - 1), (board.cols + 1, board.rows + 1)]
    return [replace(board, cols=c, rows=r) for c, r in sizes
            if min(c, r) >= 2 and (c, r) != (board.rows, board.cols)]


def _seen_instead(cv2, images: list, board: Board, workers: int | None) -> str:
    """One line for the images where ``board`` was not found: how many, and the nearby size
    (`nearby_boards`) seen in them, if any: tried on up to three of them, then counted
    over all. Only checkerboards (a ChArUco board's markers name its size)."""
    line = f"no {board} in {len(images)} of them"
    if board.kind != "checkerboard":
        return line

    def seen(item) -> bool:
        image, alt = item
        grey = _grey(cv2, image, "image")
        return not isinstance(grey, str) and not isinstance(_checkerboard(cv2, grey, alt), str)

    probe = images[::max(len(images) // 3, 1)][:3]
    with ThreadPoolExecutor(workers or min(4, os.cpu_count() or 1)) as pool:
        for alt in nearby_boards(board):
            if any(pool.map(seen, [(image, alt) for image in probe])):
                count = sum(pool.map(seen, [(image, alt) for image in images]))
                return (f"{line}; a {alt.cols}x{alt.rows} board is seen in {count} of them "
                        f"(--board {alt})")
    sizes = ", ".join(f"{b.cols}x{b.rows}" for b in nearby_boards(board))
    return f"{line}, nor a board of a nearby size ({sizes}) in {len(probe)} of them"


def summarize_skipped(skipped: dict[str, str]) -> list[str]:
    """The skipped images as lines to show: one per reason, naming its images (a board not
    found in most images is one line, not one per image)."""
    groups: dict[str, list[str]] = {}
    for name, reason in skipped.items():
        groups.setdefault(reason, []).append(name)
    return [f"{names[0]}: {reason}" if len(names) == 1 else
            f"{len(names)} images ({', '.join(names)}): {reason}"
            for reason, names in groups.items()]


def _unique(names: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for name in names:
        if name in seen:
            seen[name] += 1
            name = f"{name}_{seen[name]}"
        seen.setdefault(name, 0)
        out.append(name)
    return out
