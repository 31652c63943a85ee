"""Camera files that other tools read: OpenCV, Kalibr, basalt, ORB-SLAM3 and COLMAP.

One entry point, `write_camera` (``Camera.save``), writes one camera in one of ``FORMATS``
(atomically); ``json`` and ``ocamcalib`` are this package's JSON and OCamCalib's
``calib_results.txt`` (``formats.py``). Each format holds a few models:

=========== ========================= ============================================================
format      file                      models (the tool's name)
=========== ========================= ============================================================
json        camera JSON               every model (``Camera.load_json`` reads it)
ocamcalib   ``calib_results.txt``     scaramuzza
opencv      ``cv2.FileStorage`` YAML  kannala_brandt (``fisheye``), unified (``omnidir``), opencv
                                      (``pinhole``: ``camera_matrix``, ``distortion_coefficients``
                                      1 x N, N the shortest of 4, 5, 8, 12 that holds the
                                      non-zero coefficients, as ``cv2.calibrateCamera`` returns)
kalibr      ``camchain.yaml``         pinhole (``pinhole-radtan``, zero coefficients),
                                      kannala_brandt (``pinhole-equi``), unified (``omni-radtan``),
                                      double_sphere (``ds-none``), eucm (``eucm-none``),
                                      fov (``pinhole-fov``), opencv with k1, k2, p1, p2 only
                                      (``pinhole-radtan``)
basalt      calibration JSON          pinhole (``pinhole``), kannala_brandt (``kb4``), unified
                                      without distortion (``ucm``), double_sphere (``ds``),
                                      eucm (``eucm``), fov (``fov``, ``w`` = omega)
orbslam3    settings YAML (v1.0)      pinhole (``PinHole``), kannala_brandt (``KannalaBrandt8``)
colmap      ``cameras.txt``           pinhole (``PINHOLE``), kannala_brandt (``OPENCV_FISHEYE``),
                                      fov (``FOV``), division (``DIVISION``), opencv (``OPENCV``
                                      when k3..k6 and s1..s4 are 0, else ``FULL_OPENCV``, which
                                      needs s1..s4 = 0), thin_prism_fisheye
                                      (``THIN_PRISM_FISHEYE``), fisheye624
                                      (``RAD_TAN_THIN_PRISM_FISHEYE``)
=========== ========================= ============================================================

The conventions of these files are converted here and nowhere else:

* Pixels: OpenCV, Kalibr, basalt and ORB-SLAM3 put the centre of the top-left pixel at (0, 0),
  like this package, and take the parameters as they are. COLMAP puts it at (0.5, 0.5): its
  ``cx, cy`` are ours plus 0.5.
* Image size: ``(H, W)`` here, width first in every file.
* Parameter orders: Kalibr's ``omni`` intrinsics are ``[xi, fu, fv, pu, pv]`` with radtan
  ``[k1, k2, r1, r2]``, ``ds`` ``[xi, alpha, fu, fv, pu, pv]`` and ``eucm``
  ``[alpha, beta, fu, fv, pu, pv]`` (Kalibr's ``kalibr_common/ConfigReader.py``); basalt and
  ORB-SLAM3 name each value.
* basalt's ``ucm`` is the unified model in the alpha form of its ``unified_camera.hpp``,
  ``u = fx x / (alpha |X| + (1 - alpha) z) + cx``: ``alpha = xi / (1 + xi)`` and focal lengths
  divided by ``1 + xi``.
* The imaged area: a camera's ``fov`` and ``blind_fov`` (the image circle and a catadioptric
  camera's blind cone, full angles) have no field in any of these tools' files; every writer
  keeps them where the tool's own reader passes over them, and ``ot.Camera.load`` reads them
  back, so that a later conversion or export judges the area the camera images, not the whole
  sensor: ``fov_deg`` / ``blind_fov_deg`` keys (OpenCV, ORB-SLAM3 top level, Kalibr under
  ``cam0``), an ``"omniscape_torch"`` object beside basalt's ``value0``, ``# fov_deg: ...``
  comments in COLMAP's ``cameras.txt`` and a sixth ``#field of view`` section after OCamCalib's
  five (``formats.write_ocamcalib``).
* Skew ``s`` (``u = fx x + s y + cx``): OpenCV ``omnidir``'s ``K[0, 1]``; for OpenCV ``fisheye``,
  ``K[0, 1] = s`` as ``cv::fisheye::calibrate`` writes it, and ``cv2.fisheye.projectPoints``
  (which ignores ``K[0, 1]``) takes ``alpha = K[0, 1] / K[0, 0]``. The other formats have none.

What a format cannot hold is refused with a ``ValueError`` that names the limit, unless the
caller accepts it (the file then records it and a ``UserWarning`` says what was lost):

* A model the format lacks (the message names the models it has): convert first
  (``ot.calibration.convert``, ``omniscape-torch convert-model``).
* Rays at or past 90 degrees off the optical axis, for the Kannala-Brandt targets of OpenCV
  (``cv2.fisheye`` divides by z and takes ``atan``: a ray 91 degrees off the axis lands on the
  wrong side of the image), COLMAP (``OPENCV_FISHEYE``, ``THIN_PRISM_FISHEYE`` and
  ``RAD_TAN_THIN_PRISM_FISHEYE`` divide by z), Kalibr (``pinhole-equi`` is a pinhole
  projection, valid for z > 0) and ORB-SLAM3 (``KannalaBrandt8::unproject`` returns
  ``(x, y, 1)``). The pinhole-based models (fov, opencv, division with k >= 0) never see 90
  degrees, and COLMAP's ``DIVISION`` projects points behind the camera as ours (k < 0). The
  camera's angle is its ``fov`` or its image's farthest valid pixel's.
  ``accept_fov=True`` writes the file with ``valid_angle_deg: 90`` (a comment for COLMAP).
* Coefficients the target lacks, named with their values: Kalibr's ``pinhole-radtan`` holds
  k1, k2, p1, p2 of the ``opencv`` model only, COLMAP's ``FULL_OPENCV`` no thin prism s1..s4
  (write the ``opencv`` format, which holds all twelve, or convert first).
* A non-zero skew in a format without one. ``accept_skew=True`` drops it; the warning and a
  comment in the file give the pixel error: ``|s| |v - cy| / fy`` at the image's top or bottom.

Examples:
    >>> import tempfile, pathlib, omniscape_torch as ot
    >>> cam = ot.Camera("kannala_brandt", [300.0, 300.0, 319.5, 239.5, 0.01, 0, 0, 0], (480, 640))
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = cam.save(pathlib.Path(tmp) / "camera.yaml", format="opencv")
    ...     print(path.read_text().splitlines()[4])
    camera_model: "fisheye"
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import torch

from ..io.atomic import atomic_write_text
from . import formats
from ._checks import not_a_camera
from .registry import MODELS

#: The formats `write_camera` writes.
FORMATS = ("json", "ocamcalib", "opencv", "kalibr", "basalt", "orbslam3", "colmap")

# Targets that cannot represent a ray at or past 90 degrees off the axis: (format, model) -> why.
_FOLDS_AT_90 = (
    ("opencv", "kannala_brandt", "OpenCV's fisheye model (cv2.fisheye) divides by z and folds "
                                 "rays at or past 90 deg onto the wrong side of the image"),
    ("colmap", "kannala_brandt", "COLMAP's OPENCV_FISHEYE divides by z and cannot project rays "
                                 "at or past 90 deg"),
    ("colmap", "thin_prism_fisheye", "COLMAP's THIN_PRISM_FISHEYE divides by z and cannot "
                                     "project rays at or past 90 deg"),
    ("colmap", "fisheye624", "COLMAP's RAD_TAN_THIN_PRISM_FISHEYE divides by z and cannot "
                             "project rays at or past 90 deg"),
    ("kalibr", "kannala_brandt", "Kalibr's pinhole-equi is a pinhole projection, valid for z > 0 "
                                 "only (rays below 90 deg)"),
    ("orbslam3", "kannala_brandt", "ORB-SLAM3's KannalaBrandt8 unprojects pixels to rays "
                                   "(x, y, 1), which cannot reach 90 deg"),
)

#: Frame rate and ORB parameters written into ORB-SLAM3 settings: the values of ORB-SLAM3's
#: own fisheye example, Examples/Monocular/TUM-VI.yaml (ORB-SLAM3 requires them).
_ORBSLAM3_DEFAULTS = (
    ("Camera.fps", "20"), ("Camera.RGB", "1"), ("ORBextractor.nFeatures", "1500"),
    ("ORBextractor.scaleFactor", "1.2"), ("ORBextractor.nLevels", "8"),
    ("ORBextractor.iniThFAST", "20"), ("ORBextractor.minThFAST", "7"),
    ("Viewer.KeyFrameSize", "0.05"), ("Viewer.KeyFrameLineWidth", "1.0"),
    ("Viewer.GraphLineWidth", "0.9"), ("Viewer.PointSize", "2.0"), ("Viewer.CameraSize", "0.08"),
    ("Viewer.CameraLineWidth", "3.0"), ("Viewer.ViewpointX", "0.0"),
    ("Viewer.ViewpointY", "-0.7"), ("Viewer.ViewpointZ", "-3.5"), ("Viewer.ViewpointF", "500.0"),
)


def supported_models(format: str) -> tuple[str, ...]:
    """The models that ``format`` (one of ``FORMATS``) holds (module docstring)."""
    fmt = _check_format(format)
    if fmt == "json":
        return tuple(MODELS)
    return {
        "ocamcalib": ("scaramuzza",),
        "opencv": ("kannala_brandt", "unified", "opencv"),
        "kalibr": ("pinhole", "kannala_brandt", "unified", "double_sphere", "eucm", "fov",
                   "opencv"),
        "basalt": ("pinhole", "kannala_brandt", "unified", "double_sphere", "eucm", "fov"),
        "orbslam3": ("pinhole", "kannala_brandt"),
        "colmap": ("pinhole", "kannala_brandt", "fov", "division", "opencv", "thin_prism_fisheye",
                   "fisheye624"),
    }[fmt]


def fold_limit(format: str, model: str) -> str | None:
    """Why the `format` file of a `model` camera cannot hold rays at or past 90 degrees off the
    axis (the tool folds or drops them), or None where it can. `write_camera` refuses such a
    camera that sees that far, unless `accept_fov`."""
    return next((why for fmt, folding, why in _FOLDS_AT_90 if (fmt, folding) == (format, model)),
                None)


def write_camera(camera, path: str | Path, format: str, *, accept_fov: bool = False,
                 accept_skew: bool = False) -> Path:
    """Write one camera as the file another tool reads, atomically (module docstring).

    Args:
        camera: an ``ot.Camera``; one camera, except for ``json`` (batches too).
        path: the file to write (for ``colmap``, ``cameras.txt`` of a sparse model folder).
        format: one of ``FORMATS``.
        accept_fov: write a fisheye camera that sees at or past 90 degrees off its axis
            into a format that folds there; the file records ``valid_angle_deg: 90``.
        accept_skew: write a camera with a non-zero skew ``s`` into a format without one; the
            skew is dropped and the file states the pixel error.

    Returns:
        The path written. A ``UserWarning`` says what an accepted limit costs.

    Raises:
        ValueError: unknown format; a model the format lacks (naming those it has); a batch; a
            field of view or skew the format cannot hold (naming the limit), unless accepted;
            a value the tool rejects (Kalibr: negative principal point, alpha >= 1; basalt:
            a unified camera with distortion).
        TypeError: ``camera`` is not a camera.
    """
    fmt = _check_format(format)
    if not all(hasattr(camera, a) for a in ("model", "params", "image_size", "batch_shape")):
        raise not_a_camera("camera", camera)
    if fmt == "json":
        return formats.save_json(camera, path)
    model = camera.model.name
    if model not in supported_models(fmt):
        raise ValueError(f"camera: the {fmt} format holds {', '.join(supported_models(fmt))}, not "
                         f"{model} (convert it first: ot.calibration.convert, or omniscape-torch "
                         f"convert-model --to MODEL)")
    if camera.batch_shape != ():
        raise ValueError(f"camera: the {fmt} format holds one camera, got a batch of shape "
                         f"{tuple(camera.batch_shape)}")
    if fmt == "ocamcalib":
        return formats.write_ocamcalib(camera, path)
    p = dict(zip(camera.param_names, camera.params.detach().double().cpu().tolist()))
    skew = p.pop("s", 0.0)
    notes: list[str] = []   # what an accepted limit costs: warnings and file comments
    keep_skew = fmt == "opencv"
    if skew != 0 and not keep_skew:
        h, _ = camera.image_size
        error = abs(skew) * max(p["cy"] + 0.5, h - 0.5 - p["cy"]) / p["fy"]
        message = (f"the {fmt} format has no skew: dropping s = {skew:.6g} px moves pixels by up "
                   f"to {error:.3g} px (|s| |v - cy| / fy at the image's top or bottom edge)")
        if not accept_skew:
            raise ValueError(f"camera: {message}; accept_skew=True (--accept-skew) writes it "
                             f"without the skew")
        notes.append(message)
    valid_angle = None
    why = fold_limit(fmt, model)
    if why is not None:
        angle = math.degrees(formats.farthest_angle(camera))
        if angle >= 90.0:
            message = f"the camera sees up to {angle:.2f} deg off its optical axis, but {why}"
            if not accept_fov:
                raise ValueError(f"camera: {message} (restrict the camera with fov < 180 deg, or "
                                 f"accept_fov=True (--accept-fov) writes it with "
                                 f"valid_angle_deg: 90)")
            notes.append(f"{message}; the file is valid for rays below 90 deg only")
            valid_angle = 90.0
    writer = {"opencv": _opencv, "kalibr": _kalibr, "basalt": _basalt, "orbslam3": _orbslam3,
              "colmap": _colmap}[fmt]
    written = atomic_write_text(path, writer(camera, p, skew, notes, valid_angle))
    for note in notes:
        warnings.warn(f"{written}: {note}", UserWarning, stacklevel=2)
    return written


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------

def _check_format(format) -> str:
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {', '.join(FORMATS)}, got {format!r}")
    return format


def _num(value: float) -> str:
    """A float that YAML 1.1 (PyYAML, Kalibr), cv::FileStorage, JSON and COLMAP all read back
    exactly: the shortest round-trip repr, with a '.' before any exponent (PyYAML reads '1e-05'
    as a string)."""
    text = repr(float(value))
    if "e" in text and "." not in text:
        mantissa, exponent = text.split("e")
        text = f"{mantissa}.0e{exponent}"
    return text


def _list(values) -> str:
    return "[" + ", ".join(_num(v) for v in values) + "]"


def area_fields(camera) -> list[tuple[str, float]]:
    """``[("fov_deg", ...), ("blind_fov_deg", ...)]``: the camera's ``fov`` and ``blind_fov``
    (full angles, degrees) where set (module docstring: how each format keeps them)."""
    return [(key, math.degrees(value)) for key, value in
            (("fov_deg", camera.fov), ("blind_fov_deg", camera.blind_fov)) if value is not None]


def _area_keys(camera, indent: str = "") -> list[str]:
    return [f"{indent}{key}: {_num(value)}" for key, value in area_fields(camera)]


def _comments(camera, tool: str, notes: list[str], extra: tuple[str, ...] = ()) -> list[str]:
    h, w = camera.image_size
    lines = [f"# omniscape_torch: a {camera.model.name} camera of {w} x {h} pixels as {tool}."]
    lines += [f"# {line}" for line in extra]
    lines += [f"# NOTE: {note}." for note in notes]
    return lines


#: The ``opencv`` model's coefficients, in OpenCV's order (``cv2.projectPoints``).
_OPENCV_COEFFS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")


def _opencv_coeffs(p: dict, lengths: tuple[int, ...]) -> list[float] | None:
    """The ``opencv`` model's coefficients cut to the shortest of ``lengths`` that holds every
    non-zero one (None if none does)."""
    values = [p[n] for n in _OPENCV_COEFFS]
    last = max((i + 1 for i, v in enumerate(values) if v != 0), default=0)
    n = next((n for n in lengths if n >= last), None)
    return None if n is None else (values + [0.0] * max(n - len(values), 0))[:n]


def _nonzero(p: dict, names) -> str:
    return ", ".join(f"{n} = {p[n]:.6g}" for n in names if p[n] != 0)


def _opencv_matrix(name: str, rows: int, cols: int, values) -> list[str]:
    return [f"{name}: !!opencv-matrix", f"   rows: {rows}", f"   cols: {cols}", "   dt: d",
            "   data: [ " + ", ".join(_num(v) for v in values) + " ]"]


# --------------------------------------------------------------------------------------------
# Writers: (camera, params by name without s, s, notes, valid angle or None) -> text
# --------------------------------------------------------------------------------------------

def _opencv(camera, p: dict, s: float, notes: list[str], valid_angle) -> str:
    """``cv2.FileStorage`` YAML: ``camera_model`` ("fisheye", "omnidir" or "pinhole"),
    ``image_width``, ``image_height``, then ``K`` (3 x 3, ``K[0, 1] = s``) and ``D`` (fisheye:
    k1..k4 as 4 x 1, as ``cv2.fisheye.calibrate`` returns it; omnidir: k1, k2, p1, p2 as 1 x 4)
    and ``xi``; or, for the ``opencv`` model, ``camera_matrix`` and ``distortion_coefficients``
    (1 x N, N = 4, 5, 8 or 12, as ``cv2.calibrateCamera`` returns them and OpenCV's
    calibration sample writes them)."""
    h, w = camera.image_size
    K = (p["fx"], s, p["cx"], 0.0, p["fy"], p["cy"], 0.0, 0.0, 1.0)
    k_name = "K"
    if camera.model.name == "kannala_brandt":
        usage = ("cv2.fisheye.projectPoints(points, rvec, tvec, K, D, "
                 "alpha=K[0, 1] / K[0, 0]) (it ignores K[0, 1]).",)
        kind, D = "fisheye", _opencv_matrix("D", 4, 1, [p[f"k{i}"] for i in range(1, 5)])
    elif camera.model.name == "unified":
        usage = ("cv2.omnidir.projectPoints(points, rvec, tvec, K, xi, D) (K[0, 1] is the skew).",)
        kind, D = "omnidir", _opencv_matrix("D", 1, 4, [p["k1"], p["k2"], p["p1"], p["p2"]])
        D += [f"xi: {_num(p['xi'])}"]
    else:
        coeffs = _opencv_coeffs(p, (4, 5, 8, 12))
        usage = ("cv2.projectPoints(points, rvec, tvec, camera_matrix, "
                 "distortion_coefficients).",)
        kind, k_name = "pinhole", "camera_matrix"
        D = _opencv_matrix("distortion_coefficients", 1, len(coeffs), coeffs)
    lines = ["%YAML:1.0", "---"]
    lines += _comments(camera, f"OpenCV's {kind} model, pixel centres at integers",
                       notes, usage)
    lines += [f'camera_model: "{kind}"', f"image_width: {w}", f"image_height: {h}"]
    lines += _opencv_matrix(k_name, 3, 3, K) + D + _area_keys(camera)
    if valid_angle is not None:
        lines.append(f"valid_angle_deg: {_num(valid_angle)}")
    return "\n".join(lines) + "\n"


def _kalibr(camera, p: dict, s: float, notes: list[str], valid_angle) -> str:
    """Kalibr's ``camchain.yaml`` with one camera, ``cam0`` (``rostopic`` is a placeholder)."""
    model = camera.model.name
    focal = [p["fx"], p["fy"], p["cx"], p["cy"]]
    if p["cx"] < 0 or p["cy"] < 0:
        raise ValueError(f"camera: Kalibr rejects a negative principal point, got cx = "
                         f"{p['cx']:.6g}, cy = {p['cy']:.6g}")
    if model == "pinhole":
        kind, intr, dist, coeffs = "pinhole", focal, "radtan", [0.0] * 4
    elif model == "fov":
        kind, intr, dist, coeffs = "pinhole", focal, "fov", [p["omega"]]
    elif model == "opencv":
        coeffs = _opencv_coeffs(p, (4,))
        if coeffs is None:
            raise ValueError(f"camera: Kalibr's pinhole-radtan holds k1, k2, p1, p2 of the opencv "
                             f"model, not {_nonzero(p, _OPENCV_COEFFS[4:])} (write the opencv or "
                             f"colmap format, or convert to another model)")
        kind, intr, dist = "pinhole", focal, "radtan"
    elif model == "kannala_brandt":
        kind, intr, dist = "pinhole", focal, "equidistant"
        coeffs = [p[f"k{i}"] for i in range(1, 5)]
    elif model == "unified":
        kind, intr, dist = "omni", [p["xi"]] + focal, "radtan"
        coeffs = [p["k1"], p["k2"], p["p1"], p["p2"]]
    else:
        first, second = ("xi", "alpha") if model == "double_sphere" else ("alpha", "beta")
        if p["alpha"] >= 1:
            raise ValueError(f"camera: Kalibr takes alpha in [0, 1) for the {model} model, got "
                             f"alpha = {p['alpha']:.6g}")
        kind = "ds" if model == "double_sphere" else "eucm"
        intr, dist, coeffs = [p[first], p[second]] + focal, "none", []
    h, w = camera.image_size
    lines = _comments(camera, f"a Kalibr camchain ({kind}-{dist}), pixel centres at integers",
                      notes, ("rostopic is a placeholder: set your camera's image topic.",))
    lines += ["cam0:", f"  camera_model: {kind}", f"  intrinsics: {_list(intr)}",
              f"  distortion_model: {dist}", f"  distortion_coeffs: {_list(coeffs)}",
              f"  resolution: [{w}, {h}]", "  cam_overlaps: []", "  rostopic: /cam0/image_raw"]
    lines += _area_keys(camera, "  ")
    if valid_angle is not None:
        lines.append(f"  valid_angle_deg: {_num(valid_angle)}")
    return "\n".join(lines) + "\n"


