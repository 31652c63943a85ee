"""OCamCalib's ``calib_results.txt`` for a dataset's cameras, as the OmniScape dataset ships them.

The OmniScape dataset gives each camera's intrinsics as OCamCalib's polynomial model
(Scaramuzza et al., IROS 2006). Ours are equidistant fisheyes and unified catadioptric cameras
(any registered model), so each is converted: `fit_polynomial` fits a ``scaramuzza``
camera to it over its valid area (`omniscape_torch.calibration.convert`, least squares on
one pixel grid, errors measured on a second grid offset by half a step) for each degree of
``DEGREES`` in turn, and keeps the first whose held-out largest error is within
``TOLERANCE_PX``; `write_calib_results` writes it with ``Camera.to_ocamcalib``, whose
inverse polynomial (OCamCalib's ``world2cam``) is fitted within ``INVPOL_PX``. So both of
OCamCalib's functions stay within 0.05 px of the camera: ``cam2world`` (the direct polynomial)
within ``TOLERANCE_PX`` and ``world2cam`` within ``TOLERANCE_PX + INVPOL_PX``.

The file holds no field of view: a catadioptric camera's blind central disc and the edge of a
fisheye's image circle are in the record written beside it (``fov_deg``, ``blind_fov_deg``), and
the polynomial camera stands for the camera within that area only (outside it the polynomial
was not fitted). `polynomial_camera` reads the file back with that area.

The record (``"ocamcalib"`` in the camera's JSON)::

    {"file": "calib_results.txt", "model": "scaramuzza", "degree": 5,
     "rms_px": ..., "max_px": ...,          held-out pixel error of the direct polynomial
     "invpol_max_px": ...,                  the inverse polynomial's error at its samples
     "within_tolerance": true, "fov_deg": 190.0, "blind_fov_deg": null,
     "fit": {"degrees": [4, 5, 6, 7, 8], "tolerance_px": 0.04, "grid": 32}}

A camera that is radially symmetric about its principal point (equal focal lengths, no
tangential distortion: every preset; checked numerically by `radially_symmetric`) keeps
its centre and no affine term (``c = 1, d = e = 0``) in the file, as it has them; only the
polynomial is fitted. Otherwise OCamCalib's centre and affine term are fitted too.

The conversion starts from its own linear least-squares polynomial (the module docstring of
`omniscape_torch.calibration.convert`), solved by the ``gelsd`` driver: torch's default CPU
driver depends on the memory alignment of its inputs, and the fit would then end a few ulps
apart from run to run, and so would the file's digits. For the same reason, and for speed, the
fit runs on one thread (the previous thread count is restored after):
its sums then do not depend on the machine's thread count, and on a few thousand samples the
start-up of several threads costs more than it saves (2-3x the time on a busy 2-core machine).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import torch

from ..calibration import convert
from ..cameras import Camera
from ..cameras._checks import check_one_camera
from ..cameras.formats import fit_invpol

__all__ = ["DEGREES", "GRID", "INVPOL_PX", "TOLERANCE_PX", "PolynomialFit", "cached_record",
           "fit_polynomial", "polynomial_camera", "radially_symmetric", "write_calib_results"]

#: Polynomial degrees tried, smallest first (OCamCalib's calibrations use 4 or 5).
DEGREES = (4, 5, 6, 7, 8)
#: Largest held-out pixel error accepted for the direct polynomial: 0.05 px less the inverse
#: polynomial's ``INVPOL_PX``, so that OCamCalib's ``world2cam`` stays within 0.05 px too.
TOLERANCE_PX = 0.04
#: The inverse polynomial's largest error at its samples, pixels (OCamCalib's own target).
INVPOL_PX = 0.01
#: Samples per image side of the conversion's fitted and held-out grids: 0.1-0.2 s a degree
#: on one core; at 48 (the conversion's default) the degrees and errors of the rig's cameras
#: are the same to 0.001 px.
GRID = 32


@dataclass
class PolynomialFit:
    """Outcome of `fit_polynomial`.

    Attributes:
        camera: the ``scaramuzza`` camera, with the source's ``fov`` and ``blind_fov``.
        degree: its polynomial degree.
        rms_px: RMS pixel distance on the held-out grid.
        max_px: largest pixel distance on the held-out grid.
        invpol_max_px: the inverse polynomial's largest error at its samples, pixels.
        within_tolerance: ``max_px <= tolerance_px`` (else the best degree tried).
        fit: the settings, ``{"degrees": [...], "tolerance_px": ..., "grid": ...}``.
    """

    camera: Camera
    degree: int
    rms_px: float
    max_px: float
    invpol_max_px: float
    within_tolerance: bool
    fit: dict

    def record(self, file: str) -> dict:
        """The JSON record of the module docstring, for the file named ``file``."""
        cam = self.camera
        return {"file": file, "model": "scaramuzza", "degree": self.degree,
                "rms_px": self.rms_px, "max_px": self.max_px,
                "invpol_max_px": self.invpol_max_px, "within_tolerance": self.within_tolerance,
                "fov_deg": None if cam.fov is None else math.degrees(cam.fov),
                "blind_fov_deg": None if cam.blind_fov is None else math.degrees(cam.blind_fov),
                "fit": dict(self.fit)}


def _settings(degrees: Sequence[int], tolerance_px: float, grid: int) -> dict:
    return {"degrees": [int(d) for d in degrees], "tolerance_px": float(tolerance_px),
            "grid": int(grid)}


def _centre(camera: Camera) -> torch.Tensor:
    """The principal point ``(2,)`` (u, v), float64."""
    p = camera.params.detach().double().cpu()
    return p[:2] if camera.model.name == "scaramuzza" else p[2:4]


def radially_symmetric(camera: Camera, *, rings: int = 8, azimuths: int = 12,
                       tol: float = 1e-9) -> bool:
    """Whether ``camera``'s rays depend on the pixel's distance to the principal point only,
    and turn with the pixel about it (no affine term, no tangential distortion): the angle to
    the axis is the same around each of ``rings`` circles about the centre (radii up to the
    shorter half side), and each ray's azimuth is its pixel's, within ``tol`` radians, where
    the model unprojects them (its domain, without ``fov``)."""
    h, w = camera.image_size
    centre = _centre(camera)
    radius = torch.arange(1, rings + 1, dtype=torch.float64) / rings * (0.5 * min(h, w) - 0.5)
    phi = torch.arange(azimuths, dtype=torch.float64) * (2 * math.pi / azimuths)
    offset = radius[:, None, None] * torch.stack((phi.cos(), phi.sin()), -1)   # [R, A, 2]
    params = camera.params.detach().double().cpu()
    rays, valid = camera.model.unproject(centre + offset, params)
    theta = torch.atan2(rays[..., :2].norm(dim=-1), rays[..., 2])
    turn = torch.atan2(rays[..., 1], rays[..., 0]) - phi
    turn = torch.remainder(turn + math.pi, 2 * math.pi) - math.pi
    full = valid.all(-1)                     # rings the model unprojects all around
    if not bool(full.any()) or not bool(torch.isfinite(rays[valid]).all()):
        return False
    spread = (theta - theta[:, :1]).abs()[full]
    return bool(spread.max() <= tol) and bool(turn.abs()[valid].max() <= tol)


@contextlib.contextmanager
def _one_thread():
    """Run the block on one intra-op thread, then restore the previous count (module
    docstring)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def fit_polynomial(camera: Camera, *, degrees: Sequence[int] = DEGREES,
                   tolerance_px: float = TOLERANCE_PX, grid: int = GRID) -> PolynomialFit:
    """OCamCalib's polynomial model of ``camera`` (module docstring): the smallest degree of
    ``degrees`` whose held-out largest pixel error is within ``tolerance_px`` and whose inverse
    polynomial reaches ``INVPOL_PX``, else the degree with the smallest error.

    Args:
        camera: one camera of any lens model (its ``fov`` and ``blind_fov`` bound the area).
        degrees: the degrees tried, in this order.
        tolerance_px: the largest held-out error accepted, pixels.
        grid: samples per image side of the fitted and the held-out grids.

    Returns:
        A `PolynomialFit`; check ``within_tolerance``. Runs on one thread (module
        docstring).

    Raises:
        TypeError, ValueError: not one camera, bad settings, too few valid pixels.
        RuntimeError: no degree gave a polynomial camera covering the camera's valid area.
    """
    check_one_camera(camera)
    degrees = tuple(degrees)
    if not degrees or any(isinstance(d, bool) or not isinstance(d, int) or d < 2
                          for d in degrees):
        raise ValueError(f"degrees: expected integers >= 2, got {degrees!r}")
    if not (isinstance(tolerance_px, (int, float)) and tolerance_px > 0):
        raise ValueError(f"tolerance_px: expected a positive number, got {tolerance_px!r}")
    if isinstance(grid, bool) or not isinstance(grid, int) or grid < 4:
        raise ValueError(f"grid: expected an integer >= 4, got {grid!r}")
    with _one_thread():
        return _fit_polynomial(camera, degrees, tolerance_px, grid)


