"""Calibration from images (issue 19): boards detected with OpenCV and fitted.

The truth is known: checkerboards are rendered through a Kannala-Brandt fisheye with an image
circle of 180 degrees (``calibration.targets.render_board``: every pixel the mean of 4 x 4 rays
unprojected with the true camera and intersected with the board's plane), so the detected
corners can be compared with the true camera's projections of the board's corners, and the
fitted camera with the true camera over the image. A real set of fisheye images
(``tests/data/ocamcalib_fisheye2``, see its README) checks the same pipeline on a real lens.
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.calibration import random_views
from omniscape_torch.calibration.detect import detect_corners
from omniscape_torch.calibration.params import transform
from omniscape_torch.calibration.targets import Board, image_circle_mask, render_board
from omniscape_torch.io.images import write_image

cv2 = pytest.importorskip("cv2")
pytestmark = pytest.mark.usefixtures("one_thread")

D = torch.float64
REAL = Path(__file__).resolve().parent / "data" / "ocamcalib_fisheye2"

#: The true camera: a Kannala-Brandt fisheye (conftest.CASES' distortion) on a 640 x 480 image
#: whose 180 degree image circle is cut by the top and bottom edges.
TRUTH = ([170.0, 171.0, 321.3, 238.7, -0.02, 0.004, -0.001, 0.0002], (480, 640))
BOARD = "checkerboard:9x6:0.03"
VIEWS = 10

#: Corner accuracy of detection on these renders (0.01 grey-level noise, squares of 10-40 px),
#: measured: RMS 0.064 px, the largest 0.26 px (small, far-off-axis boards).
CORNER_RMS = 0.12
CORNER_MAX = 0.35

#: The issue's bound on the fitted camera against the truth, pixels (RMS over the image within
#: the angle the corners reach).
RAY_RMS = 0.3


def _truth() -> ot.Camera:
    params, size = TRUTH
    return ot.Camera("kannala_brandt", torch.tensor(params, dtype=D), size, fov=math.pi)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """``VIEWS`` rendered views of ``BOARD`` in a folder, their poses and the truth."""
    camera = _truth()
    board = Board.parse(BOARD)
    # the whole printed page (with its white margin) must be in view, not only the corners
    page = torch.cat((board.object_points(), board.outline(8)))
    _, poses, _ = random_views(camera, page, VIEWS, generator=torch.Generator().manual_seed(0),
                               distance=(0.25, 0.5), max_angle=math.radians(80))
    folder = tmp_path_factory.mktemp("rendered")
    circle = image_circle_mask(camera)
    for i, pose in enumerate(poses):
        image = render_board(camera, board, pose, noise=0.01, circle=circle,
                             generator=torch.Generator().manual_seed(i))
        write_image(folder / f"view_{i:02d}.png", image)
    return folder, poses, camera, board


def _corner_errors(pixels: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Distances to the truth in the detected order or its reverse (the board turned by 180
    degrees in its plane: the same points, which a pose absorbs)."""
    same = (pixels - truth).norm(dim=-1)
    turned = (pixels.flip(0) - truth).norm(dim=-1)
    return same if float(same.max()) <= float(turned.max()) else turned


# --------------------------------------------------------------------------------------------
# boards
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, kind, size, square, marker", [
    ("checkerboard:9x6:0.03", "checkerboard", (9, 6), 0.03, None),
    ("Checkerboard:8X6:0.117", "checkerboard", (8, 6), 0.117, None),
    ("charuco:5x7:0.04:0.03", "charuco", (5, 7), 0.04, 0.03),
    ("charuco:5x7:0.04:0.03:DICT_4X4_50", "charuco", (5, 7), 0.04, 0.03),
])
def test_board_spec(text, kind, size, square, marker):
    board = Board.parse(text)
    assert (board.kind, (board.cols, board.rows), board.square, board.marker) == \
        (kind, size, square, marker)
    assert Board.parse(str(board)) == board
    assert board.object_points().shape == (board.num_corners, 3)


