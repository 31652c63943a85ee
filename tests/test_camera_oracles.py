"""Camera models against independent implementations: OpenCV ``fisheye`` and ``omnidir``, pycolmap.

Every comparison runs in float64 over a swept grid of directions (angle to the optical axis x
azimuth, at several distances), keeps only the points where *both* sides are valid, counts them
(``compared``) and ends with ``assert compared > 0``, so that a domain that shrinks to nothing
fails instead of passing vacuously. Run with ``-s`` to see one summary line per comparison.

Conventions converted here, and only here:

* OpenCV puts pixel centres at integers, as we do: its (K, D, xi) are our parameters as they are.
* COLMAP puts the centre of the top-left pixel at (0.5, 0.5) (``src/colmap/sensor/models.h``), so
  ``cx_colmap = cx + 0.5`` and ``pixel_colmap = pixel + 0.5``.
* ``cv2.fisheye`` and COLMAP's fisheye models take ``theta = atan(r / z)``, which folds points
  behind the camera onto the front: they are compared below 90 degrees only.
* ``cv2.fisheye.undistortPoints``, ``cv2.omnidir.undistortPoints`` and COLMAP's ``cam_from_img``
  return ``(x / z, y / z)``: a ray only in front of the camera (z > 0).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.cameras import get_model

cv2 = pytest.importorskip("cv2")
pycolmap = pytest.importorskip("pycolmap")

f64 = torch.float64

#: Pixel tolerance of every projection comparison. Both sides evaluate the same closed form in
#: float64 in a different order, so they differ by rounding only: a few hundred ulp of the largest
#: pixel coordinate compared (< 1e5 px here), i.e. < 1e-8 px (measured: <= 4e-12 px). 1e-6 px
#: leaves two orders of margin above that and stays five orders below the smallest convention
#: error it must catch (a half-pixel shift, a swapped or mis-scaled parameter).
PIXEL_TOL = 1e-6

#: Tolerance of ``cv2.fisheye.undistortPoints``'s rays (rad). OpenCV inverts ``theta_d(theta)``
#: by Newton and stops when a step is below its criteria's epsilon (default 1e-8): the error left
#: is then below the size of that last step, so 1e-8 rad is what OpenCV itself guarantees. Newton
#: converges quadratically: measured against the known rays, OpenCV's error is <= 4e-14 rad (the
#: largest at the fold of the "folding" set, where there is 1 px per radian).
CV_FISHEYE_RAY_TOL = 1e-8

#: A point counts as converged by an OpenCV undistortion when OpenCV's own forward model maps its
#: answer back onto the input pixel within this many pixels (1000 times the float64 rounding of a
#: pixel coordinate, ~1e-12 px). It excludes OpenCV's failures, which it does not flag:
#: ``cv2.fisheye`` clamps ``theta_d`` to pi / 2 (strong positive distortion near 90 degrees), and
#: ``cv2.omnidir`` runs a fixed 20 fixed-point iterations, which may stop short of the root.
CV_CONVERGED_PX = 1e-9

#: Tolerance of ``cv2.omnidir.undistortPoints``'s rays (rad), on converged points only. Its 20
#: iterations have no tolerance of their own; the round-trip residual (<= CV_CONVERGED_PX) over the
#: local scale (>= 148 px per radian on these grids) bounds OpenCV's ray error by 7e-12 rad.
#: Measured: <= 2e-12 rad. 1e-9 rad leaves two orders of margin.
CV_OMNIDIR_RAY_TOL = 1e-9

#: Tolerance of pycolmap's ``cam_ray_from_img`` rays (rad). COLMAP's ``IterativeUndistortion``
#: (models.h) stops when a Newton step is below 1e-5 normalised units (``kMinStepSquaredNorm =
#: 1e-10``); the error left after such a step is quadratic in it, C * 1e-10 with C of order one
#: away from a fold (measured: <= 6e-11 rad), larger next to one (7e-10 rad at the fold of the
#: "folding" set). 1e-8 rad keeps an order of margin. Models with a closed-form inverse are held to
#: the same bound (measured ~6e-16 rad).
COLMAP_RAY_TOL = 1e-8


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------

def sphere_grid(max_deg: float, step_deg: float = 0.5, n_azimuth: int = 24) -> np.ndarray:
    """Points at angles 0..max_deg (step_deg) from +z x n_azimuth azimuths, at distances from
    0.2 m to 40 m (the models are central: the distance must not matter). ``(N, 3)``."""
    theta = np.radians(np.arange(0.0, max_deg + step_deg / 2, step_deg))
    azimuth = np.radians(np.arange(n_azimuth) * 360.0 / n_azimuth + 7.0)
    t, a = np.meshgrid(theta, azimuth, indexing="ij")
    dirs = np.stack((np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)), -1).reshape(-1, 3)
    distances = np.array([0.2, 1.0, 7.5, 40.0])
    return dirs * distances[np.arange(len(dirs)) % len(distances), None]


def off_axis_angle(points: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(points[:, :2], axis=-1), points[:, 2])


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (rad) between rows of ``a`` and ``b``; atan2 is accurate at small angles."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1))


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def plane_rays(xy: np.ndarray) -> np.ndarray:
    """Unit rays of normalised pinhole coordinates ``(x / z, y / z)`` (z > 0)."""
    return unit(np.concatenate((xy, np.ones_like(xy[:, :1])), axis=-1))


def ours_project(model: str, points: np.ndarray, params) -> tuple[np.ndarray, np.ndarray]:
    pixels, valid = get_model(model).project(torch.from_numpy(points),
                                             torch.tensor(params, dtype=f64))
    return pixels.numpy(), valid.numpy()


def ours_unproject(model: str, pixels: np.ndarray, params) -> tuple[np.ndarray, np.ndarray]:
    rays, valid = get_model(model).unproject(torch.from_numpy(np.ascontiguousarray(pixels)),
                                             torch.tensor(params, dtype=f64))
    return rays.numpy(), valid.numpy()


def in_image(pixels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixels on a sensor of ``size = (H, W)`` (pixel edges included), pixel centres at integers."""
    h, w = size
    finite = np.isfinite(pixels).all(-1)
    p = np.where(finite[:, None], pixels, 0.0)
    return finite & (p[:, 0] >= -0.5) & (p[:, 0] <= w - 0.5) & (p[:, 1] >= -0.5) & (
        p[:, 1] <= h - 0.5)


