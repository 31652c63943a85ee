"""Writers for the files other tools read (issue 18, item 3): ot.cameras.write_camera,
Camera.save and ``omniscape-torch convert-model --format``.

Each file is read back by the tool's own reader (cv2.FileStorage with cv2.fisheye / cv2.omnidir,
pycolmap) or parsed with yaml / json and projected by the small numpy models below, written from
Kalibr's aslam_cv (``OmniProjection``, ``DoubleSphereProjection``, ``ExtendedUnifiedProjection``,
``PinholeProjection`` with ``EquidistantDistortion`` / ``RadialTangentialDistortion``) and basalt's
camera headers (``kannala_brandt_camera4``, ``double_sphere_camera``, ``extended_camera``,
``unified_camera``), never by this package's projections. The file must reproduce the camera's
pixels for rays spread over its valid field of view.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pycolmap
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.cameras import FORMATS, get_model, write_camera
from omniscape_torch.cameras.export import supported_models

from conftest import OCAMCALIB_FILE

D = torch.float64
SIZE = (480, 640)   # (H, W)

#: Largest pixel difference between the camera and the file read back: every number is
#: written with its shortest round-trip repr, so what is left is float64 rounding.
PIXEL_TOL = 1e-6

KB = [300.0, 300.0, 320.0, 240.0, 0.01, -0.005, 0.001, 0.0]
UNIFIED = [280.0, 285.0, 319.5, 239.5, 0.9, -0.05, 0.01, 0.001, -0.002]
UCM = [280.0, 285.0, 319.5, 239.5, 0.9, 0.0, 0.0, 0.0, 0.0]
DS = [160.0, 161.0, 319.5, 239.5, -0.2, 0.6]
EUCM = [220.0, 221.0, 320.5, 238.5, 0.6, 1.1]
PINHOLE = [400.0, 401.0, 319.5, 239.5]
FOV = [300.0, 301.0, 319.5, 239.5, 0.9]
DIVISION = [300.0, 301.0, 319.5, 239.5, -0.05]
RADTAN = [400.0, 401.0, 319.5, 239.5, -0.1, 0.01, 0.001, -0.002] + [0.0] * 8
OPENCV5 = RADTAN[:8] + [0.001] + [0.0] * 7
RATIONAL = RADTAN[:8] + [0.001, 0.02, -0.003, 0.0004] + [0.0] * 4
PRISM = RATIONAL[:12] + [0.0005, -0.0001, 0.0002, 0.0001]
TPF = [300.0, 301.0, 319.5, 239.5, 0.01, -0.005, 0.001, -0.001, 0.0002, -0.0001, 0.0005,
       -0.0005]
F624 = [300.0, 301.0, 319.5, 239.5, 0.01, -0.005, 0.001, 0.0002, -0.0001, 0.00002, 0.0005,
        -0.0005, 0.0001, 0.00002, -0.0001, 0.00001]


def _safe_load(text: str):
    """PyYAML's ``safe_load``, as Kalibr reads its files (PyYAML is not a dev dependency)."""
    return pytest.importorskip("yaml").safe_load(text)


def _takes_skew(model: str) -> bool:
    """The optional trailing skew ``s`` of kannala_brandt and unified (issue 18)."""
    m = get_model(model)
    try:
        return "s" in m.names_for(len(m.param_names) + 1)
    except ValueError:
        return False


needs_skew = pytest.mark.skipif(not (_takes_skew("kannala_brandt") and _takes_skew("unified")),
                                reason="the models do not take the skew s yet")


def _camera(model, params, size=SIZE, **kwargs):
    return ot.Camera(model, torch.tensor(params, dtype=D), size, **kwargs)


def _rays(camera) -> np.ndarray:
    """About 100 unit rays of pixel centres spread over the camera's valid area."""
    h, w = camera.image_size
    v, u = torch.meshgrid(torch.linspace(0, h - 1, 10, dtype=D),
                          torch.linspace(0, w - 1, 12, dtype=D), indexing="ij")
    rays, valid = camera.unproject(torch.stack((u, v), -1).reshape(-1, 2))
    assert int(valid.sum()) > 60
    return rays[valid].numpy()


def _ours(camera, rays: np.ndarray) -> np.ndarray:
    pixels, valid = camera.project(torch.from_numpy(rays))
    assert bool(valid.all())
    return pixels.numpy()