@pytest.mark.parametrize("text, match", [
    ("chessboard:9x6:0.03", "unknown kind"),
    ("checkerboard:9x6", "expected checkerboard:COLSxROWS:SQUARE"),
    ("checkerboard:9by6:0.03", "COLSxROWS"),
    ("checkerboard:9x1:0.03", "rows must be an integer >= 2"),
    ("checkerboard:9x6:-1", "positive number of metres"),
    ("checkerboard:9x6:abc", "numbers of metres"),
    ("charuco:5x7:0.04:0.05", "smaller than the square"),
    ("aprilgrid:6x6:0.088:0.3", "AprilGrid is not supported"),
])
def test_board_spec_errors(text, match):
    with pytest.raises(ValueError, match=match):
        Board.parse(text)


def test_checkerboard_corners_are_the_calibration_module_s():
    """``checkerboard:COLSxROWS`` is ``calibration.checkerboard(rows, cols, square)``: row-major,
    ``cols`` points per row, x along a row (OpenCV's ``patternSize = (cols, rows)`` order)."""
    points = Board.parse("checkerboard:4x3:0.5").object_points()
    assert torch.equal(points, ot.calibration.checkerboard(3, 4, 0.5))
    assert points[1, 0] - points[0, 0] == 0.5 and points[4, 1] - points[0, 1] == 0.5


def test_opencv_is_optional(monkeypatch):
    """Without OpenCV the error says what to install."""
    from omniscape_torch.calibration.targets import require_cv2

    monkeypatch.setitem(sys.modules, "cv2", None)
    with pytest.raises(ImportError, match="pip install opencv-contrib-python-headless"):
        require_cv2()
    with pytest.raises(ImportError, match="opencv-contrib-python-headless"):
        detect_corners([torch.zeros(8, 8, dtype=torch.uint8)], BOARD)


# --------------------------------------------------------------------------------------------
# detection
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
def test_detected_corners_are_the_truth_s_projections(rendered):
    """Every view found; the corners lie within CORNER_RMS / CORNER_MAX of the true camera's
    projections of the board's corners (so OpenCV's corner coordinates are this package's
    pixel convention, centres at integers: a half-pixel shift would show as 0.7 px), in the
    order of ``board.object_points()`` (or the board turned by 180 degrees)."""
    folder, poses, camera, board = rendered
    data = detect_corners(folder, board)
    assert data.names == [f"view_{i:02d}" for i in range(VIEWS)] and data.skipped == {}
    assert data.image_size == camera.image_size
    errors = []
    for points, pixels, pose in zip(data.object_points, data.image_points, poses):
        assert torch.equal(points, board.object_points())
        truth, valid = camera.project(transform(pose, points))
        assert bool(valid.all())
        errors.append(_corner_errors(pixels, truth))
    errors = torch.cat(errors)
    assert errors.numel() == VIEWS * board.num_corners
    assert float(errors.pow(2).mean().sqrt()) < CORNER_RMS, float(errors.pow(2).mean().sqrt())
    assert float(errors.max()) < CORNER_MAX, float(errors.max())