def report(what: str, compared: int, px: float | None = None, rad: float | None = None) -> None:
    px_s = "-" if px is None else f"{px:.2e}"
    rad_s = "-" if rad is None else f"{rad:.2e}"
    print(f"\n[oracle] {what}: compared={compared} max_px={px_s} max_rad={rad_s}")


def k_matrix(fx, fy, cx, cy) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------------
# 1. cv2.fisheye vs kannala_brandt
# --------------------------------------------------------------------------------------------

#: (id, fx, fy, cx, cy, (k1, k2, k3, k4), image size (H, W)).
FISHEYE_SETS = [
    # k = 0: the equidistant model.
    ("equidistant", 300.0, 300.0, 639.5, 479.5, (0.0, 0.0, 0.0, 0.0), (960, 1280)),
    # A typical calibrated 190-degree lens (small coefficients, fx != fy, off-centre).
    ("typical", 285.72, 286.11, 640.31, 481.17, (-0.0134, 0.0513, -0.0437, 0.0089), (960, 1280)),
    # Strong positive distortion: OpenCV's undistortion clamps theta_d to pi / 2 near 90 deg.
    ("strong_positive", 400.0, 390.0, 700.0, 500.0, (0.3, 0.1, -0.05, 0.01), (1000, 1400)),
    # Strong barrel distortion whose r(theta) folds at ~69 deg: compared inside the fold only.
    ("folding", 350.0, 352.0, 640.0, 480.0, (-0.35, 0.05, 0.0, 0.0), (960, 1280)),
]


def _fisheye_case(case):
    _, fx, fy, cx, cy, d, size = case
    return k_matrix(fx, fy, cx, cy), np.array(d), [fx, fy, cx, cy, *d], size


def _cv_fisheye_project(points: np.ndarray, K, D) -> np.ndarray:
    pixels, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    return pixels.reshape(-1, 2)


