"""Calibration formats: OCamCalib's ``calib_results.txt``, OpenCV ``fisheye``/``omnidir``, JSON.

Conventions are converted here and only here: OCamCalib stores its centre as (row, column),
0-based, and its sensor axes as (row, column); OpenCV's pixel centres are at integers, like ours.

The readers take the camera class to build (``cls``): they are ``Camera``'s constructors
(``Camera.from_ocamcalib``, ``from_dict``, ...), which call them, and this module needs no
import of ``camera.py`` (which imports it). The files of other tools (OpenCV YAML, Kalibr,
basalt, ORB-SLAM3, COLMAP) are written by ``export.py``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..io.atomic import atomic_write_text
from .registry import get_model
from .scaramuzza import scaramuzza_project

# --------------------------------------------------------------------------------------------
# OCamCalib
# --------------------------------------------------------------------------------------------

_OCAM_SECTIONS = (
    ("#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). "
     "These are used by cam2world"),
    ("#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). "
     "These are used by world2cam"),
    '#center: "row" and "column", starting from 0 (C convention)',
    '#affine parameters "c", "d", "e"',
    '#image size: "height" and "width"',
)

#: A sixth section after OCamCalib's five, which its readers (``get_ocam_model``, the MATLAB
#: toolbox) never reach: the camera's ``fov`` and ``blind_fov``, full angles in degrees, ``-``
#: where unset (``export.py``: every format keeps the imaged area).
_OCAM_AREA = ('#field of view and blind cone: full angles in degrees, "-" for none '
              '(omniscape_torch; OCamCalib reads only the sections above)')


def _ocam_sections(path: Path) -> list[tuple[int, list[str]]]:
    """Group the data lines of a calib_results.txt under its five comment headers."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file") from None
    sections: list[tuple[int, list[str]]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line.startswith("#"):
            sections.append((number, []))
        elif line:
            if not sections:
                raise ValueError(f"{path}, line {number}: data before the first '#' header")
            if not sections[-1][1]:
                sections[-1] = (number, [])
            sections[-1][1].extend(line.split())
    if len(sections) < 5:
        raise ValueError(f"{path}: expected 5 sections (direct polynomial, inverse polynomial, "
                         f"centre, affine, image size), found {len(sections)}; is the file "
                         f"truncated?")
    return sections


def _numbers(path: Path, line: int, tokens: list[str], what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise ValueError(f"{path}, line {line}: {what}: expected numbers, got "
                         f"{' '.join(tokens)!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{path}, line {line}: {what}: values must be finite, got {values}")
    return values


def _counted(path: Path, line: int, tokens: list[str], what: str) -> list[float]:
    values = _numbers(path, line, tokens, what)
    if not values or values[0] != int(values[0]) or values[0] < 1:
        raise ValueError(f"{path}, line {line}: {what}: expected a coefficient count first, got "
                         f"{tokens[:1]}")
    n = int(values[0])
    if len(values) - 1 != n:
        raise ValueError(f"{path}, line {line}: {what}: the count says {n} coefficients, "
                         f"found {len(values) - 1}")
    return values[1:]


def read_ocamcalib(cls, path: str | Path, *, dtype: torch.dtype = torch.float64, **kwargs):
    """Read OCamCalib's ``calib_results.txt`` as a ``scaramuzza`` camera.

    The centre (row, column) becomes (cx, cy) = (column, row); ``c, d, e`` and the direct
    polynomial are kept as written. The inverse polynomial is kept as ``camera.invpol`` for
    ``ot.cameras.scaramuzza.scaramuzza_project(..., invpol=...)``, OCamCalib's fast
    ``world2cam``; ``Camera.project`` inverts the direct polynomial exactly instead.

    Args:
        path: the file.
        dtype: dtype of the parameters.
        **kwargs: passed to ``Camera`` (``fov``, ``learnable``).

    Raises:
        ValueError: naming the file and line of a malformed or truncated file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such calibration file")
    sections = _ocam_sections(path)
    (l_pol, t_pol), (l_inv, t_inv), (l_c, t_c), (l_a, t_a), (l_s, t_s) = sections[:5]
    pol = _counted(path, l_pol, t_pol, "direct polynomial")
    invpol = _counted(path, l_inv, t_inv, "inverse polynomial")
    centre = _numbers(path, l_c, t_c, "centre")
    affine = _numbers(path, l_a, t_a, "affine parameters")
    size = _numbers(path, l_s, t_s, "image size")
    for values, n, line, what in ((centre, 2, l_c, "centre (row column)"),
                                  (affine, 3, l_a, "affine parameters (c d e)"),
                                  (size, 2, l_s, "image size (height width)")):
        if len(values) != n:
            raise ValueError(f"{path}, line {line}: {what}: expected {n} numbers, got "
                             f"{len(values)}")
    if any(v != int(v) or v <= 0 for v in size):
        raise ValueError(f"{path}, line {l_s}: image size: expected positive integers, got {size}")
    row, col = centre
    params = torch.tensor([col, row, *affine, *pol], dtype=dtype)
    if len(sections) > 5 and _OCAM_AREA in path.read_text():   # ours, not another tool's
        kwargs = {**_ocam_area(path, *sections[5]), **kwargs}
    try:
        camera = cls("scaramuzza", params, (int(size[0]), int(size[1])), **kwargs)
    except ValueError as err:
        # name the line the offending value came from: the polynomial's a0 or the affine part
        line = l_pol if " a0 " in str(err) else l_a if "affine" in str(err) else None
        where = f"{path}, line {line}" if line is not None else str(path)
        raise ValueError(f"{where}: {err}") from None
    camera.invpol = torch.tensor(invpol, dtype=dtype)
    return camera


def _ocam_area(path: Path, line: int, tokens: list[str]) -> dict:
    """``fov`` and ``blind_fov`` (radians) of the ``_OCAM_AREA`` section."""
    if len(tokens) != 2:
        raise ValueError(f"{path}, line {line}: field of view and blind cone: expected 2 "
                         f"values (degrees or -), got {len(tokens)}")
    values = [None if t == "-" else _numbers(path, line, [t], "field of view")[0]
              for t in tokens]
    return {name: None if v is None else math.radians(v)
            for name, v in zip(("fov", "blind_fov"), values)}


def fit_invpol(camera, *, max_error: float = 0.01, max_degree: int = 20,
               theta_range: tuple[float, float] = (-math.pi / 2, 1.20), step: float = 0.01
               ) -> tuple[np.ndarray, float]:
    """Fit OCamCalib's inverse polynomial ``rho(t)`` the way its ``findinvpoly`` does.

    ``t = theta - pi / 2`` (OCamCalib's elevation) is sampled every ``step`` over ``theta_range``,
    kept where the model is valid and ``rho`` is inside the image's half-diagonal, ``rho(t)`` is
    computed exactly (Newton), and the degree grows from 2 until the largest fitting error is
    below ``max_error`` pixels.

    Returns:
        ``(invpol ascending, max error in pixels)``.
    """
    if camera.model.name != "scaramuzza" or camera.batch_shape != ():
        raise ValueError("camera: fit_invpol needs one scaramuzza camera")
    params = camera.params.detach().double().clone()
    params[:5] = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64)
    t = torch.arange(theta_range[0], theta_range[1] + step / 2, step, dtype=torch.float64)
    theta = t + math.pi / 2
    points = torch.stack((torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)), -1)
    pixels, valid = scaramuzza_project(points, params)
    h, w = camera.image_size
    rho = pixels[:, 0]
    keep = valid & (rho <= math.hypot(w / 2, h / 2))
    t, rho = t[keep].numpy(), rho[keep].numpy()
    if len(t) < 3:
        raise ValueError("camera: too few valid angles to fit an inverse polynomial")
    for degree in range(2, max_degree + 1):
        coeffs = np.polynomial.polynomial.polyfit(t, rho, degree)
        err = float(np.abs(np.polynomial.polynomial.polyval(t, coeffs) - rho).max())
        if err < max_error:
            return coeffs, err
    raise ValueError(f"camera: no inverse polynomial of degree <= {max_degree} fits within "
                     f"{max_error} px (best {err:.3g} px)")


def write_ocamcalib(camera, path: str | Path, *, max_error: float = 0.01) -> Path:
    """Write ``camera`` (one ``scaramuzza`` camera) as OCamCalib's ``calib_results.txt``.

    The layout is the one OCamCalib's ``export_data`` writes and its C ``get_ocam_model`` reads;
    the inverse polynomial is refitted (``fit_invpol``, within ``max_error`` px); numbers are
    written with 17 significant digits; the camera's ``fov`` / ``blind_fov``, where set, in a
    sixth section that OCamCalib's readers never reach. Written atomically.
    """
    if camera.model.name != "scaramuzza" or camera.batch_shape != ():
        raise ValueError(f"camera: OCamCalib files hold one scaramuzza camera, got "
                         f"{camera.model.name} with batch shape {tuple(camera.batch_shape)}")
    invpol, _ = fit_invpol(camera, max_error=max_error)
    p = camera.params.detach().double().cpu().tolist()
    cx, cy, c, d, e, pol = p[0], p[1], p[2], p[3], p[4], p[5:]
    h, w = camera.image_size
    g = lambda v: f"{v:.17g}"  # noqa: E731
    lines = [
        _OCAM_SECTIONS[0], "", " ".join([str(len(pol))] + [g(v) for v in pol]) + " ", "",
        _OCAM_SECTIONS[1], "", " ".join([str(len(invpol))] + [g(v) for v in invpol]) + " ", "",
        _OCAM_SECTIONS[2], "", f"{g(cy)} {g(cx)}", "",
        _OCAM_SECTIONS[3], "", f"{g(c)} {g(d)} {g(e)}", "",
        _OCAM_SECTIONS[4], "", f"{h} {w}", "",
    ]
    if camera.fov is not None or camera.blind_fov is not None:
        angles = [("-" if a is None else g(math.degrees(a))) for a in (camera.fov,
                                                                       camera.blind_fov)]
        lines += [_OCAM_AREA, "", " ".join(angles), ""]
    return atomic_write_text(path, "\n".join(lines))


# --------------------------------------------------------------------------------------------
# OpenCV
# --------------------------------------------------------------------------------------------

def _as_array(value, name: str, shapes: tuple[tuple[int, ...], ...]) -> np.ndarray:
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected an array of numbers, got {type(value).__name__}"
                        ) from None
    if arr.shape not in shapes:
        raise ValueError(f"{name}: expected shape {' or '.join(map(str, shapes))}, got "
                         f"{arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: values must be finite, got {arr.tolist()}")
    return arr


def _intrinsics(K) -> list[float]:
    """``fx, fy, cx, cy`` of ``K``, and its skew ``s = K[0, 1]`` where non-zero."""
    K = _as_array(K, "K", ((3, 3),))
    if K[1, 0] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise ValueError(f"K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    return [K[0, 0], K[1, 1], K[0, 2], K[1, 2]] + ([K[0, 1]] if K[0, 1] != 0 else [])


def _one_camera(camera, model: str) -> dict[str, float]:
    if camera.model.name != model or camera.batch_shape != ():
        raise ValueError(f"camera: expected one {model} camera, got {camera.model.name} with "
                         f"batch shape {tuple(camera.batch_shape)}")
    return dict(zip(camera.param_names, camera.params.detach().double().cpu().tolist()))


def _k_matrix(p: dict[str, float]) -> np.ndarray:
    return np.array([[p["fx"], p.get("s", 0.0), p["cx"]], [0.0, p["fy"], p["cy"]],
                     [0.0, 0.0, 1.0]])


def farthest_angle(camera) -> float:
    """Largest angle (radians) between the optical axis and the ray of a valid pixel centre of
    a radially symmetric camera (Kannala-Brandt, pinhole: the models the 90-degree limit meets).

    The angle grows with the distance from the principal point in normalised coordinates, so it
    is largest at an image corner when the whole border is valid; otherwise the model's domain
    or ``fov`` cuts the image and the valid pixels reach ``camera.max_angle()``. Only the border
    is unprojected (a whole ray grid costs seconds for a Kannala-Brandt camera).
    """
    limit = float(camera.max_angle())
    if limit < math.pi / 2:
        return limit
    h, w = camera.image_size
    kw = dict(dtype=camera.params.dtype, device=camera.params.device)
    u, v = torch.arange(w, **kw), torch.arange(h, **kw)
    border = torch.cat([
        torch.stack((u, torch.zeros_like(u)), -1), torch.stack((u, torch.full_like(u, h - 1)), -1),
        torch.stack((torch.zeros_like(v), v), -1), torch.stack((torch.full_like(v, w - 1), v), -1),
    ])   # [2 (H + W), 2]
    with torch.no_grad():
        rays, valid = camera.unproject(border)
    if not bool(valid.all()):
        return limit
    theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
    return float(theta.max())


def from_opencv_fisheye(cls, K, D, image_size: tuple[int, int], *, dtype=torch.float64,
                        **kwargs):
    """``cv2.fisheye`` intrinsics ``K (3, 3)`` and ``D (4,)`` as a ``kannala_brandt`` camera;
    ``K[0, 1]`` (``fx alpha``, as ``cv2.fisheye.calibrate`` returns it) is the skew ``s``."""
    D = _as_array(D, "D", ((4,), (1, 4), (4, 1))).ravel()
    k = _intrinsics(K)
    return cls("kannala_brandt", torch.tensor([*k[:4], *D, *k[4:]], dtype=dtype), image_size,
               **kwargs)


def to_opencv_fisheye(camera, *, accept_fov: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(K (3, 3), D (4,))`` of one ``kannala_brandt`` camera, for ``cv2.fisheye``; its skew
    ``s`` in ``K[0, 1]`` (as ``cv2.fisheye.calibrate`` writes it: ``projectPoints`` ignores
    ``K[0, 1]`` and takes ``alpha = K[0, 1] / K[0, 0]``).

    Raises:
        ValueError: the camera sees 90 degrees or more off its axis, where ``cv2.fisheye``
            folds (``atan(r / z)``), unless ``accept_fov``.
    """
    p = _one_camera(camera, "kannala_brandt")
    angle = math.degrees(farthest_angle(camera))
    if angle >= 90.0 and not accept_fov:
        raise ValueError(f"camera: it sees up to {angle:.2f} deg off its optical axis, but "
                         f"cv2.fisheye folds rays at 90 deg and beyond (atan(r / z)); restrict "
                         f"its fov below 180 deg, or pass accept_fov=True")
    return _k_matrix(p), np.array([p["k1"], p["k2"], p["k3"], p["k4"]])


def from_opencv_omnidir(cls, K, D, xi, image_size: tuple[int, int], *, dtype=torch.float64,
                        **kwargs):
    """``cv2.omnidir`` intrinsics ``K (3, 3)`` (its skew ``K[0, 1]`` is ``s``), ``D (k1, k2, p1,
    p2)`` and ``xi`` as a ``unified`` camera."""
    D = _as_array(D, "D", ((4,), (1, 4), (4, 1))).ravel()
    xi = _as_array(xi, "xi", ((), (1,), (1, 1))).ravel()
    k = _intrinsics(K)
    return cls("unified", torch.tensor([*k[:4], xi[0], *D, *k[4:]], dtype=dtype), image_size,
               **kwargs)


def to_opencv_omnidir(camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K (3, 3), D (1, 4), xi (1,))`` of one ``unified`` camera, for ``cv2.omnidir`` (its
    skew ``s`` in ``K[0, 1]``)."""
    p = _one_camera(camera, "unified")
    return _k_matrix(p), np.array([[p["k1"], p["k2"], p["p1"], p["p2"]]]), np.array([p["xi"]])


# --------------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------------

def camera_to_dict(camera) -> dict:
    """``{"model", "image_size": [H, W], "fov_deg", "blind_fov_deg", "params": {name: value}}``;
    for a batch,
    ``"params"`` is a list of such objects. Angles are in degrees in the file."""
    names = camera.param_names
    rows = camera.params.detach().double().cpu().reshape(-1, len(names)).tolist()
    params = [dict(zip(names, row)) for row in rows]
    out = {"model": camera.model.name, "image_size": list(camera.image_size),
           "fov_deg": None if camera.fov is None else math.degrees(camera.fov),
           "blind_fov_deg": (None if camera.blind_fov is None
                             else math.degrees(camera.blind_fov)),
           "params": params[0] if camera.batch_shape == () else params}
    if camera.batch_shape not in ((), (len(rows),)):
        out["batch_shape"] = list(camera.batch_shape)
    if camera.invpol is not None:
        out["invpol"] = camera.invpol.detach().double().cpu().tolist()
    return out


def camera_from_dict(cls, data: dict, *, dtype: torch.dtype = torch.float64, **kwargs):
    """Inverse of ``camera_to_dict``; ``fov`` / ``blind_fov`` in ``kwargs`` override the
    file's."""
    if not isinstance(data, dict):
        raise TypeError(f"data: expected a dict, got {type(data).__name__}")
    missing = {"model", "image_size", "params"} - set(data)
    if missing:
        raise ValueError(f"data: missing keys {sorted(missing)}")
    model = get_model(data["model"])
    rows = data["params"] if isinstance(data["params"], list) else [data["params"]]
    values = []
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise ValueError(f"data: params[{i}] must map parameter names to values")
        names = model.names_for(len(row))
        if list(row) != list(names):
            raise ValueError(f"data: params[{i}] of the {model.name} model must be "
                             f"{list(names)} in this order, got {list(row)}")
        values.append([row[n] for n in names])
    params = torch.tensor(values, dtype=dtype)
    if not isinstance(data["params"], list):
        params = params[0]
    elif "batch_shape" in data:
        params = params.reshape(*data["batch_shape"], params.shape[-1])
    fov, blind = data.get("fov_deg"), data.get("blind_fov_deg")
    area = {"fov": None if fov is None else math.radians(fov),
            "blind_fov": None if blind is None else math.radians(blind)}
    camera = cls(model, params, tuple(data["image_size"]), **{**area, **kwargs})
    if data.get("invpol") is not None:
        camera.invpol = torch.tensor(data["invpol"], dtype=dtype)
    return camera


def save_json(camera, path: str | Path) -> Path:
    """Write ``camera_to_dict(camera)`` to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(camera_to_dict(camera), indent=2) + "\n")


def load_json(cls, path: str | Path, **kwargs):
    """Read a camera written by ``save_json``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}, line {err.lineno}: not valid JSON ({err.msg})") from None
    try:
        return camera_from_dict(cls, data, **kwargs)
    except (ValueError, TypeError) as err:
        raise type(err)(f"{path}: {err}") from None