@pytest.mark.numerics
def test_refinement_windows_follow_the_spacing_and_beat_11x11(rendered):
    """The refinement window of each corner (``detect.refine_windows``) stays short of every
    other corner (0.6 of the distance to the closest, whatever the grid) and grows with the
    spacing; on the renders the refined corners are closer to the truth than
    ``cv2.cornerSubPix`` with OpenCV samples' 11 x 11 window for every corner, from the same
    unrefined corners (measured: 0.064 against 0.142 px RMS)."""
    from omniscape_torch.calibration.detect import refine_windows

    folder, poses, camera, board = rendered
    raw = detect_corners(folder, board, refine=False)
    ours = detect_corners(folder, board)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    errors = {"ours": [], "11x11": []}
    sizes = set()
    for path, pixels, refined, ids, pose in zip(sorted(folder.iterdir()), raw.image_points,
                                                ours.image_points, raw.ids, poses):
        corners = pixels.numpy()
        windows = refine_windows(corners, ids.numpy(), board)
        others = torch.cdist(pixels, pixels) + torch.eye(len(pixels), dtype=D) * 1e9
        window = torch.from_numpy(windows)
        assert bool(((window <= 0.6 * others.min(dim=1).values) | (window == 2)).all())
        sizes |= set(windows.tolist())
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        opencv = cv2.cornerSubPix(grey, corners.astype("float32").reshape(-1, 1, 2), (5, 5),
                                  (-1, -1), criteria).reshape(-1, 2)
        truth, _ = camera.project(transform(pose, board.object_points()[ids]))
        errors["ours"].append(_corner_errors(refined, truth))
        errors["11x11"].append(_corner_errors(torch.from_numpy(opencv).double(), truth))
    assert len(sizes) > 1 and max(sizes) == 5   # small squares get smaller windows
    rms = {k: float(torch.cat(v).pow(2).mean().sqrt()) for k, v in errors.items()}
    assert rms["ours"] < rms["11x11"], rms


def test_images_without_the_board_are_skipped_and_listed(rendered):
    folder, _, camera, board = rendered
    blank = torch.full(camera.image_size, 128, dtype=torch.uint8)
    images = sorted(folder.iterdir())[:3]
    data = detect_corners([*images, blank], board, names=["a", "b", "c", "empty wall"])
    assert data.names == ["a", "b", "c"]
    assert list(data.skipped) == ["empty_wall"] and "no 9x6 checkerboard" in \
        data.skipped["empty_wall"]
    with pytest.raises(ValueError, match=r"found in 2 of 3 images, fewer than the 3 needed; "
                                         r"no checkerboard:9x6:0.03 in 1 of them, nor a board "
                                         r"of a nearby size \(10x6, 8x6, 9x7, 9x5, 8x5, 10x7\)"):
        detect_corners([*images[:2], blank], board, names=["a", "b", "empty wall"])
    with pytest.raises(ValueError, match="all images must have one size"):
        detect_corners([images[0], torch.zeros(100, 100, dtype=torch.uint8)], board)


def _bad_files(folder: Path, view: Path) -> dict[str, bytes]:
    """Three unusable files beside the views: a JPEG of ``view`` cut at 90% (OpenCV decodes
    its top part without an error), random bytes, and an empty file."""
    ok, jpeg = cv2.imencode(".jpg", cv2.imread(str(view), cv2.IMREAD_GRAYSCALE))
    files = {"cut.jpg": jpeg.tobytes()[:int(0.9 * len(jpeg))],
             "noise.png": torch.randint(0, 256, (5000,), dtype=torch.uint8,
                                        generator=torch.Generator().manual_seed(0))
             .numpy().tobytes(),
             "empty.jpg": b""}
    for name, data in files.items():
        (folder / name).write_bytes(data)
    assert cv2.imread(str(folder / "cut.jpg")) is not None   # OpenCV alone would use it
    assert cv2.imread(str(folder / "noise.png")) is None
    return files


def test_corrupt_images_are_skipped_with_their_reason(rendered, tmp_path):
    """``detect_corners`` on a folder with a truncated JPEG, random bytes and an empty file
    among the views: each is skipped with why, the views are kept."""
    folder, _, _, board = rendered
    views = sorted(folder.iterdir())[:2]
    for path in views:
        (tmp_path / path.name).write_bytes(path.read_bytes())
    bad = _bad_files(tmp_path, views[0])
    data = detect_corners(tmp_path, board, min_views=2)
    assert data.names == [p.stem for p in views]
    assert data.skipped == {"cut": "not an image OpenCV can decode (corrupt or truncated?)",
                            "noise": "not an image OpenCV can decode (corrupt or truncated?)",
                            "empty": "an empty file (0 bytes)"}, data.skipped
    assert set(data.skipped) == {Path(name).stem for name in bad}