def _basalt(camera, p: dict, s: float, notes: list[str], valid_angle) -> str:
    """basalt's calibration JSON (cereal): one camera at the IMU's pose, IMU values zero as in
    basalt's own ``scripts/basalt_convert_kitti_calib.py``."""
    model = camera.model.name
    focal = {k: p[k] for k in ("fx", "fy", "cx", "cy")}
    if model == "pinhole":
        kind, intrinsics = "pinhole", focal
    elif model == "kannala_brandt":
        kind, intrinsics = "kb4", {**focal, **{f"k{i}": p[f"k{i}"] for i in range(1, 5)}}
    elif model == "unified":
        distortion = {k: p[k] for k in ("k1", "k2", "p1", "p2")}
        if any(distortion.values()):
            raise ValueError(f"camera: basalt's ucm is the unified model without distortion; "
                             f"k1, k2, p1, p2 must be 0, got {distortion} (convert to "
                             f"double_sphere or eucm for basalt)")
        scale = 1.0 + p["xi"]
        kind = "ucm"
        intrinsics = {"fx": p["fx"] / scale, "fy": p["fy"] / scale, "cx": p["cx"],
                      "cy": p["cy"], "alpha": p["xi"] / scale}
    elif model == "double_sphere":
        kind, intrinsics = "ds", {**focal, "xi": p["xi"], "alpha": p["alpha"]}
    elif model == "fov":   # basalt's fov_camera.hpp: [fx, fy, cx, cy, w], w our omega
        kind, intrinsics = "fov", {**focal, "w": p["omega"]}
    else:
        kind, intrinsics = "eucm", {**focal, "alpha": p["alpha"], "beta": p["beta"]}
    h, w = camera.image_size
    zeros = [0.0] * 3
    data = {"value0": {
        "T_imu_cam": [{"px": 0.0, "py": 0.0, "pz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0,
                       "qw": 1.0}],
        "intrinsics": [{"camera_type": kind, "intrinsics": intrinsics}],
        "resolution": [[w, h]],
        "calib_accel_bias": [0.0] * 9, "calib_gyro_bias": [0.0] * 12, "imu_update_rate": 0.0,
        "accel_noise_std": zeros, "gyro_noise_std": zeros, "accel_bias_std": zeros,
        "gyro_bias_std": zeros, "cam_time_offset_ns": 0, "vignette": [],
    }}
    if area_fields(camera):   # beside value0, which basalt reads (cereal ignores the rest)
        data["omniscape_torch"] = dict(area_fields(camera))
    return json.dumps(data, indent=4) + "\n"