def _compare(camera, rays, theirs):
    ours = _ours(camera, rays)
    assert theirs.shape == ours.shape and len(ours) > 60
    assert np.abs(theirs - ours).max() < PIXEL_TOL


# --------------------------------------------------------------------------------------------
# Independent models (numpy), from the tools' sources
# --------------------------------------------------------------------------------------------

def _radtan(mx, my, k1, k2, p1, p2):
    """aslam_cv RadialTangentialDistortion::distort (the same as OpenCV's)."""
    mx2, my2, mxy = mx * mx, my * my, mx * my
    rho2 = mx2 + my2
    rad = k1 * rho2 + k2 * rho2 * rho2
    return (mx + mx * rad + 2 * p1 * mxy + p2 * (rho2 + 2 * mx2),
            my + my * rad + 2 * p2 * mxy + p1 * (rho2 + 2 * my2))


def _kb_scale(theta, r, k):
    thetad = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    return np.where(r > 1e-8, thetad / np.where(r > 1e-8, r, 1.0), 1.0)


def kalibr_project(cam: dict, X: np.ndarray) -> np.ndarray:
    """Kalibr's camchain entry ``cam`` applied to points ``X (N, 3)``."""
    x, y, z = X.T
    d = np.linalg.norm(X, axis=-1)
    intr, coeffs = cam["intrinsics"], cam["distortion_coeffs"]
    model, dist = cam["camera_model"], cam["distortion_model"]
    if model == "pinhole":               # [fu, fv, pu, pv]
        (fu, fv, pu, pv), mx, my = intr, x / z, y / z
    elif model == "omni":                # [xi, fu, fv, pu, pv]
        xi, fu, fv, pu, pv = intr
        mx, my = x / (z + xi * d), y / (z + xi * d)
    elif model == "ds":                  # [xi, alpha, fu, fv, pu, pv]
        xi, alpha, fu, fv, pu, pv = intr
        k = xi * d + z
        den = alpha * np.sqrt(x * x + y * y + k * k) + (1 - alpha) * k
        mx, my = x / den, y / den
    else:                                # eucm: [alpha, beta, fu, fv, pu, pv]
        assert model == "eucm"
        alpha, beta, fu, fv, pu, pv = intr
        den = alpha * np.sqrt(beta * (x * x + y * y) + z * z) + (1 - alpha) * z
        mx, my = x / den, y / den
    if dist == "equidistant":            # on the pinhole's normalised plane: theta = atan(r)
        r = np.hypot(mx, my)
        scale = _kb_scale(np.arctan(r), r, coeffs)
        mx, my = mx * scale, my * scale
    elif dist == "radtan":
        mx, my = _radtan(mx, my, *coeffs)
    elif dist == "fov":                  # aslam_cv FovDistortion::distort
        (w,), r = coeffs, np.hypot(mx, my)
        factor = np.arctan(2 * np.tan(w / 2) * r) / (w * np.where(r > 1e-8, r, 1.0))
        factor = np.where(r > 1e-8, factor, 2 * np.tan(w / 2) / w)
        mx, my = mx * factor, my * factor
    else:
        assert dist == "none" and coeffs == []
    return np.stack((fu * mx + pu, fv * my + pv), -1)


def basalt_project(calib: dict, X: np.ndarray) -> np.ndarray:
    """basalt's first camera of a calibration JSON applied to points ``X (N, 3)``."""
    cam = calib["value0"]["intrinsics"][0]
    kind, q = cam["camera_type"], cam["intrinsics"]
    x, y, z = X.T
    d = np.linalg.norm(X, axis=-1)
    if kind == "pinhole":
        mx, my = x / z, y / z
    elif kind == "kb4":                  # theta = atan2(r, z)
        r = np.hypot(x, y)
        scale = _kb_scale(np.arctan2(r, z), r, [q["k1"], q["k2"], q["k3"], q["k4"]])
        mx, my = x * np.where(r > 1e-8, scale, 1 / z), y * np.where(r > 1e-8, scale, 1 / z)
    elif kind == "ucm":
        den = q["alpha"] * d + (1 - q["alpha"]) * z
        mx, my = x / den, y / den
    elif kind == "fov":                  # fov_camera.hpp: rd = atan2(2 r tan(w / 2), z) / (r w)
        r = np.hypot(x, y)
        rd = np.arctan2(2 * r * np.tan(q["w"] / 2), z) / (np.where(r > 1e-8, r, 1.0) * q["w"])
        rd = np.where(r > 1e-8, rd, 2 * np.tan(q["w"] / 2) / q["w"] / z)
        mx, my = x * rd, y * rd
    elif kind == "ds":
        k = q["xi"] * d + z
        den = q["alpha"] * np.sqrt(x * x + y * y + k * k) + (1 - q["alpha"]) * k
        mx, my = x / den, y / den
    else:
        assert kind == "eucm"
        den = q["alpha"] * np.sqrt(q["beta"] * (x * x + y * y) + z * z) + (1 - q["alpha"]) * z
        mx, my = x / den, y / den
    return np.stack((q["fx"] * mx + q["cx"], q["fy"] * my + q["cy"]), -1)