@pytest.mark.slow   # a fit and its plots: 3 to 5 s
@pytest.mark.numerics
def test_corrupt_images_are_skipped_one_line_each(rendered, tmp_path, capsys):
    """``fit --images`` with a truncated JPEG, random bytes and an empty file among the views:
    each is skipped with one line naming it, and the fit is written from the others."""
    folder, _, _, board = rendered
    views = tmp_path / "views"
    views.mkdir()
    for path in sorted(folder.iterdir())[:4]:
        (views / path.name).write_bytes(path.read_bytes())
    bad = _bad_files(views, sorted(folder.iterdir())[0])
    out = tmp_path / "out"
    code = cli.main(["fit", "--images", str(views), "--board", BOARD, "--model",
                     "kannala_brandt", "--fov", "180", "--out", str(out), "--no-progress"])
    captured = capsys.readouterr()
    assert code in (0, 3), captured.err
    assert (out / "camera.json").exists()
    report = json.loads((out / "report.json").read_text())
    assert report["num_views"] == 4 and set(report["skipped_images"]) == {
        Path(name).stem for name in bad}
    for name in bad:
        lines = [line for line in captured.out.splitlines() if Path(name).stem in line]
        assert len(lines) == 1 and "skipped" in lines[0], captured.out
    assert "corrupt or truncated" in next(line for line in captured.out.splitlines()
                                          if "cut" in line)


@pytest.mark.slow   # 3 to 5 s: the sector-based detector's exhaustive search fails slowly
def test_a_wrong_board_size_is_one_summary_line(rendered):
    """A 9x6 board given as 8x6 (a corner fewer): one short message saying which size is
    seen where the given one is not (OpenCV may find the 8x6 part of the board in a view),
    not a reason per image."""
    folder, _, _, board = rendered
    images = sorted(folder.iterdir())[:3]
    with pytest.raises(ValueError) as err:
        detect_corners(images, "checkerboard:8x6:0.03")
    message = str(err.value)
    assert re.search(r"found in [01] of 3 images, fewer than the 3 needed; no "
                     r"checkerboard:8x6:0.03 in ([23]) of them; a 9x6 board is seen in \1 of "
                     r"them \(--board checkerboard:9x6:0.03\)$", message), message
    assert "\n" not in message and len(message) < 250


def _aruco_or_skip():
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
        pytest.skip("OpenCV without aruco's CharucoDetector (opencv-contrib >= 4.7)")


@pytest.mark.numerics
def test_charuco_boards_are_detected():
    """A ChArUco board rendered through the fisheye: the corners found (partial views kept)
    are the truth's projections of their ids' target points, so ``Board.object_points`` and
    OpenCV's ids agree. (Less accurate than a checkerboard's: OpenCV interpolates the corners
    from the markers before the refinement.)"""
    _aruco_or_skip()
    camera = _truth()
    board = Board.parse("charuco:7x5:0.06:0.045:4X4_50")
    page = torch.cat((board.object_points(), board.outline(8)))
    _, poses, _ = random_views(camera, page, 3, generator=torch.Generator().manual_seed(3),
                               distance=(0.3, 0.35), max_angle=math.radians(40))
    texture = board.texture()
    images = [render_board(camera, board, pose, noise=0.005, texture=texture,
                           generator=torch.Generator().manual_seed(i))
              for i, pose in enumerate(poses)]
    data = detect_corners(images, board)
    assert data.skipped == {} and sum(map(len, data.ids)) >= 0.7 * 3 * board.num_corners
    errors = []
    for points, pixels, ids, pose in zip(data.object_points, data.image_points, data.ids, poses):
        assert torch.equal(points, board.object_points()[ids])
        truth, _ = camera.project(transform(pose, points))
        errors.append((pixels - truth).norm(dim=-1))
    errors = torch.cat(errors)
    assert float(errors.pow(2).mean().sqrt()) < 0.3 and float(errors.max()) < 0.7, errors.max()