def _orbslam3(camera, p: dict, s: float, notes: list[str], valid_angle) -> str:
    """ORB-SLAM3 settings, version 1.0 (``File.version: "1.0"``), for a monocular run: the
    camera, and the frame rate, ORB and viewer values ORB-SLAM3 requires (its TUM-VI example's).
    ORB-SLAM3 reads the values as single-precision floats."""
    kind = "KannalaBrandt8" if camera.model.name == "kannala_brandt" else "PinHole"
    names = ("fx", "fy", "cx", "cy") + (("k1", "k2", "k3", "k4") if kind == "KannalaBrandt8"
                                        else ())
    h, w = camera.image_size
    lines = ["%YAML:1.0", ""]
    lines += _comments(camera, f"ORB-SLAM3 settings ({kind}), pixel centres at integers", notes,
                       ("Camera.fps, ORBextractor.* and Viewer.* are the values of ORB-SLAM3's",
                        "Examples/Monocular/TUM-VI.yaml: set them for your sequence."))
    lines += ['File.version: "1.0"', "", f'Camera.type: "{kind}"', ""]
    lines += [f"Camera1.{n}: {_num(p[n])}" for n in names]
    lines += ["", f"Camera.width: {w}", f"Camera.height: {h}"] + _area_keys(camera)
    if valid_angle is not None:
        lines.append(f"valid_angle_deg: {_num(valid_angle)}")
    lines.append("")
    lines += [f"{key}: {value}" for key, value in _ORBSLAM3_DEFAULTS]
    return "\n".join(lines) + "\n"