def _zeros3():
    return np.zeros(3), np.zeros(3)


def opencv_project(path, X: np.ndarray) -> np.ndarray:
    """The OpenCV YAML read by cv2.FileStorage, projected by cv2.fisheye / cv2.omnidir."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    kind = fs.getNode("camera_model").string()
    assert fs.getNode("image_width").isInt() and fs.getNode("image_height").isInt()
    pts = X.reshape(-1, 1, 3)
    if kind == "pinhole":   # cv2.calibrateCamera's names, as OpenCV's calibration sample
        K, Dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
        assert Dist.shape[0] == 1 and Dist.shape[1] in (4, 5, 8, 12, 14)
        out = cv2.projectPoints(pts, *_zeros3(), K, Dist)[0]
        fs.release()
        return out.reshape(-1, 2)
    K, Dist = fs.getNode("K").mat(), fs.getNode("D").mat()
    if kind == "fisheye":
        out = cv2.fisheye.projectPoints(pts, *_zeros3(), K, Dist, alpha=K[0, 1] / K[0, 0])[0]
    else:
        assert kind == "omnidir"
        out = cv2.omnidir.projectPoints(pts, *_zeros3(), K, fs.getNode("xi").real(), Dist)[0]
    fs.release()
    return out.reshape(-1, 2)


def orbslam3_project(path, X: np.ndarray) -> np.ndarray:
    """ORB-SLAM3 settings read by cv2.FileStorage (as ORB-SLAM3's Settings.cc does, with the
    node types it requires), projected by cv2.fisheye (KannalaBrandt8) or as a pinhole."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("File.version").string() == "1.0"
    for key in ("Camera.width", "Camera.height", "Camera.fps", "Camera.RGB",
                "ORBextractor.nFeatures", "ORBextractor.nLevels", "ORBextractor.iniThFAST",
                "ORBextractor.minThFAST"):
        assert fs.getNode(key).isInt(), key
    for key in ("ORBextractor.scaleFactor", "Viewer.KeyFrameSize", "Viewer.ViewpointF"):
        assert fs.getNode(key).isReal(), key
    kind = fs.getNode("Camera.type").string()
    fx, fy, cx, cy = (fs.getNode(f"Camera1.{n}").real() for n in ("fx", "fy", "cx", "cy"))
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    if kind == "KannalaBrandt8":
        dist = np.array([fs.getNode(f"Camera1.k{i}").real() for i in range(1, 5)])
        out = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), *_zeros3(), K, dist)[0]
        return out.reshape(-1, 2)
    assert kind == "PinHole" and fs.getNode("Camera1.k1").empty()
    return np.stack((fx * X[:, 0] / X[:, 2] + cx, fy * X[:, 1] / X[:, 2] + cy), -1)


def colmap_camera(path):
    """cameras.txt read by pycolmap (beside empty images.txt and points3D.txt)."""
    for name in ("images.txt", "points3D.txt"):
        (path.parent / name).write_text("")
    cameras = pycolmap.Reconstruction(str(path.parent)).cameras
    assert list(cameras) == [1]
    return cameras[1]


def colmap_project(path, X: np.ndarray) -> np.ndarray:
    return np.asarray(colmap_camera(path).img_from_cam(X)) - 0.5   # COLMAP's (0.5, 0.5) centre


# --------------------------------------------------------------------------------------------
# Each writer read back by its tool
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
@pytest.mark.parametrize("model, params", [("kannala_brandt", KB), ("unified", UNIFIED),
                                           ("opencv", RADTAN), ("opencv", OPENCV5),
                                           ("opencv", RATIONAL), ("opencv", PRISM)])
