"""Calibration by least squares over the differentiable camera models.

* `fit`: intrinsics and per-view poses from target points and their pixels
  (Levenberg-Marquardt, L-BFGS, Adam, or OCamCalib's linear solution), robust losses, frozen
  parameter groups, constraints by reparametrisation, covariance of the result.
* `convert`: a camera of another model (or polynomial degree) fitted to an existing one
  over its valid area, with held-out pixel and angular errors.
* `select_model`: the fewest parameters whose held-out error is within a tolerance.
* `fit_photometric`: intrinsics (and attitude) from a target image, by rendering a cubemap
  through the camera and matching the target, coarse to fine.
* `read_correspondences` / `write_correspondences`: the text format of
  ``omniscape-torch fit``.
* `checkerboard` / `random_views`: synthetic data of a known camera.
* `detect_corners`: a board's corners in images (OpenCV, optional), `Board` the
  boards of ``fit --board``, `render_board` images of a board through a known camera.
* `assess_coverage`: where the corners lie and the predicted error over the image;
  `leave_one_out` the same error by refitting without each view;
  `write_fit_files`: everything ``omniscape-torch fit`` writes (report, plots).
* `calibrate`: all of ``omniscape-torch fit`` as one function (the fit, the area the lens sees,
  the coverage and predicted error over it, the blind cone, the verdict), a `Calibration`
  whose `write` writes the files.

Examples:
    >>> import torch, omniscape_torch as ot
    >>> from omniscape_torch.calibration import checkerboard, fit, random_views
    >>> truth = ot.Camera("equidistant", torch.tensor([200.0, 200.0, 319.5, 239.5],
    ...                   dtype=torch.float64), (480, 640))
    >>> board = checkerboard(6, 8, 0.04)
    >>> pixels, _, _ = random_views(truth, board, 4, generator=torch.Generator().manual_seed(0))
    >>> result = fit(board, pixels, "equidistant", (480, 640))
    >>> result.converged, round(result.rms, 6)
    (True, 0.0)
"""

from .calibrate import Calibration, FitNotWritten, calibrate
from .convert import ConversionResult, convert, image_circle, without_affine
from .files import Correspondences, read_correspondences, save_result, write_correspondences
from .fit import FitResult, METHODS, fit
from .linear import planar_pose, scaramuzza_linear
from .lm import LOSSES
from .select import Candidate, Selection, select_model
from .starts import default_intrinsics
from .synthetic import checkerboard, random_views

from .photometric import PHOTOMETRIC_LOSSES, PhotometricResult, fit_photometric, photometric_error
from .coverage import Coverage, Resampling, assess_coverage, covered_rays, leave_one_out
from .detect import Detection, detect_corners
from .report import fit_report, write_fit_files
from .targets import Board, render_board

__all__ = ["assess_coverage", "Board", "calibrate", "Calibration", "Candidate", "checkerboard",
           "ConversionResult", "convert", "Correspondences", "Coverage", "covered_rays",
           "default_intrinsics", "detect_corners", "Detection", "fit", "fit_photometric",
           "fit_report", "FitNotWritten", "FitResult", "image_circle", "leave_one_out", "LOSSES",
           "METHODS", "photometric_error", "PHOTOMETRIC_LOSSES", "PhotometricResult",
           "planar_pose", "random_views", "read_correspondences", "render_board", "Resampling",
           "save_result", "scaramuzza_linear", "select_model", "Selection", "without_affine",
           "write_correspondences", "write_fit_files"]