def _colmap(camera, p: dict, s: float, notes: list[str], valid_angle) -> str:
    """COLMAP's ``cameras.txt`` with one camera, id 1; ``cx, cy`` shifted by +0.5 (COLMAP puts
    the top-left pixel's centre at (0.5, 0.5))."""
    h, w = camera.image_size
    params = [p["fx"], p["fy"], p["cx"] + 0.5, p["cy"] + 0.5]
    model = camera.model.name
    # COLMAP's extra parameters are ours in our order (models.h), by name
    extra_names = {"pinhole": (), "kannala_brandt": ("k1", "k2", "k3", "k4"), "fov": ("omega",),
                   "division": ("k",), "thin_prism_fisheye": camera.param_names[4:12],
                   "fisheye624": camera.param_names[4:16]}
    if model == "opencv":
        coeffs = _opencv_coeffs(p, (4, 8))
        if coeffs is None:
            raise ValueError(f"camera: COLMAP's FULL_OPENCV has no thin prism: "
                             f"{_nonzero(p, _OPENCV_COEFFS[8:])} (write the opencv format, or "
                             f"convert to another model)")
        kind = "OPENCV" if len(coeffs) == 4 else "FULL_OPENCV"
        params += coeffs
    else:
        kind = {"pinhole": "PINHOLE", "kannala_brandt": "OPENCV_FISHEYE", "fov": "FOV",
                "division": "DIVISION", "thin_prism_fisheye": "THIN_PRISM_FISHEYE",
                "fisheye624": "RAD_TAN_THIN_PRISM_FISHEYE"}[model]
        params += [p[n] for n in extra_names[model]]
    extra = ("cx, cy are omniscape_torch's + 0.5 (COLMAP's top-left pixel centre is (0.5, 0.5)).",)
    extra += tuple(_area_keys(camera))
    if valid_angle is not None:
        extra += (f"valid_angle_deg: {_num(valid_angle)}",)
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", "# Number of cameras: 1"]
    lines += _comments(camera, f"COLMAP's {kind}", notes, extra)
    lines.append(" ".join(["1", kind, str(w), str(h)] + [_num(v) for v in params]))
    return "\n".join(lines) + "\n"