def test_opencv_file_reproduces_the_camera(tmp_path, model, params):
    camera = _camera(model, params)
    path = write_camera(camera, tmp_path / "camera.yaml", "opencv")
    assert path.read_text().startswith("%YAML:1.0\n")
    rays = _rays(camera)
    _compare(camera, rays, opencv_project(path, rays))


@pytest.mark.parametrize("params, n", [(RADTAN, 4), (OPENCV5, 5), (RATIONAL, 8), (PRISM, 12),
                                       (PINHOLE + [0.0] * 12, 4)])
def test_opencv_distortion_is_the_shortest_vector_holding_the_terms(tmp_path, params, n):
    path = write_camera(_camera("opencv", params), tmp_path / "camera.yaml", "opencv")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    D = fs.getNode("distortion_coefficients").mat()
    assert fs.getNode("camera_model").string() == "pinhole"
    assert D.shape == (1, n) and D.ravel().tolist() == params[4:4 + n]
    assert fs.getNode("camera_matrix").mat().tolist() == [
        [params[0], 0, params[2]], [0, params[1], params[3]], [0, 0, 1]]


@needs_skew
@pytest.mark.numerics
@pytest.mark.parametrize("model, params", [("kannala_brandt", KB + [4.0]),
                                           ("unified", UNIFIED + [-3.0])])
def test_opencv_file_keeps_the_skew(tmp_path, model, params):
    camera = _camera(model, params)
    path = camera.save(tmp_path / "camera.yaml", format="opencv")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("K").mat()[0, 1] == params[-1]   # fisheye: alpha = K[0, 1] / fx
    rays = _rays(camera)
    _compare(camera, rays, opencv_project(path, rays))


@pytest.mark.numerics
@pytest.mark.parametrize("model, params", [
    ("pinhole", PINHOLE), ("kannala_brandt", KB), ("unified", UNIFIED), ("double_sphere", DS),
    ("eucm", EUCM), ("fov", FOV), ("opencv", RADTAN)])
def test_kalibr_file_reproduces_the_camera(tmp_path, model, params):
    camera = _camera(model, params)
    path = write_camera(camera, tmp_path / "camchain.yaml", "kalibr")
    cam = _safe_load(path.read_text())["cam0"]
    # what Kalibr's ConfigReader checks: floats for the intrinsics, ints for the resolution
    assert all(isinstance(v, float) for v in cam["intrinsics"] + cam["distortion_coeffs"])
    assert cam["resolution"] == [640, 480] and isinstance(cam["rostopic"], str)
    expected = {"pinhole": ("pinhole", "radtan"), "kannala_brandt": ("pinhole", "equidistant"),
                "unified": ("omni", "radtan"), "double_sphere": ("ds", "none"),
                "eucm": ("eucm", "none"), "fov": ("pinhole", "fov"),
                "opencv": ("pinhole", "radtan")}[model]
    assert (cam["camera_model"], cam["distortion_model"]) == expected
    rays = _rays(camera)
    _compare(camera, rays, kalibr_project(cam, rays))


@pytest.mark.numerics
@pytest.mark.parametrize("model, params, kind", [
    ("pinhole", PINHOLE, "pinhole"), ("kannala_brandt", KB, "kb4"), ("unified", UCM, "ucm"),
    ("double_sphere", DS, "ds"), ("eucm", EUCM, "eucm"), ("fov", FOV, "fov")])
def test_basalt_file_reproduces_the_camera(tmp_path, model, params, kind):
    camera = _camera(model, params)
    path = write_camera(camera, tmp_path / "calibration.json", "basalt")
    calib = json.loads(path.read_text())
    value = calib["value0"]
    # every key basalt's cereal serialisation of Calibration reads
    assert list(value) == ["T_imu_cam", "intrinsics", "resolution", "calib_accel_bias",
                           "calib_gyro_bias", "imu_update_rate", "accel_noise_std",
                           "gyro_noise_std", "accel_bias_std", "gyro_bias_std",
                           "cam_time_offset_ns", "vignette"]
    assert value["T_imu_cam"] == [{"px": 0.0, "py": 0.0, "pz": 0.0, "qx": 0.0, "qy": 0.0,
                                   "qz": 0.0, "qw": 1.0}]
    assert value["resolution"] == [[640, 480]] and value["intrinsics"][0]["camera_type"] == kind
    rays = _rays(camera)
    _compare(camera, rays, basalt_project(calib, rays))