def _fit_polynomial(camera: Camera, degrees: tuple[int, ...], tolerance_px: float,
                    grid: int) -> PolynomialFit:
    """`fit_polynomial` once its arguments are checked."""
    settings = _settings(degrees, tolerance_px, grid)
    # a1 = 0 as in OCamCalib; a symmetric camera keeps its centre and no affine term
    freeze = ("a1", "center", "affine") if radially_symmetric(camera) else ("a1",)
    best: PolynomialFit | None = None
    failures = []
    for degree in degrees:
        result = convert(camera, "scaramuzza", degree=degree, grid=grid, minimax=0,
                         freeze=freeze)
        if result.camera is None or not math.isfinite(result.max_px) \
                or result.unrepresentable > 0:
            failures.append(f"degree {degree}: "
                            + ("the fit left the model's range" if result.camera is None else
                               f"{result.unrepresentable:.1%} of the area not represented"))
            continue
        poly = Camera("scaramuzza", result.camera.params.detach().double().cpu(),
                      camera.image_size, fov=camera.fov, blind_fov=camera.blind_fov)
        try:
            _, invpol_error = fit_invpol(poly, max_error=INVPOL_PX)
        except ValueError as err:
            failures.append(f"degree {degree}: {err}")
            continue
        fit = PolynomialFit(poly, degree, result.rms_px, result.max_px, invpol_error,
                            result.max_px <= tolerance_px, settings)
        if fit.within_tolerance:
            return fit
        if best is None or fit.max_px < best.max_px:
            best = fit
    if best is None:
        raise RuntimeError(f"camera: no polynomial model of degree {list(degrees)} covers the "
                           f"{camera.model.name} camera's valid area: " + "; ".join(failures))
    return best


