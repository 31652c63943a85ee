"""The whole of `omniscape-torch fit` as one function a notebook can call: `calibrate`.

`fit` finds the intrinsics; `calibrate` also judges what the views leave undetermined, as the
command line does, and writes the files (`Calibration.write`):

1. the fit (`fit`, every option of it), refused (`Calibration.failed`) where it did not
   converge, except a least-squares minimum that only fails the near-degenerate check (written
   and flagged, unless `strict`);
2. the area the lens sees (`Calibration.fov`): `fov` if given; else the image circle of the
   views' `images` (`image_circle` of their mean); else, where it cannot be measured (a dark
   centre or border) or there are no images (correspondences alone give no image circle),
   the corners' reach (twice the largest angle off axis of the corners' rays through the
   fitted camera); or the whole sensor where the images are lit to its edges. A sensor's
   corners may lie far past what the lens sees (the fitted polynomial of a 190-degree lens
   on a 1280 x 1024 sensor puts them 130 to 150 degrees off axis), so the coverage and the
   predicted error are judged over that area, never over the whole sensor unless the images
   show it lit (before issue 44, correspondences were judged over the whole sensor: a
   well-covered 21-view fit could count fewer than half of its cells). Over the corners' reach
   the angle check passes by construction: give `fov` to judge how far short of the lens's
   edge the corners stop. `camera.json` keeps the area as the camera's `fov`, except the
   corners' reach of bare correspondences (the lens may see past it);
3. the coverage and the predicted pixel error over that area (`assess_coverage`), and with
   `leave_one_out` the same error measured by refitting without each view;
4. the blind cone of a catadioptric camera (`blind_cone` of the views' maximum), kept in
   `camera.json`.

Measuring the area or the cone never turns a finished fit into an error: a failure falls back
(to the corners' reach, or no cone) and `Calibration.fov_note` says why.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..io.atomic import publish
from .convert import blind_cone, image_circle
from .coverage import Coverage, Resampling, assess_coverage, leave_one_out as _leave_one_out
from .files import Correspondences
from .fit import FitResult, correlated_pairs, fit

#: Images of the views read to measure the image circle and the blind cone (at most).
MEASURED_VIEWS = 8


class FitNotWritten(OSError):
    """`Calibration.write` could not write its files (disk full, a path in the way...): the
    `OSError` that stopped it, and `kept`, the folder where every file of the fit still is."""

    def __init__(self, err: OSError, kept: Path) -> None:
        super().__init__(err.errno, err.strerror or str(err), err.filename)
        self.kept = kept


@dataclass
class Calibration:
    """What `calibrate` found (module docstring).

    Attributes:
        result: the `FitResult`.
        data: the correspondences it was fitted to.
        coverage: the coverage and predicted error over `fov` (None where `failed`).
        fov: the full field of view (radians) over which the views were judged, kept as the
            camera's `fov` in `camera.json`; None: the whole sensor.
        fov_source: where `fov` came from: `"--fov"` (given: `fov=`), `"image circle"`,
            `"corners' reach"`, `"whole sensor"`.
        fov_note: why the image circle was not used, where it was looked for (else None).
        blind_fov: the blind cone (full angle, radians) dark in every image, or None.
        resampling: the leave-one-view-out check (None without `leave_one_out`).
        source: where the correspondences came from, for the report.
        board: the board's spec, for the report.
        strict: a near-degenerate fit counts as failed.
        images: the images the corners were detected in (they are then written as
            `correspondences.txt` too), or None.
    """

    result: FitResult
    data: Correspondences
    coverage: Coverage | None = None
    fov: float | None = None
    fov_source: str = "whole sensor"
    fov_note: str | None = None
    blind_fov: float | None = None
    resampling: Resampling | None = None
    source: str | None = None
    board: str | None = None
    strict: bool = False
    images: object = None

    @property
    def near_degenerate(self) -> bool:
        """A least-squares minimum whose views leave a combination of intrinsics undetermined
        (`FitResult.near_degenerate` names them); written unless `strict`."""
        return not self.result.converged and self.result.only_near_degenerate

    @property
    def failed(self) -> bool:
        """Nothing to write: the fit did not converge (or is near-degenerate with `strict`)."""
        return not self.result.converged and (self.strict or not self.near_degenerate)

    @property
    def correlated(self) -> str:
        """The near-degenerate parameters and their correlations, one phrase (else "")."""
        return correlated_pairs(self.result.near_degenerate) if self.near_degenerate else ""

    @property
    def poorly_covered(self) -> bool:
        """The coverage check failed: the views do not pin the camera down over `fov`."""
        return self.coverage is not None and not self.coverage.ok

    @property
    def resampling_limit(self) -> float:
        """The largest predicted pixel error a fit may have (pixels: the coverage's limit)."""
        return float(self.coverage.thresholds["max_pixel_error"]) if self.coverage else math.nan

    @property
    def poorly_resampled(self) -> bool:
        """The refits without each view move the projections by more than the limit."""
        return (self.resampling is not None
                and not self.resampling.pixel_error <= self.resampling_limit)

    @property
    def well_constrained(self) -> bool:
        """Written, not near-degenerate, and both the coverage and the refits (if run) pass:
        the command line's exit 0."""
        return not (self.failed or self.near_degenerate or self.poorly_covered
                    or self.poorly_resampled)

    def write(self, folder: str | Path) -> tuple[list[Path], list[str]]:
        """Write every file of the fit into `folder` (created), all or none: `camera.json`,
        `report.json`, `report.md`, `residuals.png`, `uncertainty.png` (with matplotlib), and
        `calib_results.txt` for `scaramuzza`, `correspondences.txt` for detected corners.

        Returns:
            The paths written, and the report's warnings (one line each).

        Raises:
            ValueError: the fit `failed` (nothing to write).
            FitNotWritten: an `OSError` while writing; nothing is left in `folder`, and the
                files are kept in `FitNotWritten.kept`.
        """
        from .report import write_fit_files

        if self.failed:
            raise ValueError(f"the fit did not converge ({self.result.reason}); nothing to "
                             f"write")
        # every file into a temporary folder first: a failed writer leaves nothing
        # half-written, and an output that cannot be written (disk full, removed) does not
        # lose the fit
        staging = Path(tempfile.mkdtemp(prefix="omniscape-fit-"))
        try:
            files, report = write_fit_files(
                staging, self.result, self.data, coverage=self.coverage, source=self.source,
                board=self.board, skipped=getattr(self.data, "skipped", {}),
                write_points=self.images is not None, fov_source=self.fov_source,
                fov_note=self.fov_note, resampling=self.resampling)
            written = publish(files, folder)
        except OSError as err:
            raise FitNotWritten(err, staging) from err
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        shutil.rmtree(staging, ignore_errors=True)
        return written, list(report["warnings"])


def calibrate(data: Correspondences, model: str, *, images: str | Path | Sequence | None = None,
              fov: float | None = None, leave_one_out: bool = False, strict: bool = False,
              source: str | None = None, board: str | None = None,
              **fit_options) -> Calibration:
    """Fit `model` to `data` and judge the views as `omniscape-torch fit` does (module
    docstring); `Calibration.write` writes its files.

    Args:
        data: correspondences (`read_correspondences`), or corners detected in images
            (`detect_corners`: its `skipped` go into the report).
        model: the camera model (`fit`).
        images: the images the corners were found in: their folder (`detect_corners`' files,
            matched to `data.names`) or a list of paths in `data`'s view order; for the image
            circle and the blind cone.
        fov: full field of view in radians: the area judged (module docstring) and one more
            start of the fit.
        leave_one_out: also refit without each view in turn (`leave_one_out`).
        strict: a near-degenerate fit counts as failed (not written).
        source: where `data` came from, for the report (default: none).
        board: the board's spec, for the report.
        **fit_options: passed to `fit` (`method`, `degree`, `freeze`, `loss`, `loss_scale`,
            `reject_outliers`, `outlier_threshold`, `max_iterations`, `progress`...).

    Returns:
        A `Calibration`: check `failed`, `near_degenerate`, `poorly_covered` and
        `poorly_resampled` (or `well_constrained`).

    Examples:
        >>> import math, torch, omniscape_torch as ot
        >>> from omniscape_torch import calibration
        >>> truth = ot.Camera("equidistant", torch.tensor([150.0, 150.0, 319.5, 239.5],
        ...                   dtype=torch.float64), (480, 640), fov=math.radians(190))
        >>> board = calibration.checkerboard(6, 8, 0.04)
        >>> pixels, _, _ = calibration.random_views(truth, board, 6, noise=0.3,
        ...                                         generator=torch.Generator().manual_seed(0))
        >>> data = calibration.Correspondences([board] * 6, pixels, (480, 640),
        ...                                    [f"view{i}" for i in range(6)])
        >>> run = calibration.calibrate(data, "equidistant")
        >>> run.failed, run.fov_source, run.result.camera.fov is None
        (False, "corners' reach", True)
    """
    result = fit(data.object_points, data.image_points, model, data.image_size, fov=fov,
                 **fit_options)
    run = Calibration(result, data, source=source, board=board, strict=strict, images=images)
    if run.failed:
        return run
    camera = result.camera
    views = _view_images(images, data, camera.image_size)
    run.fov, run.fov_source, run.fov_note = _area(camera, data, views, fov)
    run.coverage = assess_coverage(camera, result.covariance, data.image_points, fov=run.fov)
    if run.fov is not None and (views is not None or fov is not None):
        # camera.json keeps the area the images (or fov) show, for conversions and exports;
        # not the corners' reach of bare correspondences: the lens may see past it
        camera.fov = max(run.fov, min(_corners_reach(camera, data), 2 * math.pi))
    run.blind_fov = _blind_cone(camera, data, views)
    if run.blind_fov is not None:
        camera.blind_fov = run.blind_fov
    if leave_one_out:
        run.resampling = _leave_one_out(result, data.object_points, data.image_points,
                                        fov=run.fov)
    return run


def _area(camera, data: Correspondences, views, fov: float | None
          ) -> tuple[float | None, str, str | None]:
    """`Calibration.fov`, `fov_source`, `fov_note` (module docstring)."""
    if fov is not None:
        return fov, "--fov", None
    if views is None:   # correspondences alone: no image circle, the corners tell the area
        reach = _corners_reach(camera, data)
        if math.isfinite(reach) and reach > 0:
            return min(reach, 2 * math.pi), "corners' reach", None
        return None, "whole sensor", "no corner's ray is valid through the fitted camera"
    try:
        if isinstance(views, Exception):
            raise views
        circle = float(image_circle(views.mean(0), camera))
        why = f"it measured {circle:g} rad"
    except Exception as err:   # noqa: BLE001 (any failure of the measurement: fall back)
        circle, why = math.nan, f"{type(err).__name__}: {err}"
    if math.isfinite(circle) and circle >= 2 * math.pi:
        return None, "whole sensor", ("the images are lit to the sensor's edges (the image "
                                      "circle lies beyond the sensor)")
    if math.isfinite(circle) and circle > 0:
        return circle, "image circle", None
    reach = _corners_reach(camera, data) / 2
    if not math.isfinite(reach) or reach <= 0:
        return None, "whole sensor", (f"the image circle could not be measured ({why}), nor "
                                      f"the corners' reach")
    return (min(2 * reach, 2 * math.pi), "corners' reach",
            f"the image circle could not be measured ({why}: a dark centre or border?)")


def _view_images(images, data: Correspondences, image_size: tuple[int, int]):
    """`(V, H, W)` grey levels of up to `MEASURED_VIEWS` of the images where the board was
    found (not a corrupt file the detection skipped); None without `images`, the error where
    they cannot be read (the measurements that need them fall back)."""
    if images is None:
        return None
    try:
        from ..io.images import read_image
        from .detect import image_files

        if isinstance(images, (str, Path)):
            names = set(data.names)
            files = [f for f in image_files(images) if "_".join(f.stem.split()) in names]
        else:
            files = list(images)
        return np.stack([read_image(f).double().numpy().reshape(tuple(image_size) + (-1,))
                         .mean(-1) for f in files[:MEASURED_VIEWS]])
    except Exception as err:   # noqa: BLE001 (never lose the fit for a measurement)
        return err


def _blind_cone(camera, data: Correspondences, views) -> float | None:
    """The blind cone (full angle, radians) of the images: the disc about the axis dark in
    every view (`blind_cone` of their per-pixel maximum), kept below the corners' nearest angle
    to the axis; None where there is none or it cannot be measured."""
    if views is None or isinstance(views, Exception):
        return None
    try:
        blind = blind_cone(views.max(0), camera)
    except Exception:   # noqa: BLE001 (a measurement that fails leaves the cone out)
        return None
    angle = _corner_angles(camera, data)
    if angle.numel():
        blind = min(blind, 2 * float(angle.min()))
    return blind if 0 < blind < (camera.fov or 2 * math.pi) else None


def _corner_angles(camera, data: Correspondences) -> torch.Tensor:
    """The angles off axis (radians) of the corners' valid rays through `camera`."""
    with torch.no_grad():
        rays, valid = camera.unproject(torch.cat(list(data.image_points)).to(
            camera.params.dtype))
        return torch.atan2(rays[..., :2].norm(dim=-1), rays[..., 2])[valid]


def _corners_reach(camera, data: Correspondences) -> float:
    """Twice the largest angle off axis of the corners' rays through `camera` (radians; NaN
    where none is valid)."""
    angle = _corner_angles(camera, data)
    return 2 * float(angle.max()) if angle.numel() else math.nan