# --------------------------------------------------------------------------------------------
# fit --images
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fitted(rendered, tmp_path_factory):
    folder, poses, camera, board = rendered
    out = tmp_path_factory.mktemp("fit") / "out"
    # --fov: the image circle of the renders is known (test_real_fisheye_images measures one)
    code = cli.main(["fit", "--images", str(folder), "--board", BOARD, "--model",
                     "kannala_brandt", "--fov", "180", "--out", str(out), "--no-progress"])
    return code, out


def _rms_to_the_truth(camera, fitted_camera, out) -> float:
    """RMS pixel distance between the true and the fitted camera's projections of the true
    camera's pixel rays (every 4th pixel), over the angle the detected corners reach
    (``out/correspondences.txt``)."""
    h, w = camera.image_size
    v, u = torch.meshgrid(torch.arange(0, h, 4, dtype=D), torch.arange(0, w, 4, dtype=D),
                          indexing="ij")
    grid = torch.stack((u, v), -1).reshape(-1, 2)
    rays, valid = camera.unproject(grid)
    angle = torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2])
    corners = ot.calibration.read_correspondences(out / "correspondences.txt").image_points
    corner_rays, _ = camera.unproject(torch.cat(corners))
    reach = float(torch.atan2(corner_rays[:, :2].norm(dim=-1), corner_rays[:, 2]).max())
    keep = valid & (angle <= reach)
    pixels, ok = fitted_camera.project(rays[keep])
    assert bool(ok.all()) and int(keep.sum()) > 5000
    return float((pixels - grid[keep]).norm(dim=-1).pow(2).mean().sqrt())


@pytest.mark.numerics
def test_fit_images_recovers_the_truth(rendered, fitted):
    """``fit --images``: converged, well covered (exit 0), and within RAY_RMS of the truth: the
    RMS over a grid of pixels of |fitted.project(ray) - pixel| for the truth's rays no farther
    off axis than the corners reach."""
    folder, _, camera, board = rendered
    code, out = fitted
    assert code == 0
    assert {p.name for p in out.iterdir()} == {
        "camera.json", "report.json", "report.md", "residuals.png", "uncertainty.png",
        "correspondences.txt"}
    fitted_camera = ot.Camera.load_json(out / "camera.json")
    report = json.loads((out / "report.json").read_text())
    assert report["board"] == BOARD and report["coverage"]["ok"]
    assert report["coverage"]["fov_deg"] == 180
    rms = _rms_to_the_truth(camera, fitted_camera, out)
    assert rms < RAY_RMS, rms


@pytest.mark.slow
@pytest.mark.numerics
@pytest.mark.parametrize("model, freeze", [("thin_prism_fisheye", "p1,p2,sx1,sy1"),
                                           ("fisheye624", "p0,p1,s0,s1,s2,s3"),
                                           ("woodscape", None)])
def test_fit_images_with_the_issue_34_fisheyes(rendered, tmp_path, model, freeze):
    """``fit --images --model`` with issue 34's fisheyes (both hold the true Kannala-Brandt
    lens) and WoodScape's (its quartic in theta follows it): converged, and within RAY_RMS of
    the truth over the angle the corners reach.

    Their tangential and thin-prism terms are held (``--freeze``): the lens is symmetric, and
    freed they trade off against the principal point and the poses' rotations (measured on
    these renders: the same 0.075 px residual with the centre 3.3 px off and the truth's
    pixels 1.7 px (fisheye624) to 2.8 px (thin prism) RMS away in the camera's frame)."""
    folder, _, camera, board = rendered
    out = tmp_path / "out"
    code = cli.main(["fit", "--images", str(folder), "--board", BOARD, "--model", model,
                     *(["--freeze", freeze] if freeze else []), "--fov", "180", "--out",
                     str(out), "--no-progress"])
    assert code in (0, 3)   # 3: coverage warnings only; the files are written
    fit_report = json.loads((out / "camera.json").read_text())["fit"]
    assert fit_report["converged"], fit_report["reason"]
    fitted_camera = ot.Camera.load_json(out / "camera.json")
    assert fitted_camera.model.name == model
    rms = _rms_to_the_truth(camera, fitted_camera, out)
    assert rms < RAY_RMS, rms