def test_basalt_ucm_is_the_unified_model_in_alpha_form(tmp_path):
    xi = UCM[4]
    calib = json.loads(write_camera(_camera("unified", UCM), tmp_path / "c.json", "basalt")
                       .read_text())
    q = calib["value0"]["intrinsics"][0]["intrinsics"]
    assert q["alpha"] == pytest.approx(xi / (1 + xi), rel=1e-15)
    assert q["fx"] == pytest.approx(UCM[0] / (1 + xi), rel=1e-15)
    assert q["fy"] == pytest.approx(UCM[1] / (1 + xi), rel=1e-15)


@pytest.mark.numerics
@pytest.mark.parametrize("model, params", [("kannala_brandt", KB), ("pinhole", PINHOLE)])
def test_orbslam3_file_reproduces_the_camera(tmp_path, model, params):
    camera = _camera(model, params)
    path = write_camera(camera, tmp_path / "settings.yaml", "orbslam3")
    rays = _rays(camera)
    _compare(camera, rays, orbslam3_project(path, rays))


@pytest.mark.numerics
@pytest.mark.parametrize("model, params, name", [
    ("kannala_brandt", KB, "OPENCV_FISHEYE"), ("pinhole", PINHOLE, "PINHOLE"),
    ("fov", FOV, "FOV"), ("division", DIVISION, "DIVISION"),
    ("division", DIVISION[:4] + [0.05], "DIVISION"), ("opencv", RADTAN, "OPENCV"),
    ("opencv", OPENCV5, "FULL_OPENCV"), ("opencv", RATIONAL, "FULL_OPENCV"),
    ("thin_prism_fisheye", TPF, "THIN_PRISM_FISHEYE"),
    ("fisheye624", F624, "RAD_TAN_THIN_PRISM_FISHEYE")])
def test_colmap_file_reproduces_the_camera(tmp_path, model, params, name):
    camera = _camera(model, params)
    path = write_camera(camera, tmp_path / "cameras.txt", "colmap")
    read = colmap_camera(path)
    assert read.model_name == name and (read.width, read.height) == (640, 480)
    assert read.principal_point_x == params[2] + 0.5   # COLMAP's top-left centre at 0.5
    rays = _rays(camera)
    _compare(camera, rays, colmap_project(path, rays))


def test_json_and_ocamcalib_complete_the_list(tmp_path):
    camera = _camera("eucm", EUCM, fov=math.radians(200))
    back = ot.Camera.load_json(write_camera(camera, tmp_path / "c.json", "json"))
    assert back.model.name == "eucm" and torch.equal(back.params, camera.params)
    assert back.fov == pytest.approx(camera.fov)
    poly = ot.Camera.from_ocamcalib(OCAMCALIB_FILE)
    back = ot.Camera.from_ocamcalib(poly.save(tmp_path / "calib_results.txt", "ocamcalib"))
    assert torch.allclose(back.params, poly.params, rtol=1e-15, atol=0)


# --------------------------------------------------------------------------------------------
# The imaged area (issue 33): every format keeps fov and blind_fov, its tool still reads it
# --------------------------------------------------------------------------------------------

#: (format, model, params, fov deg, blind fov deg, the tool's own reader projecting the rays)
AREAS = [
    ("opencv", "unified", UNIFIED, 200.0, 40.0, opencv_project),
    ("kalibr", "unified", UNIFIED, 200.0, 40.0,
     lambda path, rays: kalibr_project(_safe_load(path.read_text())["cam0"], rays)),
    ("basalt", "unified", UCM, 200.0, 40.0,
     lambda path, rays: basalt_project(json.loads(path.read_text()), rays)),
    ("orbslam3", "kannala_brandt", KB, 150.0, None, orbslam3_project),
    ("colmap", "kannala_brandt", KB, 150.0, 20.0, colmap_project),
    ("ocamcalib", "scaramuzza", None, 170.0, 30.5, None),
    ("json", "eucm", EUCM, 200.0, 40.0, None),
]


@pytest.mark.numerics
@pytest.mark.parametrize("fmt, model, params, fov, blind, project", AREAS,
                         ids=[a[0] for a in AREAS])