@pytest.mark.parametrize("case", FISHEYE_SETS, ids=[c[0] for c in FISHEYE_SETS])
def test_kannala_brandt_project_matches_cv2_fisheye(case):
    K, D, params, _ = _fisheye_case(case)
    points = sphere_grid(89.0)  # cv2.fisheye folds at 90 degrees (atan(r / z))
    cv_px = _cv_fisheye_project(points, K, D)
    px, valid = ours_project("kannala_brandt", points, params)
    both = valid & np.isfinite(cv_px).all(-1)
    err = np.abs(px - cv_px).max(-1)[both]
    compared = int(both.sum())
    report(f"kannala_brandt/{case[0]} vs cv2.fisheye.projectPoints", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    if case[0] == "folding":  # the fold is excluded, not compared
        assert compared < len(points)
    assert compared > 0


@pytest.mark.parametrize("case", FISHEYE_SETS, ids=[c[0] for c in FISHEYE_SETS])
def test_kannala_brandt_unproject_matches_cv2_fisheye_undistort(case):
    K, D, params, _ = _fisheye_case(case)
    points = sphere_grid(89.0)
    _, valid = ours_project("kannala_brandt", points, params)
    points = points[valid]  # inside our domain (below the fold), as in the projection test
    pixels = _cv_fisheye_project(points, K, D)
    cv_xy = cv2.fisheye.undistortPoints(pixels.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    # OpenCV marks its own failures (theta flipped, no convergence) with -1e6; its clamp of theta_d
    # at pi / 2 is not marked: the round trip through OpenCV's forward model catches it.
    flagged = (cv_xy <= -1e5).all(-1) | ~np.isfinite(cv_xy).all(-1)
    back = cv2.fisheye.distortPoints(np.where(flagged[:, None], 0.0, cv_xy).reshape(-1, 1, 2),
                                     K, D).reshape(-1, 2)
    converged = ~flagged & (np.abs(back - pixels).max(-1) <= CV_CONVERGED_PX)
    rays, ok = ours_unproject("kannala_brandt", pixels, params)
    both = converged & ok
    err = angle_between(rays[both], plane_rays(cv_xy[both]))
    compared = int(both.sum())
    report(f"kannala_brandt/{case[0]} vs cv2.fisheye.undistortPoints "
           f"(OpenCV vs truth {angle_between(plane_rays(cv_xy[both]), points[both]).max():.1e})",
           compared, rad=err.max())
    assert err.max() <= CV_FISHEYE_RAY_TOL
    assert compared > 0


# --------------------------------------------------------------------------------------------
# 2. cv2.omnidir vs unified
# --------------------------------------------------------------------------------------------

#: (id, fx, fy, cx, cy, xi, (k1, k2, p1, p2), image size (H, W)); skew 0.
OMNI_SETS = [
    ("xi_lt_1", 250.0, 252.0, 640.3, 480.7, 0.6, (0.0, 0.0, 0.0, 0.0), (960, 1280)),
    ("xi_lt_1_dist", 250.0, 252.0, 640.3, 480.7, 0.6, (-0.25, 0.07, 1e-3, -5e-4), (960, 1280)),
    ("xi_eq_1", 300.0, 300.0, 640.0, 480.0, 1.0, (0.0, 0.0, 0.0, 0.0), (960, 1280)),
    ("xi_eq_1_dist", 300.0, 301.0, 640.0, 480.0, 1.0, (-0.1, 0.02, 2e-3, 1e-3), (960, 1280)),
    ("xi_gt_1", 900.0, 905.0, 640.0, 480.0, 2.5, (0.0, 0.0, 0.0, 0.0), (960, 1280)),
    ("xi_gt_1_dist", 900.0, 905.0, 640.0, 480.0, 2.5, (0.3, -0.05, -1e-3, 2e-3), (960, 1280)),
    ("xi_gt_1_barrel", 1100.0, 1100.0, 640.0, 480.0, 1.7, (-0.3, 0.1, 0.0, 0.0), (960, 1280)),
]


def _omni_case(case):
    _, fx, fy, cx, cy, xi, d, size = case
    return k_matrix(fx, fy, cx, cy), np.array([d]), xi, [fx, fy, cx, cy, xi, *d], size


def _cv_omnidir_project(points: np.ndarray, K, D, xi: float) -> np.ndarray:
    pixels, _ = cv2.omnidir.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                          xi, D)
    return pixels.reshape(-1, 2)


@pytest.mark.skipif(not hasattr(cv2, "omnidir"), reason="needs opencv-contrib (cv2.omnidir)")
@pytest.mark.parametrize("case", OMNI_SETS, ids=[c[0] for c in OMNI_SETS])
def test_unified_project_matches_cv2_omnidir(case):
    K, D, xi, params, size = _omni_case(case)
    # The unified model sees past 90 degrees; OpenCV does not check its domain (it divides by
    # z / |X| + xi wherever that is), so our valid set decides, and the sensor bounds the radius
    # (far outside it 1 + cos(theta) cancels and the pixel coordinates reach 1e4 f).
    points = sphere_grid(179.0)
    cv_px = _cv_omnidir_project(points, K, D, xi)
    px, valid = ours_project("unified", points, params)
    both = valid & in_image(cv_px, size)
    err = np.abs(px - cv_px).max(-1)[both]
    compared = int(both.sum())
    report(f"unified/{case[0]} vs cv2.omnidir.projectPoints (to "
           f"{math.degrees(off_axis_angle(points[both]).max()):.1f} deg)", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    assert compared > 0


@pytest.mark.skipif(not hasattr(cv2, "omnidir"), reason="needs opencv-contrib (cv2.omnidir)")
@pytest.mark.parametrize("case", OMNI_SETS, ids=[c[0] for c in OMNI_SETS])
def test_unified_unproject_matches_cv2_omnidir_undistort(case):
    K, D, xi, params, size = _omni_case(case)
    # cv2.omnidir.undistortPoints returns (x / z, y / z) of the lifted ray: a ray only for z > 0,
    # so the inputs are the pixels of points in front of the camera.
    points = sphere_grid(89.0)
    _, valid = ours_project("unified", points, params)
    pixels = _cv_omnidir_project(points, K, D, xi)
    keep = valid & in_image(pixels, size)
    points, pixels = points[keep], pixels[keep]
    cv_xy = cv2.omnidir.undistortPoints(pixels.reshape(-1, 1, 2), K, D, np.array([xi]),
                                        np.eye(3)).reshape(-1, 2)
    finite = np.isfinite(cv_xy).all(-1)
    cv_rays = plane_rays(np.where(finite[:, None], cv_xy, 0.0))
    back = _cv_omnidir_project(cv_rays, K, D, xi)
    converged = finite & (np.abs(back - pixels).max(-1) <= CV_CONVERGED_PX)
    rays, ok = ours_unproject("unified", pixels, params)
    both = converged & ok
    err = angle_between(rays[both], cv_rays[both])
    compared = int(both.sum())
    report(f"unified/{case[0]} vs cv2.omnidir.undistortPoints ({int((~converged).sum())} not "
           f"converged by OpenCV)", compared, rad=err.max())
    assert err.max() <= CV_OMNIDIR_RAY_TOL
    assert compared > 0


# --------------------------------------------------------------------------------------------
# 3. pycolmap
# --------------------------------------------------------------------------------------------

def _c(v: float) -> float:
    """Our pixel coordinate -> COLMAP's (pixel centres at +0.5)."""
    return v + 0.5


#: (id, COLMAP model, COLMAP params, our model, our params, image size (H, W), grid max angle).
#: Parameter orders from ``pycolmap.Camera(...).params_info`` (COLMAP's models.h). COLMAP's
#: perspective and fisheye models need z > 0 (``w >= eps``; fisheye theta = atan(r / z)), so their
#: grids stop at 89 degrees.
COLMAP_CASES = [
    ("pinhole", "PINHOLE", [500.0, 510.0, _c(639.5), _c(479.5)],
     "pinhole", [500.0, 510.0, 639.5, 479.5], (960, 1280), 89.0),
    ("simple_pinhole", "SIMPLE_PINHOLE", [500.0, _c(320.2), _c(240.9)],
     "pinhole", [500.0, 500.0, 320.2, 240.9], (480, 640), 89.0),
    # SIMPLE_FISHEYE / FISHEYE: "equidistant (theta = r)" (models.h), no distortion.
    ("simple_fisheye", "SIMPLE_FISHEYE", [310.0, _c(640.0), _c(480.0)],
     "equidistant", [310.0, 310.0, 640.0, 480.0], (960, 1280), 89.0),
    ("fisheye", "FISHEYE", [310.0, 305.0, _c(641.3), _c(479.1)],
     "equidistant", [310.0, 305.0, 641.3, 479.1], (960, 1280), 89.0),
    # OPENCV_FISHEYE is cv2.fisheye: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8).
    *[(f"opencv_fisheye/{c[0]}", "OPENCV_FISHEYE", [c[1], c[2], _c(c[3]), _c(c[4]), *c[5]],
       "kannala_brandt", [c[1], c[2], c[3], c[4], *c[5]], c[6], 89.0) for c in FISHEYE_SETS],
    # RADIAL_FISHEYE (f, cx, cy, k1, k2) and SIMPLE_RADIAL_FISHEYE (f, cx, cy, k): the same
    # polynomial truncated, one focal length.
    ("radial_fisheye", "RADIAL_FISHEYE", [320.0, _c(640.0), _c(480.0), 0.02, -0.004],
     "kannala_brandt", [320.0, 320.0, 640.0, 480.0, 0.02, -0.004, 0.0, 0.0], (960, 1280), 89.0),
    ("simple_radial_fisheye", "SIMPLE_RADIAL_FISHEYE", [320.0, _c(640.0), _c(480.0), -0.03],
     "kannala_brandt", [320.0, 320.0, 640.0, 480.0, -0.03, 0.0, 0.0, 0.0], (960, 1280), 89.0),
    # THIN_PRISM_FISHEYE with p1 = p2 = sx1 = sy1 = 0 is OPENCV_FISHEYE; its order is
    # fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1.
    ("thin_prism_fisheye", "THIN_PRISM_FISHEYE",
     [285.72, 286.11, _c(640.31), _c(481.17), -0.0134, 0.0513, 0.0, 0.0, -0.0437, 0.0089, 0, 0],
     "kannala_brandt", [285.72, 286.11, 640.31, 481.17, -0.0134, 0.0513, -0.0437, 0.0089],
     (960, 1280), 89.0),
    # OPENCV (fx, fy, cx, cy, k1, k2, p1, p2) is pinhole + radial-tangential distortion of x / z:
    # the unified model with xi = 0 (Mei's distortion acts on the same normalised plane). Swept
    # to 60 degrees, what such a lens sees: at 89 degrees k2 (x / z)^5 puts the pixel at 1e10 px,
    # where float64 rounding alone is 1e-6 px.
    ("opencv", "OPENCV", [400.0, 402.0, _c(640.5), _c(479.8), -0.28, 0.07, 1e-3, -5e-4],
     "unified", [400.0, 402.0, 640.5, 479.8, 0.0, -0.28, 0.07, 1e-3, -5e-4], (960, 1280), 60.0),
    ("simple_radial", "SIMPLE_RADIAL", [600.0, _c(640.0), _c(480.0), -0.1],
     "unified", [600.0, 600.0, 640.0, 480.0, 0.0, -0.1, 0.0, 0.0, 0.0], (960, 1280), 60.0),
    # EUCM: same parameters, same order (Khomenko et al.).
    ("eucm", "EUCM", [350.0, 352.0, _c(640.0), _c(480.0), 0.6, 1.1],
     "eucm", [350.0, 352.0, 640.0, 480.0, 0.6, 1.1], (960, 1280), 89.0),
    ("eucm_low_alpha", "EUCM", [420.0, 420.0, _c(639.5), _c(479.5), 0.3, 0.8],
     "eucm", [420.0, 420.0, 639.5, 479.5, 0.3, 0.8], (960, 1280), 89.0),
    # EUCM with beta = 1 is the unified model: xi = alpha / (1 - alpha), f_unified = f / (1 - a).
    ("eucm_as_unified", "EUCM", [350.0, 352.0, _c(640.0), _c(480.0), 0.6, 1.0],
     "unified", [350.0 / 0.4, 352.0 / 0.4, 640.0, 480.0, 0.6 / 0.4, 0.0, 0.0, 0.0, 0.0],
     (960, 1280), 89.0),
]


def _colmap_camera(model: str, params, size):
    h, w = size
    cam = pycolmap.Camera(model=model, width=w, height=h, params=params)
    assert cam.model_name == model and len(cam.params) == len(params)
    return cam


@pytest.mark.parametrize("case", COLMAP_CASES, ids=[c[0] for c in COLMAP_CASES])
def test_project_matches_pycolmap(case):
    name, cmodel, cparams, model, params, size, max_deg = case
    cam = _colmap_camera(cmodel, cparams, size)
    points = sphere_grid(max_deg)
    colmap_px = cam.img_from_cam(points) - 0.5  # NaN where COLMAP fails (z < eps)
    px, valid = ours_project(model, points, params)
    both = valid & np.isfinite(colmap_px).all(-1)
    err = np.abs(px - colmap_px).max(-1)[both]
    compared = int(both.sum())
    report(f"{model}/{name} vs pycolmap {cmodel}.img_from_cam", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    assert compared > 0


@pytest.mark.parametrize("case", COLMAP_CASES, ids=[c[0] for c in COLMAP_CASES])
def test_unproject_matches_pycolmap(case):
    name, cmodel, cparams, model, params, size, max_deg = case
    cam = _colmap_camera(cmodel, cparams, size)
    points = sphere_grid(max_deg)
    _, valid = ours_project(model, points, params)
    colmap_px = cam.img_from_cam(points)
    keep = valid & np.isfinite(colmap_px).all(-1)  # both valid, as in the projection test
    colmap_px = colmap_px[keep]
    # cam_ray_from_img: the unit ray of cam_from_img's (x / z, y / z); NaN where COLMAP's
    # iterative undistortion does not converge.
    colmap_rays = cam.cam_ray_from_img(colmap_px)
    rays, ok = ours_unproject(model, colmap_px - 0.5, params)
    both = ok & np.isfinite(colmap_rays).all(-1)
    err = angle_between(rays[both], colmap_rays[both])
    compared = int(both.sum())
    report(f"{model}/{name} vs pycolmap {cmodel}.cam_ray_from_img", compared, rad=err.max())
    assert err.max() <= COLMAP_RAY_TOL
    assert compared > 0


def _equirectangular(size):
    """COLMAP's EQUIRECTANGULAR (params w, h: a full 360 x 180 panorama) and ours."""
    h, w = size
    cam = _colmap_camera("EQUIRECTANGULAR", [float(w), float(h)], size)
    # COLMAP: x = (lon / 2 pi + 1/2) W, lon = atan2(x, z); y = (1/2 - phi / pi) H with the
    # elevation phi = atan2(-y, |(x, z)|) positive *up*. The two sign flips (phi = -lat, and rows
    # growing downwards) cancel: y_colmap = (1/2 + lat / pi) H with our lat = atan2(y, |(x, z)|)
    # positive down. So fx = W / 2 pi, fy = H / pi, and the centre (W/2, H/2) in COLMAP's pixels
    # is ((W - 1) / 2, (H - 1) / 2) in ours: no axis flip, only the half-pixel shift.
    params = [w / (2 * math.pi), h / math.pi, (w - 1) / 2, (h - 1) / 2]
    return cam, params


def test_equirectangular_project_matches_pycolmap():
    cam, params = _equirectangular((512, 1024))
    points = sphere_grid(180.0, step_deg=1.0, n_azimuth=36)  # the whole sphere
    # Longitude is undefined at the poles (+-y): COLMAP takes atan2 of two roundoff-sized numbers
    # there, we take 0. Compare away from them.
    off_pole = np.hypot(points[:, 0], points[:, 2]) > 1e-9 * np.linalg.norm(points, axis=-1)
    colmap_px = cam.img_from_cam(points, check_cheirality=False) - 0.5
    px, valid = ours_project("equirectangular", points, params)
    both = valid & off_pole & np.isfinite(colmap_px).all(-1)
    err = np.abs(px - colmap_px).max(-1)[both]
    compared = int(both.sum())
    report("equirectangular vs pycolmap EQUIRECTANGULAR.img_from_cam", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    assert (off_axis_angle(points[both]) > math.radians(170)).any()  # behind the camera too
    assert compared > 0


def test_equirectangular_unproject_matches_pycolmap():
    size = (512, 1024)
    cam, params = _equirectangular(size)
    # Every pixel centre of a subsampled image, and the image edges (lon = +-pi, lat = +-pi/2).
    u = np.concatenate((np.arange(0, size[1], 7.0), [-0.5, size[1] - 0.5]))
    v = np.concatenate((np.arange(0, size[0], 5.0), [-0.5, size[0] - 0.5]))
    uu, vv = np.meshgrid(u, v, indexing="xy")
    pixels = np.stack((uu.ravel(), vv.ravel()), -1)
    colmap_rays = cam.cam_ray_from_img(pixels + 0.5)
    rays, ok = ours_unproject("equirectangular", pixels, params)
    both = ok & np.isfinite(colmap_rays).all(-1)
    err = angle_between(rays[both], colmap_rays[both])
    compared = int(both.sum())
    report("equirectangular vs pycolmap EQUIRECTANGULAR.cam_ray_from_img", compared,
           rad=err.max())
    assert err.max() <= COLMAP_RAY_TOL
    assert (rays[both][:, 2] < -0.99).any()  # the back of the sphere is compared
    assert compared > 0


# --------------------------------------------------------------------------------------------
# 4. Conversions to and from OpenCV
# --------------------------------------------------------------------------------------------

def _random_intrinsics(rng) -> np.ndarray:
    fx, fy = rng.uniform(200, 900, 2)
    cx, cy = rng.uniform(300, 700, 2)
    return k_matrix(fx, fy, cx, cy)


@pytest.mark.parametrize("d_shape", [(4,), (1, 4), (4, 1)])
def test_opencv_fisheye_round_trip_is_exact(d_shape):
    rng = np.random.default_rng(7)
    compared = 0
    for _ in range(5):
        K = _random_intrinsics(rng)
        D = rng.normal(0, 0.05, 4)
        camera = ot.Camera.from_opencv_fisheye(K, D.reshape(d_shape), (960, 1280))
        assert camera.model.name == "kannala_brandt" and camera.params.dtype == f64
        K2, D2 = camera.to_opencv_fisheye()
        assert np.array_equal(K2, K) and D2.shape == (4,) and np.array_equal(D2, D)
        # And the camera means what cv2.fisheye means by (K, D).
        points = sphere_grid(80.0, step_deg=10.0, n_azimuth=8)
        cv_px = _cv_fisheye_project(points, K2, D2)
        px, valid = camera.model.project(torch.from_numpy(points), camera.params)
        assert np.abs(px.numpy() - cv_px)[valid.numpy()].max() <= PIXEL_TOL
        compared += int(valid.sum())
    assert compared > 0


@pytest.mark.skipif(not hasattr(cv2, "omnidir"), reason="needs opencv-contrib (cv2.omnidir)")
@pytest.mark.parametrize("xi_value", [0.0, 0.8, 1.0, 1.9])
def test_opencv_omnidir_round_trip_is_exact(xi_value):
    rng = np.random.default_rng(11)
    compared = 0
    for xi_shape, d_shape in (((1,), (1, 4)), ((), (4,)), ((1, 1), (4, 1))):
        K = _random_intrinsics(rng)
        D = rng.normal(0, 0.02, 4)
        xi = np.full(xi_shape, xi_value + rng.uniform(0, 1e-3))
        camera = ot.Camera.from_opencv_omnidir(K, D.reshape(d_shape), xi, (960, 1280))
        assert camera.model.name == "unified" and camera.params.dtype == f64
        K2, D2, xi2 = camera.to_opencv_omnidir()
        assert np.array_equal(K2, K)
        assert D2.shape == (1, 4) and np.array_equal(D2.ravel(), D)
        assert xi2.shape == (1,) and np.array_equal(xi2, xi.ravel())
        points = sphere_grid(80.0, step_deg=10.0, n_azimuth=8)
        cv_px = _cv_omnidir_project(points, K2, D2, float(xi2[0]))
        px, valid = camera.model.project(torch.from_numpy(points), camera.params)
        assert np.abs(px.numpy() - cv_px)[valid.numpy()].max() <= PIXEL_TOL
        compared += int(valid.sum())
    assert compared > 0


def test_opencv_skew_round_trips():
    """OpenCV's skew ``K[0, 1]`` is the optional ``s`` (omnidir's ``s``; fisheye's ``fx alpha``,
    as ``cv2.fisheye.calibrate`` returns it): read, written back, and projecting as OpenCV's
    own ``projectPoints`` does (``cv2.fisheye`` takes ``alpha = K[0, 1] / K[0, 0]``)."""
    K = k_matrix(300.0, 310.0, 640.0, 480.0)
    K[0, 1] = 2.5
    D = np.array([0.01, -0.005, 0.001, 0.0])
    points = sphere_grid(80.0, step_deg=10.0, n_azimuth=8)
    fisheye = ot.Camera.from_opencv_fisheye(K, D, (960, 1280), fov=math.radians(170))
    assert fisheye.param_names[-1] == "s" and float(fisheye.params[-1]) == 2.5
    K2, D2 = fisheye.to_opencv_fisheye()
    assert np.array_equal(K2, K) and np.array_equal(D2, D)
    cv_px, _ = cv2.fisheye.projectPoints(points[:, None], np.zeros(3), np.zeros(3), K, D,
                                         alpha=K[0, 1] / K[0, 0])
    px, valid = fisheye.model.project(torch.from_numpy(points), fisheye.params)
    assert np.abs(px.numpy() - cv_px[:, 0])[valid.numpy()].max() <= PIXEL_TOL
    if hasattr(cv2, "omnidir"):
        omni = ot.Camera.from_opencv_omnidir(K, D, np.array([0.9]), (960, 1280))
        K3, D3, _ = omni.to_opencv_omnidir()
        assert np.array_equal(K3, K) and np.array_equal(D3.ravel(), D)
        cv_px = _cv_omnidir_project(points, K, D[None], 0.9)
        px, valid = omni.model.project(torch.from_numpy(points), omni.params)
        assert np.abs(px.numpy() - cv_px)[valid.numpy()].max() <= PIXEL_TOL


def test_opencv_fisheye_export_refuses_what_it_folds():
    """``cv2.fisheye`` folds rays at 90 degrees off the axis (``atan(r / z)``): a 190-degree
    camera is refused, unless accepted; one restricted below 180 degrees is not."""
    params = torch.tensor([200.0, 200.0, 639.5, 479.5, 0, 0, 0, 0], dtype=f64)
    wide = ot.Camera("kannala_brandt", params, (960, 1280))
    with pytest.raises(ValueError, match="90 deg"):
        wide.to_opencv_fisheye()
    assert wide.to_opencv_fisheye(accept_fov=True)[0][0, 0] == 200.0
    narrow = ot.Camera("kannala_brandt", params, (960, 1280), fov=math.radians(170))
    assert narrow.to_opencv_fisheye()[0][0, 0] == 200.0


# --------------------------------------------------------------------------------------------
# 5. fov, division, opencv, thin_prism_fisheye, fisheye624 (issue 34)
# --------------------------------------------------------------------------------------------

#: Tolerance of the closed-form and Newton inverses of the new models against pycolmap and
#: OpenCV (rad): the issue's 1e-6 rad. Measured below 1e-9 rad (COLMAP's iterative undistortion
#: stops at steps of 1e-5, COLMAP_RAY_TOL above).
NEW_RAY_TOL = 1e-6

#: (id, COLMAP model, COLMAP params, our model, our params, image size (H, W), grid max angle).
#: The COLMAP parameter orders are ``pycolmap.Camera(...).params_info``; COLMAP's perspective
#: and fisheye models divide by z, so these grids stop at 89 degrees (the division model past 90
#: degrees and fisheye624 against Project Aria are compared below).
NEW_COLMAP_CASES = [
    # FOV with omega^2 >= 1e-4 (COLMAP's exact branch; its series below is the next test)
    ("fov", "FOV", [500.0, 505.0, _c(319.5), _c(239.5), 0.9],
     "fov", [500.0, 505.0, 319.5, 239.5, 0.9], (480, 640), 89.0),
    ("fov_wide", "FOV", [300.0, 300.0, _c(640.2), _c(479.9), 1.6],
     "fov", [300.0, 300.0, 640.2, 479.9, 1.6], (960, 1280), 89.0),
    ("division_barrel", "DIVISION", [400.0, 402.0, _c(320.0), _c(240.0), -0.3],
     "division", [400.0, 402.0, 320.0, 240.0, -0.3], (480, 640), 89.0),
    ("division_pincushion", "DIVISION", [420.0, 420.0, _c(319.5), _c(239.5), 0.3],
     "division", [420.0, 420.0, 319.5, 239.5, 0.3], (480, 640), 89.0),
    # OPENCV: the first 8 of our 16
    ("opencv/OPENCV", "OPENCV", [400.0, 402.0, _c(640.5), _c(479.8), -0.28, 0.07, 1e-3, -5e-4],
     "opencv", [400.0, 402.0, 640.5, 479.8, -0.28, 0.07, 1e-3, -5e-4] + [0.0] * 8,
     (960, 1280), 60.0),
    # FULL_OPENCV: the first 12 (k1 k2 p1 p2 k3 k4 k5 k6, the rational model)
    ("opencv/FULL_OPENCV", "FULL_OPENCV",
     [600.0, 601.0, _c(640.0), _c(360.0), 0.6, -0.05, 1e-3, -5e-4, 0.01, 0.9, 0.02, 0.003],
     "opencv", [600.0, 601.0, 640.0, 360.0, 0.6, -0.05, 1e-3, -5e-4, 0.01, 0.9, 0.02, 0.003]
     + [0.0] * 4, (720, 1280), 60.0),
    ("thin_prism_fisheye", "THIN_PRISM_FISHEYE",
     [285.72, 286.11, _c(640.31), _c(481.17), -0.0134, 0.0513, 1e-3, -2e-3, -0.0437, 0.0089,
      5e-4, -3e-4],
     "thin_prism_fisheye", [285.72, 286.11, 640.31, 481.17, -0.0134, 0.0513, 1e-3, -2e-3,
                            -0.0437, 0.0089, 5e-4, -3e-4], (960, 1280), 89.0),
    ("fisheye624", "RAD_TAN_THIN_PRISM_FISHEYE",
     [240.0, 241.0, _c(320.2), _c(239.6), -0.02, 0.003, -2e-4, 1e-5, 1e-6, -1e-7, 4e-4, -3e-4,
      2e-4, 1e-5, -3e-4, 2e-5],
     "fisheye624", [240.0, 241.0, 320.2, 239.6, -0.02, 0.003, -2e-4, 1e-5, 1e-6, -1e-7, 4e-4,
                    -3e-4, 2e-4, 1e-5, -3e-4, 2e-5], (480, 640), 89.0),
    # an Aria-like lens whose radius folds near 119 degrees, strongly distorted
    ("fisheye624_strong", "RAD_TAN_THIN_PRISM_FISHEYE",
     [240.0, 241.0, _c(320.0), _c(240.0), 0.38, -0.42, 0.34, -0.18, 0.05, -0.005, 1e-3, -5e-4,
      2e-4, 1e-5, -3e-4, 2e-5],
     "fisheye624", [240.0, 241.0, 320.0, 240.0, 0.38, -0.42, 0.34, -0.18, 0.05, -0.005, 1e-3,
                    -5e-4, 2e-4, 1e-5, -3e-4, 2e-5], (480, 640), 89.0),
]


@pytest.mark.parametrize("case", NEW_COLMAP_CASES, ids=[c[0] for c in NEW_COLMAP_CASES])
def test_new_models_project_match_pycolmap(case):
    name, cmodel, cparams, model, params, size, max_deg = case
    if not hasattr(pycolmap.CameraModelId, cmodel):
        pytest.skip(f"this pycolmap has no {cmodel}")
    test_project_matches_pycolmap(case)


@pytest.mark.parametrize("case", NEW_COLMAP_CASES, ids=[c[0] for c in NEW_COLMAP_CASES])
def test_new_models_unproject_match_pycolmap(case):
    name, cmodel, cparams, model, params, size, max_deg = case
    if not hasattr(pycolmap.CameraModelId, cmodel):
        pytest.skip(f"this pycolmap has no {cmodel}")
    cam = _colmap_camera(cmodel, cparams, size)
    points = sphere_grid(max_deg)
    _, valid = ours_project(model, points, params)
    colmap_px = cam.img_from_cam(points)
    keep = valid & np.isfinite(colmap_px).all(-1) & in_image(colmap_px - 0.5, size)
    colmap_px = colmap_px[keep]
    colmap_rays = cam.cam_ray_from_img(colmap_px)
    rays, ok = ours_unproject(model, colmap_px - 0.5, params)
    both = ok & np.isfinite(colmap_rays).all(-1)
    err = angle_between(rays[both], colmap_rays[both])
    truth = angle_between(rays[both], unit(points[keep][both]))
    compared = int(both.sum())
    report(f"{model}/{name} vs pycolmap {cmodel}.cam_ray_from_img (ours vs truth "
           f"{truth.max():.1e})", compared, rad=err.max())
    assert err.max() <= NEW_RAY_TOL
    assert truth.max() <= 1e-9
    assert compared > 0


def test_division_past_90_degrees_matches_pycolmap():
    """COLMAP's DIVISION projection has no cheirality test of its own: with k < 0 its ray
    ``(xd, yd, 1 + k rd^2)`` points behind the camera beyond ``rd^2 = -1 / k``, and both sides
    project the whole sphere up to 180 degrees (pixels within a few image sizes compared)."""
    size = (480, 640)
    cam = _colmap_camera("DIVISION", [400.0, 402.0, _c(320.0), _c(240.0), -0.3], size)
    params = [400.0, 402.0, 320.0, 240.0, -0.3]
    points = sphere_grid(179.0)
    colmap_px = cam.img_from_cam(points, check_cheirality=False) - 0.5
    px, valid = ours_project("division", points, params)
    near = np.isfinite(colmap_px).all(-1) & (np.abs(colmap_px - [320, 240]).max(-1) < 4 * 640)
    both = valid & near
    err = np.abs(px - colmap_px).max(-1)[both]
    compared = int(both.sum())
    report("division past 90 deg vs pycolmap DIVISION.img_from_cam (to "
           f"{math.degrees(off_axis_angle(points[both]).max()):.1f} deg)", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    assert (off_axis_angle(points[both]) > math.radians(120)).any()
    assert compared > 0


def test_fov_small_omega_colmap_series_is_its_inverse_s():
    """Below omega^2 = 1e-4 COLMAP's FOV projection uses ``1 - omega^2 / 12 + omega^2 r^2 / 3``,
    the series of its *unprojection*'s factor; the projection's own is ``1 + omega^2 / 12 -
    omega^2 r^2 / 3``. So there COLMAP's projection is not the inverse of its unprojection,
    ours is, and ours matches COLMAP's unprojection (whose series is right) and COLMAP's exact
    projection formula written out here."""
    omega, size = 0.005, (480, 640)
    cparams = [400.0, 401.0, _c(320.2), _c(239.7), omega]
    params = [400.0, 401.0, 320.2, 239.7, omega]
    cam = _colmap_camera("FOV", cparams, size)
    points = sphere_grid(60.0)
    px, valid = ours_project("fov", points, params)
    xy = points[:, :2] / points[:, 2:]
    r = np.linalg.norm(xy, axis=-1, keepdims=True)
    safe = np.where(r > 0, r, 1.0)
    factor = np.where(r > 0, np.arctan(2 * safe * math.tan(omega / 2)) / (safe * omega), 1.0)
    exact = xy * factor * [400.0, 401.0] + [320.2, 239.7]
    assert np.abs(px - exact)[valid].max() <= PIXEL_TOL
    # COLMAP's projection is off by the sign of its series: omega^2 (r^2 / 3 - 1/12) r f / 2
    colmap_px = cam.img_from_cam(points) - 0.5
    assert np.abs(colmap_px - px)[valid].max() > 1e-3
    # COLMAP's unprojection of our pixels gives the points back, ours too
    colmap_rays = cam.cam_ray_from_img(px[valid] + 0.5)
    rays, ok = ours_unproject("fov", px[valid], params)
    err = angle_between(rays[ok], colmap_rays[ok])
    truth = angle_between(colmap_rays, unit(points[valid]))
    report("fov omega=0.005 vs pycolmap FOV.cam_ray_from_img", int(ok.sum()), rad=err.max())
    assert err.max() <= NEW_RAY_TOL and truth.max() <= NEW_RAY_TOL
    assert int(ok.sum()) > 0


#: (id, params (16), image size): OpenCV's 12 coefficients k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4.
CV_OPENCV_SETS = [
    ("brown", [500.0, 502.0, 320.3, 239.7, -0.28, 0.07, 1e-3, -5e-4] + [0.0] * 8, (480, 640)),
    ("rational_thin_prism", [600.0, 601.0, 640.0, 360.0, 0.6, -0.05, 1e-3, -5e-4, 0.01, 0.9,
                             0.02, 0.003, 1e-3, -2e-4, 5e-4, 1e-4], (720, 1280)),
    ("folding", [350.0, 352.0, 320.0, 240.0, -0.35, 0.05] + [0.0] * 10, (480, 640)),
]


def _cv_opencv(params):
    K = k_matrix(*params[:4])
    return K, np.array(params[4:16], dtype=np.float64)


@pytest.mark.parametrize("case", CV_OPENCV_SETS, ids=[c[0] for c in CV_OPENCV_SETS])
def test_opencv_project_matches_cv2_project_points(case):
    _, params, size = case
    K, D = _cv_opencv(params)
    points = sphere_grid(70.0)
    cv_px, _ = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    cv_px = cv_px.reshape(-1, 2)
    px, valid = ours_project("opencv", points, params)
    both = valid & in_image(cv_px, size)
    err = np.abs(px - cv_px).max(-1)[both]
    compared = int(both.sum())
    report(f"opencv/{case[0]} vs cv2.projectPoints (12 coefficients)", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    assert compared > 0


@pytest.mark.parametrize("case", CV_OPENCV_SETS, ids=[c[0] for c in CV_OPENCV_SETS])
def test_opencv_unproject_matches_cv2_undistort_points_iter(case):
    _, params, size = case
    K, D = _cv_opencv(params)
    points = sphere_grid(70.0)
    _, valid = ours_project("opencv", points, params)
    cv_px, _ = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    cv_px = cv_px.reshape(-1, 2)
    keep = valid & in_image(cv_px, size)
    pixels = cv_px[keep]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    # OpenCV 4's undistortPointsIter is OpenCV 5's undistortPoints with criteria
    undistort = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)
    cv_xy = undistort(pixels.reshape(-1, 1, 2), K, D, R=np.eye(3), P=np.eye(3),
                      criteria=criteria).reshape(-1, 2)
    # OpenCV's fixed-point iteration does not flag non-convergence: its own forward model checks
    back, _ = cv2.projectPoints(plane_rays(cv_xy).reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                K, D)
    converged = np.abs(back.reshape(-1, 2) - pixels).max(-1) <= CV_CONVERGED_PX
    rays, ok = ours_unproject("opencv", pixels, params)
    both = converged & ok
    err = angle_between(rays[both], plane_rays(cv_xy[both]))
    compared = int(both.sum())
    report(f"opencv/{case[0]} vs cv2.{undistort.__name__} ({int((~converged).sum())} not "
           "converged by OpenCV)", compared, rad=err.max())
    assert err.max() <= NEW_RAY_TOL
    assert angle_between(rays, unit(points[keep])).max() <= 1e-9
    assert compared > 0


def _aria():
    calibration = pytest.importorskip("projectaria_tools.core.calibration")
    return calibration


#: Project Aria's FISHEYE624 has one focal length: params f, cx, cy, k0..k5, p0, p1, s0..s3.
ARIA_SETS = [
    ("mild", [240.0, 320.2, 239.6, -0.02, 0.003, -2e-4, 1e-5, 1e-6, -1e-7, 4e-4, -3e-4, 2e-4,
              1e-5, -3e-4, 2e-5], (480, 640)),
    ("strong", [240.0, 320.0, 240.0, 0.38, -0.42, 0.34, -0.18, 0.05, -0.005, 1e-3, -5e-4, 2e-4,
                1e-5, -3e-4, 2e-5], (480, 640)),
]


def _ours_624(aria_params):
    return [aria_params[0], *aria_params]


@pytest.mark.parametrize("case", ARIA_SETS, ids=[c[0] for c in ARIA_SETS])
def test_fisheye624_project_matches_project_aria(case):
    """Project Aria's FisheyeRadTanThinPrism, in front of the camera: behind it (z < 0) Aria's
    ``project`` folds the point onto the front half (91 degrees lands opposite 89), where ours
    goes on past 90 degrees (``atan2``; checked by the round trips of tests/test_cameras.py)."""
    calibration = _aria()
    _, aparams, size = case
    proj = calibration.CameraProjection(calibration.CameraModelType.FISHEYE624,
                                        np.array(aparams, dtype=np.float64))
    params = _ours_624(aparams)
    points = sphere_grid(89.0, step_deg=1.0)
    px, valid = ours_project("fisheye624", points, params)
    aria = np.array([np.asarray(proj.project(p)).ravel() for p in points[valid]])
    near = np.isfinite(aria).all(-1)
    err = np.abs(px[valid][near] - aria[near]).max(-1)
    compared = int(near.sum())
    report(f"fisheye624/{case[0]} vs projectaria_tools FISHEYE624.project (to "
           f"{math.degrees(off_axis_angle(points[valid][near]).max()):.1f} deg)", compared,
           px=err.max())
    assert err.max() <= PIXEL_TOL
    assert compared > 0


def test_project_aria_folds_behind_the_camera_where_fisheye624_does_not():
    """The reason the comparison above stops at 90 degrees, pinned: Aria maps a point at 91
    degrees next to the image of its mirror image at 89 degrees' opposite azimuth, ours maps
    it beyond the 90-degree circle."""
    calibration = _aria()
    aparams = ARIA_SETS[0][1]
    proj = calibration.CameraProjection(calibration.CameraModelType.FISHEYE624,
                                        np.array(aparams, dtype=np.float64))
    params = _ours_624(aparams)
    t89, t91 = math.radians(89.0), math.radians(91.0)
    p89 = np.array([math.sin(t89) * 0.6, math.sin(t89) * 0.8, math.cos(t89)])
    p91 = np.array([math.sin(t91) * 0.6, math.sin(t91) * 0.8, math.cos(t91)])
    centre = np.array(params[2:4])
    aria89, aria91 = (np.asarray(proj.project(p)).ravel() - centre for p in (p89, p91))
    assert float(np.dot(aria89, aria91)) < 0            # Aria: the opposite side
    ours = ours_project("fisheye624", np.stack((p89, p91)), params)[0] - centre
    assert float(np.dot(ours[0], ours[1])) > 0          # ours: the same side, farther out
    assert np.linalg.norm(ours[1]) > np.linalg.norm(ours[0])


@pytest.mark.parametrize("case", ARIA_SETS, ids=[c[0] for c in ARIA_SETS])
def test_fisheye624_unproject_matches_project_aria(case):
    """Aria's unprojection returns ``(x / z, y / z, 1)``: compared in front of the camera."""
    calibration = _aria()
    _, aparams, size = case
    proj = calibration.CameraProjection(calibration.CameraModelType.FISHEYE624,
                                        np.array(aparams, dtype=np.float64))
    params = _ours_624(aparams)
    points = sphere_grid(85.0, step_deg=1.0)
    px, valid = ours_project("fisheye624", points, params)
    keep = valid & in_image(px, size)
    pixels = px[keep]
    aria = plane_rays(np.array([np.asarray(proj.unproject(p)).ravel()[:2] for p in pixels]))
    rays, ok = ours_unproject("fisheye624", pixels, params)
    finite = np.isfinite(aria).all(-1)
    both = ok & finite
    err = angle_between(rays[both], aria[both])
    compared = int(both.sum())
    report(f"fisheye624/{case[0]} vs projectaria_tools FISHEYE624.unproject", compared,
           rad=err.max())
    assert err.max() <= NEW_RAY_TOL
    assert compared > 0


@pytest.mark.parametrize("case", CV_OPENCV_SETS, ids=[c[0] for c in CV_OPENCV_SETS])
def test_opencv_project_matches_kornia_distort_points(case):
    """kornia's Brown-Conrady (``kornia.geometry.calibration.distort_points``, 12 coefficients
    in OpenCV's order) on the pinhole pixels of the same points."""
    calibration = pytest.importorskip("kornia.geometry.calibration")
    _, params, size = case
    p = torch.tensor(params, dtype=f64)
    K = torch.from_numpy(k_matrix(*params[:4]))
    points = torch.from_numpy(sphere_grid(70.0))
    pinhole = points[:, :2] / points[:, 2:] * p[:2] + p[2:4]
    kornia_px = calibration.distort_points(pinhole, K, p[4:16]).numpy()
    px, valid = ours_project("opencv", points.numpy(), params)
    both = valid & in_image(kornia_px, size)
    err = np.abs(px - kornia_px).max(-1)[both]
    compared = int(both.sum())
    report(f"opencv/{case[0]} vs kornia distort_points", compared, px=err.max())
    assert err.max() <= PIXEL_TOL
    assert compared > 0
