"""Model selection, "no more than the scene needs": the fewest parameters within a tolerance.

Every candidate (a model, and a degree for ``scaramuzza``) is fitted on one set of points and
judged on another it never saw:

* from a camera (``ot.Camera``): `convert`, fitted on
  one pixel grid, judged on the grid offset by half a step;
* from correspondences (``(object_points, image_points)``): every ``holdout``-th point of each
  view is held out, the rest fitted by `fit`; the held-out
  points are projected with the fitted intrinsics and poses.

Errors are pixel distances: their RMS (the root of the mean squared distance, as
``FitResult.rms`` and `ConversionResult`; with
Gaussian noise of ``sigma`` per coordinate it tends to ``sigma sqrt 2``, so a tolerance must sit
above that) and their maximum. The selected candidate is the converged one with the fewest free
parameters whose held-out RMS is within ``tolerance`` and, if ``max_tolerance`` is given,
whose held-out maximum is within it, ties broken by the RMS. From a camera, a candidate must
also represent the whole area (``outside``, the share of held-out samples outside its domain,
is 0): a model of lesser reach (``pinhole``, ``fov``, ``opencv``, ``division`` with k > 0,
``orthographic``) fitted to a wider lens is judged on the part it sees, and is never selected.
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass
from typing import Sequence

import torch

from ..cameras import Camera
from ..cameras._checks import not_a_camera
from .convert import convert
from .fit import fit, prepare_views
from .params import transform

#: Default candidates: (model, degree); degree only matters for ``scaramuzza``.
DEFAULT_CANDIDATES = (
    ("equidistant", None), ("equisolid", None), ("stereographic", None), ("eucm", None),
    ("double_sphere", None), ("unified", None), ("kannala_brandt", None),
    ("scaramuzza", 2), ("scaramuzza", 3), ("scaramuzza", 4), ("scaramuzza", 5),
    ("scaramuzza", 6))


@dataclass
class Candidate:
    """One row of the selection table: ``fit_rms``, ``heldout_rms`` and ``heldout_max`` are RMS
    and largest pixel distances (module docstring); ``outside`` the share of the held-out
    samples the model cannot represent (0 for correspondences)."""

    model: str
    degree: int | None
    num_params: int
    fit_rms: float
    heldout_rms: float
    heldout_max: float
    converged: bool
    reason: str
    within: bool
    outside: float = 0.0


@dataclass
class Selection:
    """Outcome of `select_model`.

    Attributes:
        best: the selected row, or None when no candidate is within the tolerance.
        camera: its fitted camera (None with ``best``).
        table: every candidate, in the order tried.
    """

    best: Candidate | None
    camera: Camera | None
    table: list[Candidate]

    def to_dict(self) -> dict:
        return {"best": None if self.best is None else asdict(self.best),
                "table": [asdict(c) for c in self.table]}


def _heldout_fit(object_points, image_points, image_size, model: str, degree: int | None,
                 holdout: int, fit_kwargs: dict):
    fit_pts, fit_pix, held_pts, held_pix = [], [], [], []
    for pts, pix in zip(object_points, image_points):
        mask = torch.arange(len(pts)) % holdout == holdout - 1
        fit_pts.append(pts[~mask])
        fit_pix.append(pix[~mask])
        held_pts.append(pts[mask])
        held_pix.append(pix[mask])
    result = fit(fit_pts, fit_pix, model, image_size, degree=degree or 4, **fit_kwargs)
    if result.camera is None:
        return result, math.nan, math.nan
    err = torch.cat([result.camera.model.project(transform(pose, pts), result.params)[0] - pix
                     for pose, pts, pix in zip(result.poses, held_pts, held_pix)]).norm(dim=-1)
    return result, float(torch.sqrt((err * err).mean())), float(err.max())


def select_model(source, tolerance: float, *, max_tolerance: float | None = None,
                 image_size: tuple[int, int] | None = None,
                 candidates: Sequence[tuple[str, int | None]] = DEFAULT_CANDIDATES,
                 holdout: int = 4, progress: bool | None = False, **fit_kwargs) -> Selection:
    """The candidate with the fewest parameters whose held-out error is within the tolerances.

    Args:
        source: an ``ot.Camera`` (conversion), or ``(object_points, image_points)`` as
            `fit` takes them (calibration).
        tolerance: largest held-out RMS pixel distance.
        max_tolerance: largest held-out pixel distance (None: no bound on the worst case).
        image_size: ``(H, W)``, for correspondences.
        candidates: ``(model, degree)`` pairs (``DEFAULT_CANDIDATES``).
        holdout: with correspondences, every ``holdout``-th point of a view is held out.
        progress: show a tqdm bar over the candidates (``None``: when stderr is a terminal).
        **fit_kwargs: passed to ``fit`` for correspondences (``method``, ``loss``, ``fov``...),
            to ``convert`` for a camera (``grid``, ``fov``, ``mask``...).

    Returns:
        A `Selection` with the table of all candidates.
    """
    from tqdm import tqdm

    if not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance: expected a positive number of pixels, got {tolerance!r}")
    if max_tolerance is not None and not (isinstance(max_tolerance, (int, float))
                                          and math.isfinite(max_tolerance) and max_tolerance > 0):
        raise ValueError(f"max_tolerance: expected a positive number of pixels or None, got "
                         f"{max_tolerance!r}")
    if isinstance(holdout, bool) or not isinstance(holdout, int) or holdout < 2:
        raise ValueError(f"holdout: expected an integer >= 2, got {holdout!r}")
    if not candidates:
        raise ValueError("candidates: expected at least one (model, degree) pair")
    from_camera = isinstance(source, Camera)
    if not from_camera and isinstance(source, tuple) and source and isinstance(source[0], Camera):
        raise not_a_camera("source", source, "an ot.Camera or a pair (object_points, "
                                             "image_points)")
    if not from_camera:
        try:
            object_points, image_points = source
        except (TypeError, ValueError):
            raise TypeError("source: expected an ot.Camera or a pair (object_points, "
                            "image_points)") from None
        if image_size is None:
            raise ValueError("image_size: needed to fit correspondences")
        object_points, image_points = prepare_views(object_points, image_points)
    table, cameras = [], []
    for model, degree in tqdm(candidates, disable=not (sys.stderr.isatty() if progress is None
                                                       else progress),
                              desc="select_model", file=sys.stderr):
        if from_camera:
            conv = convert(source, model, degree=degree or 4, **fit_kwargs)
            result, held, worst = conv.fit, conv.rms_px, conv.max_px
            outside = conv.unrepresentable
        else:
            result, held, worst = _heldout_fit(object_points, image_points, image_size, model,
                                               degree, holdout, fit_kwargs)
            outside = 0.0
        ok = result.converged and math.isfinite(held) and held <= tolerance and outside == 0
        ok = ok and (max_tolerance is None or worst <= max_tolerance)
        table.append(Candidate(model, degree if model == "scaramuzza" else None,
                               len(result.free_names), result.rms, held, worst,
                               result.converged, result.reason, ok, outside))
        cameras.append(result.camera)
    eligible = [i for i, c in enumerate(table) if c.within]
    if not eligible:
        return Selection(None, None, table)
    best = min(eligible, key=lambda i: (table[i].num_params, table[i].heldout_rms))
    return Selection(table[best], cameras[best], table)