def write_calib_results(fit: PolynomialFit, path: str | Path) -> dict:
    """Write ``fit.camera`` as OCamCalib's ``calib_results.txt`` at ``path`` (atomically; the
    inverse polynomial within ``INVPOL_PX``) and return its record (module docstring)."""
    path = Path(path)
    fit.camera.to_ocamcalib(path, max_error=INVPOL_PX)
    return fit.record(path.name)


def cached_record(record, path: str | Path, source: dict, written_source,
                  *, degrees: Sequence[int] = DEGREES, tolerance_px: float = TOLERANCE_PX,
                  grid: int = GRID) -> dict | None:
    """``record`` when it still describes the file at ``path`` (a rerun skips the fit), else
    None: the camera it was fitted to (``written_source``, the camera JSON stored with it) is
    ``source`` (``Camera.to_dict()``), the fit's settings are these, and the file exists."""
    if not isinstance(record, dict) or written_source != source:
        return None
    path = Path(path)
    if record.get("file") != path.name or record.get("fit") != _settings(degrees, tolerance_px,
                                                                          grid):
        return None
    return record if path.is_file() else None


def polynomial_camera(path: str | Path, record: dict, **kwargs) -> Camera:
    """The ``scaramuzza`` camera of the file at ``path`` with the valid area of its ``record``
    (``fov_deg``, ``blind_fov_deg``); ``kwargs`` go to ``Camera.from_ocamcalib``."""
    if not isinstance(record, dict):
        raise TypeError(f"record: expected the file's JSON record, got {type(record).__name__}")
    fov, blind = record.get("fov_deg"), record.get("blind_fov_deg")
    return Camera.from_ocamcalib(path, fov=None if fov is None else math.radians(fov),
                                 blind_fov=None if blind is None else math.radians(blind),
                                 **kwargs)