def test_fit_images_report_is_consistent(fitted):
    """report.json's per-view RMS and largest error are those of the fitted camera and poses
    (camera.json) on the corners written beside them, and both files hold the same
    parameters."""
    code, out = fitted
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    saved = json.loads((out / "camera.json").read_text())
    camera = ot.Camera.load_json(out / "camera.json")
    data = ot.calibration.read_correspondences(out / "correspondences.txt")
    assert [v["name"] for v in report["views"]] == data.names
    poses = torch.tensor(saved["fit"]["poses"], dtype=D)
    squares = []
    for view, points, pixels, pose in zip(report["views"], data.object_points,
                                          data.image_points, poses):
        projected, _ = camera.project(transform(pose, points))
        dist = (projected - pixels).norm(dim=-1)
        squares.append(dist.pow(2))
        assert view["rms_px"] == pytest.approx(float(dist.pow(2).mean().sqrt()), rel=1e-6)
        assert view["max_px"] == pytest.approx(float(dist.max()), rel=1e-6)
        assert view["points"] == view["kept"] == len(dist) and view["outliers"] == []
    assert report["rms_px"] == pytest.approx(float(torch.cat(squares).mean().sqrt()), rel=1e-6)
    assert {k: p["value"] for k, p in report["params"].items()} == pytest.approx(
        saved["params"], rel=1e-12)
    assert saved["fit"]["coverage"]["ok"] is True
    md = (out / "report.md").read_text()
    assert "well constrained" in md and "| view_00 | 54 | 54 |" in md
    for name in ("residuals.png", "uncertainty.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------
# a real fisheye
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
def test_real_fisheye_images(tmp_path, capsys):
    """Eight real images of a ~180 degree fisheye (tests/data/ocamcalib_fisheye2/README.md):
    the board is found in all, the fit converges with a sub-pixel RMS (0.12 px), the image
    circle is measured (178 degrees) and the views cover it (predicted error 0.11 px at
    most)."""
    out = tmp_path / "out"
    code = cli.main(["fit", "--images", str(REAL), "--board", "checkerboard:8x6:0.117",
                     "--model", "scaramuzza", "--out", str(out), "--no-progress"])
    assert code == 0, capsys.readouterr().err   # well constrained, too
    report = json.loads((out / "report.json").read_text())
    assert report["converged"] and report["num_views"] == 8 and report["skipped_images"] == {}
    assert report["rms_px"] < 1.0, report["rms_px"]
    assert all(v["max_px"] < 2.0 for v in report["views"])
    assert ot.Camera.from_ocamcalib(out / "calib_results.txt").image_size == (480, 748)
    assert 160 < report["coverage"]["fov_deg"] < 200 and report["coverage"]["ok"]
    assert report["fov_source"] == "image circle" and report["fov_note"] is None
    saved = json.loads((out / "camera.json").read_text())   # the measured circle is kept
    assert saved["fov_deg"] == pytest.approx(report["coverage"]["fov_deg"])


# --------------------------------------------------------------------------------------------
# an image circle that cannot be measured (issue 33): the fit is never lost
# --------------------------------------------------------------------------------------------

#: Radius (pixels) of the black disc about the principal point of the ``dark centre`` renders
#: (a catadioptric camera's blind spot): inside the 60 px disc where ``image_circle`` reads the
#: lit level, so that level is lit while the innermost ring is not.
BLIND_RADIUS = 30


@pytest.fixture(scope="module")
def unmeasurable(rendered, tmp_path_factory):
    """The renders made unmeasurable two ways, each in a folder: ``full frame`` (the pixels
    past the 180 degree circle lit with the background's grey: a lens whose circle lies beyond
    the sensor) and ``dark centre`` (a black disc about the principal point)."""
    from omniscape_torch.io.images import read_image

    folder, _, camera, board = rendered
    circle = image_circle_mask(camera)
    h, w = camera.image_size
    v, u = torch.meshgrid(torch.arange(h, dtype=D), torch.arange(w, dtype=D), indexing="ij")
    blind = torch.hypot(u - camera.params[2], v - camera.params[3]) < BLIND_RADIUS
    folders = {}
    for kind in ("full frame", "dark centre"):
        out = tmp_path_factory.mktemp(kind.replace(" ", "_"))
        for path in sorted(folder.iterdir()):
            image = read_image(path).reshape(h, w).clone()
            if kind == "full frame":
                image[~circle] = round(0.45 * 255)   # render_board's background
            else:
                image[blind] = 0
            write_image(out / path.name, image)
        folders[kind] = out
    return folders


def _mean_image(folder: Path, size) -> torch.Tensor:
    from omniscape_torch.io.images import read_image

    return torch.stack([read_image(p).double().reshape(size) for p in sorted(folder.iterdir())]
                       ).mean(0)


def test_image_circle_of_a_full_frame_and_a_dark_centre(rendered, unmeasurable):
    """``image_circle`` on the mean image (as ``fit --images`` measures it): 180 degrees on the
    renders; ``2 pi`` (the circle beyond the sensor) when lit to the corners (before issue 33:
    106 degrees, a circle that is not there); ``0`` (not measurable) with a dark centre (the
    innermost ring unlit: what made ``fit`` fail after the fit, "fov: ... got 0.0")."""
    from omniscape_torch.calibration.convert import image_circle

    folder, _, camera, _ = rendered
    assert math.degrees(image_circle(_mean_image(folder, camera.image_size), camera)) == \
        pytest.approx(180, abs=2)
    full = _mean_image(unmeasurable["full frame"], camera.image_size)
    assert image_circle(full, camera) == 2 * math.pi
    dark = _mean_image(unmeasurable["dark centre"], camera.image_size)
    assert image_circle(dark, camera) == 0.0


def _max_image(folder: Path, size) -> torch.Tensor:
    from omniscape_torch.io.images import read_image

    return torch.stack([read_image(p).double().reshape(size) for p in sorted(folder.iterdir())]
                       ).amax(0)


def test_blind_cone_of_a_dark_centre(rendered, unmeasurable):
    """``blind_cone`` on the per-pixel maximum of the views (as ``fit --images`` measures it):
    the black disc of the ``dark centre`` renders is the angle its radius (BLIND_RADIUS px)
    makes through the true camera, within the 1 degree rings and the blur; none on the plain
    renders (their centre lit in some view)."""
    from omniscape_torch.calibration.convert import blind_cone

    folder, _, camera, _ = rendered
    edge, _ = camera.unproject(camera.params[2:4] + torch.tensor([BLIND_RADIUS, 0.0], dtype=D))
    truth = 2 * math.degrees(math.atan2(float(edge[:2].norm()), float(edge[2])))
    dark = _max_image(unmeasurable["dark centre"], camera.image_size)
    assert math.degrees(blind_cone(dark, camera)) == pytest.approx(truth, abs=3)
    assert blind_cone(_max_image(folder, camera.image_size), camera) == 0.0


def _broken(*args, **kwargs):
    raise RuntimeError("measurement failed")


@pytest.mark.numerics
@pytest.mark.parametrize("kind, source, patch", [
    # the renders themselves (2 to 3 s each: the slow tier) ...
    pytest.param("full frame", "whole sensor", None, marks=pytest.mark.slow),
    pytest.param("dark centre", "corners' reach", None, marks=pytest.mark.slow),
    # ... and image_circle's answers on them, or a failure, on the plain renders (under 1 s)
    ("rendered", "whole sensor", lambda *a, **k: 2 * math.pi),
    ("rendered", "corners' reach", lambda *a, **k: 0.0),
    ("rendered", "corners' reach", lambda *a, **k: math.nan),
    ("rendered", "corners' reach", _broken),
])
def test_fit_images_never_loses_a_fit(rendered, unmeasurable, tmp_path, capsys, monkeypatch,
                                      kind, source, patch):
    """Where the image circle cannot be measured (0, NaN, an error) or lies beyond the sensor,
    ``fit --images`` (no ``--fov``) still writes its files (exit 0 or 3), says so in one line
    on stderr naming ``--fov DEG``, and the reports name the fallback (``fov_source``): the
    corners' reach (twice their largest angle off axis through the fitted camera), or the whole
    sensor."""
    if patch is not None:   # where calibrate looks it up (calibration.calibrate: a function)
        monkeypatch.setattr(sys.modules["omniscape_torch.calibration.calibrate"],
                            "image_circle", patch)
    folder = rendered[0] if kind == "rendered" else unmeasurable[kind]
    out = tmp_path / "out"
    code = cli.main(["fit", "--images", str(folder), "--board", BOARD, "--model",
                     "kannala_brandt", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert code in (0, 3), err
    assert {"camera.json", "report.json", "report.md", "correspondences.txt"} <= \
        {p.name for p in out.iterdir()}
    lines = [line for line in err.splitlines() if "field of view for coverage" in line]
    assert len(lines) == 1 and "--fov DEG" in lines[0], err
    assert ("the whole sensor" if source == "whole sensor" else "the corners' reach") in lines[0]
    report = json.loads((out / "report.json").read_text())
    assert report["fov_source"] == source and report["fov_note"]
    assert f"from: {source}" in (out / "report.md").read_text()
    if source == "whole sensor":
        assert report["coverage"]["fov_deg"] is None or report["coverage"]["fov_deg"] > 180
    else:
        fitted_camera = ot.Camera.load_json(out / "camera.json")
        corners = ot.calibration.read_correspondences(out / "correspondences.txt").image_points
        rays, _ = fitted_camera.unproject(torch.cat(corners))
        reach = float(torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2]).max())
        assert report["coverage"]["fov_deg"] == pytest.approx(2 * math.degrees(reach),
                                                              rel=1e-6)


def test_fit_images_names_the_image_circle_and_fov(fitted):
    """The measured or given field of view is named in the reports too (``--fov`` here), and
    camera.json keeps it (issue 33), so that later conversions and exports judge that area."""
    _, out = fitted
    report = json.loads((out / "report.json").read_text())
    assert report["fov_source"] == "--fov" and report["fov_note"] is None
    assert "from: --fov" in (out / "report.md").read_text()
    saved = json.loads((out / "camera.json").read_text())
    assert saved["fov_deg"] == pytest.approx(180) and saved["fit"]["fov_source"] == "--fov"
    assert ot.Camera.load_json(out / "camera.json").fov == pytest.approx(math.pi)


def test_convert_image_with_a_dark_centre_asks_for_fov(rendered, unmeasurable, tmp_path, capsys):
    """``convert-model --image PHOTO`` whose image circle cannot be measured (a dark centre)
    stops before any fit with one line naming ``--fov DEG`` (before: an error on fov 0.0)."""
    _, _, camera, _ = rendered
    camera.save_json(tmp_path / "camera.json")
    photo = sorted(unmeasurable["dark centre"].iterdir())[0]
    code = cli.main(["convert-model", "--to", "unified", "--json", str(tmp_path / "camera.json"),
                     "--image", str(photo), "--out", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert code == 2 and "could not be measured" in err and "--fov DEG" in err, err