def test_every_format_keeps_the_imaged_area(tmp_path, fmt, model, params, fov, blind,
                                            project):
    """``fov`` and ``blind_fov`` are read back by ``ot.Camera.load``, and the tool's own reader
    (cv2.FileStorage, PyYAML, json, pycolmap) still reads the file and projects as the camera
    does; OCamCalib's file: its five sections are the same as without the area."""
    kwargs = dict(fov=math.radians(fov), blind_fov=None if blind is None else math.radians(blind))
    if params is None:
        poly = ot.Camera.from_ocamcalib(OCAMCALIB_FILE)
        camera = ot.Camera(poly.model, poly.params, poly.image_size, **kwargs)
    else:
        camera = _camera(model, params, **kwargs)
    name = "cameras.txt" if fmt == "colmap" else f"camera.{fmt}"   # pycolmap reads a folder
    path = write_camera(camera, tmp_path / name, fmt)
    back = ot.Camera.load(path, fmt)
    assert back.fov == pytest.approx(camera.fov, rel=1e-12)
    assert (back.blind_fov is None) == (blind is None)
    if blind is not None:
        assert back.blind_fov == pytest.approx(camera.blind_fov, rel=1e-12)
    if project is not None:
        rays = _rays(camera)
        _compare(camera, rays, project(path, rays))
    if fmt == "ocamcalib":
        plain = write_camera(poly, tmp_path / "plain.txt", fmt).read_text()
        assert path.read_text().startswith(plain) and f"{fov:.17g} 30.5" in path.read_text()
    # a caller's fov / blind_fov override the file's
    assert ot.Camera.load(path, fmt, fov=math.radians(100)).fov == math.radians(100)


def test_a_fisheye_refusal_names_the_angle_of_its_image_circle(tmp_path):
    """A 196-degree lens on a sensor whose corners lie farther off axis: with its ``fov``
    (as camera.json keeps it) the refusal names 98 deg, not the sensor corners' angle."""
    lens = [150.0, 150.0, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0]
    corner = math.degrees(math.hypot(319.5, 239.5) / 150.0)
    with pytest.raises(ValueError, match=f"{corner:.2f} deg"):
        write_camera(_camera("kannala_brandt", lens), tmp_path / "x.yaml", "opencv")
    camera = _camera("kannala_brandt", lens, fov=math.radians(196))
    back = ot.Camera.load_json(write_camera(camera, tmp_path / "camera.json", "json"))
    with pytest.raises(ValueError, match=r"sees up to 98\.00 deg") as err:
        write_camera(back, tmp_path / "x.yaml", "opencv")
    assert f"{corner:.2f}" not in str(err.value)


def test_cli_convert_model_judges_a_fit_by_its_fov(tmp_path, capsys):
    """``convert-model --json camera.json --to kannala_brandt --format opencv`` of a camera
    whose camera.json keeps its 196 degree field of view (as ``fit`` writes it): refused in
    one line naming 98 deg, the lens's, not the sensor corners' angle; written with
    ``--accept-fov`` and its area kept in the file."""
    lens = [150.0, 150.0, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0]
    _camera("kannala_brandt", lens, fov=math.radians(196)).save_json(tmp_path / "camera.json")
    argv = ["convert-model", "--json", str(tmp_path / "camera.json"), "--to", "kannala_brandt",
            "--format", "opencv", "--out", str(tmp_path / "x.yaml")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "sees up to 98.00 deg" in err and len(err.strip().splitlines()) == 1, err
    assert cli.main(argv + ["--accept-fov"]) == 0
    assert "98.00 deg" in capsys.readouterr().err   # the warning of what was accepted
    fs = cv2.FileStorage(str(tmp_path / "x.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("fov_deg").real() == pytest.approx(196)
    assert ot.Camera.load(tmp_path / "x.yaml").fov == pytest.approx(math.pi)   # valid to 90


# --------------------------------------------------------------------------------------------
# Refusals and accepted limits
# --------------------------------------------------------------------------------------------

def _wide():
    """A Kannala-Brandt camera seeing 95 deg off its axis (fov 190 deg inside the image)."""
    return _camera("kannala_brandt", [150.0, 150.0, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0],
                   fov=math.radians(190))


@pytest.mark.parametrize("fmt", ["opencv", "colmap", "kalibr", "orbslam3"])
def test_a_camera_past_90_degrees_is_refused_where_the_format_folds(tmp_path, fmt):
    with pytest.raises(ValueError, match=r"95\.00 deg.*90 deg.*accept_fov"):
        write_camera(_wide(), tmp_path / "x", fmt)
    assert not (tmp_path / "x").exists()
    # a camera inside 90 deg, and the formats whose model goes past 90 deg, write it
    write_camera(_camera("kannala_brandt", KB), tmp_path / "y", fmt)
    write_camera(_wide(), tmp_path / "z.json", "basalt")


@pytest.mark.parametrize("model", ["thin_prism_fisheye", "fisheye624"])
def test_colmap_refuses_the_new_fisheyes_past_90_degrees(tmp_path, model):
    wide = _camera(model, [150.0, 150.0, 319.5, 239.5] + [0.0] * (len(get_model(model)
                                                                      .param_names) - 4),
                   fov=math.radians(190))
    with pytest.raises(ValueError, match=r"95\.00 deg.*divides by z.*accept_fov"):
        write_camera(wide, tmp_path / "cameras.txt", "colmap")
    with pytest.warns(UserWarning, match=r"95\.00 deg"):
        path = write_camera(wide, tmp_path / "cameras.txt", "colmap", accept_fov=True)
    assert "# valid_angle_deg: 90.0" in path.read_text()
    assert ot.Camera.load(path).params.tolist() == wide.params.tolist()


@pytest.mark.numerics
def test_colmap_division_projects_behind_the_camera_as_ours(tmp_path):
    # k < 0 reaches past 90 deg in both (COLMAP solves the same quadratic for any z)
    camera = _camera("division", DIVISION[:4] + [-0.3])
    path = write_camera(camera, tmp_path / "cameras.txt", "colmap")
    angles = np.radians(np.linspace(5.0, 150.0, 30))
    rays = np.stack((np.sin(angles) * 0.6, np.sin(angles) * 0.8, np.cos(angles)), -1)
    assert (rays[:, 2] < 0).sum() > 10
    ours, valid = camera.model.project(torch.from_numpy(rays), camera.params)   # past the image
    assert bool(valid.all())
    assert np.abs(colmap_project(path, rays) - ours.numpy()).max() < PIXEL_TOL


@pytest.mark.parametrize("fmt, params, message", [
    ("kalibr", OPENCV5, r"pinhole-radtan holds k1, k2, p1, p2 of the opencv model, not k3 = "),
    ("kalibr", PRISM, r"not k3 = 0\.001, k4 = 0\.02, k5 = -0\.003, k6 = 0\.0004, s1 = "),
    ("colmap", PRISM, r"FULL_OPENCV has no thin prism: s1 = 0\.0005, s2 = -0\.0001"),
])
def test_opencv_coefficients_a_format_lacks_are_refused_by_name(tmp_path, fmt, params, message):
    with pytest.raises(ValueError, match=message):
        write_camera(_camera("opencv", params), tmp_path / "x", fmt)
    assert not (tmp_path / "x").exists()


def test_the_fov_limit_uses_the_farthest_valid_pixel(tmp_path):
    # no fov: the 640 x 480 image's corners are 400 px / 150 px = 152.8 deg off the axis
    wide = _camera("kannala_brandt", [150.0, 150.0, 319.5, 239.5, 0.0, 0.0, 0.0, 0.0])
    corner = math.degrees(math.hypot(319.5, 239.5) / 150.0)
    with pytest.raises(ValueError, match=f"{corner:.2f} deg"):
        write_camera(wide, tmp_path / "x.yaml", "opencv")


def test_an_accepted_fov_is_recorded_in_the_file(tmp_path):
    with pytest.warns(UserWarning, match=r"95\.00 deg"):
        path = write_camera(_wide(), tmp_path / "camera.yaml", "opencv", accept_fov=True)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("valid_angle_deg").real() == 90.0
    assert "95.00 deg" in path.read_text()
    with pytest.warns(UserWarning):
        path = write_camera(_wide(), tmp_path / "cameras.txt", "colmap", accept_fov=True)
    assert "# valid_angle_deg: 90.0" in path.read_text()
    assert colmap_camera(path).model_name == "OPENCV_FISHEYE"
    with pytest.warns(UserWarning):
        path = write_camera(_wide(), tmp_path / "camchain.yaml", "kalibr", accept_fov=True)
    assert _safe_load(path.read_text())["cam0"]["valid_angle_deg"] == 90.0


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f != "json"])
def test_a_model_the_format_lacks_is_refused_naming_the_models_it_has(tmp_path, fmt):
    camera = _camera("equidistant", [200.0, 200.0, 319.5, 239.5])
    names = ", ".join(supported_models(fmt))
    with pytest.raises(ValueError, match=f"{fmt} format holds {names}, not equidistant"):
        write_camera(camera, tmp_path / "x", fmt)


@needs_skew
@pytest.mark.parametrize("fmt", ["kalibr", "basalt", "orbslam3", "colmap"])
def test_a_skew_is_refused_where_the_format_has_none(tmp_path, fmt):
    skewed = _camera("kannala_brandt", KB + [4.0])
    # dropping s moves a pixel by |s| |v - cy| / fy, largest at the image's top or bottom edge
    error = 4.0 * max(240.0 + 0.5, 480 - 0.5 - 240.0) / 300.0
    with pytest.raises(ValueError, match=f"no skew.*{error:.3g} px.*accept_skew"):
        write_camera(skewed, tmp_path / "x", fmt)
    with pytest.warns(UserWarning, match=f"{error:.3g} px"):
        path = write_camera(skewed, tmp_path / "x", fmt, accept_skew=True)
    unskewed = tmp_path / "y"
    write_camera(_camera("kannala_brandt", KB), unskewed, fmt)
    file_lines = [ln for ln in path.read_text().splitlines() if "NOTE" not in ln]
    assert file_lines == [ln for ln in unskewed.read_text().splitlines() if "NOTE" not in ln]
    if fmt != "basalt":   # JSON has no comments: the warning alone says it
        assert f"{error:.3g} px" in path.read_text()


def test_other_refusals(tmp_path):
    with pytest.raises(ValueError, match="format: expected one of json, ocamcalib, opencv"):
        write_camera(_camera("kannala_brandt", KB), tmp_path / "x", "matlab")
    with pytest.raises(ValueError, match="basalt's ucm .* without distortion"):
        write_camera(_camera("unified", UNIFIED), tmp_path / "x", "basalt")
    with pytest.raises(ValueError, match="Kalibr takes alpha in \\[0, 1\\)"):
        write_camera(_camera("double_sphere", DS[:5] + [1.0]), tmp_path / "x", "kalibr")
    batch = ot.Camera("kannala_brandt", torch.tensor([KB, KB], dtype=D), SIZE)
    with pytest.raises(ValueError, match="one camera, got a batch of shape \\(2,\\)"):
        write_camera(batch, tmp_path / "x", "opencv")
    assert not (tmp_path / "x").exists()
    write_camera(batch, tmp_path / "batch.json", "json")   # JSON holds batches


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
def test_cli_convert_model_writes_the_format(tmp_path, capsys):
    source = tmp_path / "source.json"
    _camera("kannala_brandt", KB).save_json(source)
    out = tmp_path / "camera.yaml"
    assert cli.main(["convert-model", "--json", str(source), "--to", "kannala_brandt",
                     "--format", "opencv", "--out", str(out), "--grid", "8"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert fs.getNode("camera_model").string() == "fisheye"
    assert np.allclose(fs.getNode("K").mat(), [[300, 0, 320], [0, 300, 240], [0, 0, 1]],
                       atol=1e-3)


@pytest.mark.parametrize("argv, message", [
    (["--to", "eucm", "--format", "opencv", "--out", "x.yaml"],
     "--to eucm: the opencv format holds kannala_brandt, unified"),
    (["--to", "eucm,unified", "--format", "kalibr", "--out", "x.yaml"],
     "--format writes one file: give one model in --to, got eucm, unified"),
    (["--to", "eucm", "--format", "kalibr"], "--format needs --out FILE"),
    (["--to", "eucm", "--accept-skew"], "--accept-fov and --accept-skew apply to --format"),
])
def test_cli_convert_model_refuses_with_one_line(tmp_path, capsys, argv, message):
    source = tmp_path / "source.json"
    _camera("kannala_brandt", KB).save_json(source)
    assert cli.main(["convert-model", "--json", str(source)] + argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


@pytest.mark.numerics
def test_cli_convert_model_refuses_a_camera_past_90_degrees(tmp_path, capsys):
    source = tmp_path / "source.json"
    _wide().save_json(source)
    argv = ["convert-model", "--json", str(source), "--to", "kannala_brandt", "--format",
            "opencv", "--out", str(tmp_path / "x.yaml"), "--grid", "8"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "90 deg" in err[0] and "--accept-fov" in err[0], err
    assert not (tmp_path / "x.yaml").exists()
    assert cli.main(argv + ["--accept-fov"]) == 0
    captured = capsys.readouterr()
    assert "warning" in captured.err and "90 deg" in captured.err
    fs = cv2.FileStorage(str(tmp_path / "x.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("valid_angle_deg").real() == 90.0
