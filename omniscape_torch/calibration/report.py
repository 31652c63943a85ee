"""What ``omniscape-torch fit`` writes beside the fitted camera: a report and its plots.

`write_fit_files` writes every file of a fit into one folder (the command line's staging
folder, published all at once by ``omniscape_torch.io.atomic.publish``):

* ``camera.json``: the camera (``Camera.load_json`` reads it), with the fit's summary under
  ``"fit"`` and the coverage figures under ``"coverage"``;
* ``calib_results.txt`` for ``scaramuzza``: OCamCalib's file (`write_ocamcalib_file`);
* ``report.json``: `fit_report`: per view its RMS and largest error (pixels, over the
  corners the fit kept) and the corners dropped as outliers, the parameters with their standard
  deviations, the convergence reason, the coverage figures and warnings, skipped images;
* ``report.md``: the same, short, for people;
* ``residuals.png``: residual vectors over the image (scaled to be seen) and a histogram of
  their lengths;
* ``uncertainty.png``: the predicted pixel error over the image
  (`omniscape_torch.calibration.coverage`), with the corners;
* ``correspondences.txt`` when the corners came from images: the detected corners in the
  format of `omniscape_torch.calibration.files` (a later ``fit`` can read them).

The plots need matplotlib (drawn with its Agg canvas, no global backend is set); without it
they are left out and the report says so.
"""

from __future__ import annotations

import json
import math
import warnings as _warnings
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from ..io.atomic import atomic_write_bytes, atomic_write_text
from .coverage import Coverage
from .files import Correspondences, save_result, write_correspondences

#: OCamCalib's own target for its inverse polynomial, pixels.
INVPOL_TARGET = 0.01

#: Looser targets tried, in order, when the inverse polynomial misses ``INVPOL_TARGET``.
INVPOL_LADDER = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, math.inf)


def _number(x: float):
    return x if math.isfinite(x) else None


def view_errors(result, sizes: Sequence[int]) -> list[dict]:
    """Per view ``{"points", "kept", "rms_px", "max_px", "outliers", "outlier_px"}``: the RMS
    (root of the mean squared distance, the package's one RMS) and largest residual distance
    over the corners the fit kept, and the indices (into the view's points) and distances of
    those it dropped (``FitResult.outliers`` where the fit has it)."""
    outliers = getattr(result, "outliers", None) or [None] * len(result.residuals)
    rows = []
    for residuals, size, dropped in zip(result.residuals, sizes, outliers):
        dist = torch.linalg.vector_norm(residuals.detach().double(), dim=-1)
        keep = torch.ones(len(dist), dtype=torch.bool)
        dropped = [] if dropped is None else [int(i) for i in torch.as_tensor(dropped).tolist()]
        if dropped:
            keep[torch.tensor(dropped, dtype=torch.long)] = False
        kept = dist[keep]
        rows.append({"points": int(size), "kept": int(keep.sum()),
                     "rms_px": float(kept.pow(2).mean().sqrt()) if len(kept) else math.nan,
                     "max_px": float(kept.max()) if len(kept) else math.nan,
                     "outliers": dropped,
                     "outlier_px": [float(dist[i]) for i in dropped]})
    return rows


def fit_report(result, names: Sequence[str], image_size: tuple[int, int], *,
               coverage: Coverage | None = None, model: str | None = None,
               source: str | None = None, board: str | None = None,
               skipped: dict[str, str] | None = None, invpol: dict | None = None,
               fov_source: str | None = None, fov_note: str | None = None,
               resampling=None) -> dict:
    """The JSON-ready report of a fit (module docstring).

    Args:
        result: a ``FitResult``.
        names: view names, in the fit's order.
        image_size: ``(H, W)``.
        coverage: `assess_coverage`'s result.
        model: the model name (default: the fitted camera's).
        source: where the correspondences came from (a file, a folder of images).
        board: the board (``--board`` text) when detected in images.
        skipped: images where the board was not found, and why.
        invpol: ``calib_results.txt``'s inverse polynomial: ``{"max_error_px", "target_px"}``.
        fov_source: where the field of view the coverage is judged over came from:
            ``"image circle"``, ``"corners' reach"``, ``"whole sensor"`` or ``"--fov"``.
        fov_note: why the image circle was not used, when it could not be measured.
        resampling: `leave_one_out`'s result.
    """
    sizes = [len(r) for r in result.residuals]
    views = [{"name": n, **row} for n, row in zip(names, view_errors(result, sizes))]
    free = set(result.free_names)
    params = {name: {"value": v, "std": _number(s), "free": name in free}
              for name, v, s in zip(result.param_names, result.params.tolist(),
                                    result.std.tolist())}
    report = {
        "model": model or (result.camera.model.name if result.camera is not None else None),
        "image_size": list(image_size), "source": source, "board": board,
        "converged": result.converged, "reason": result.reason, "method": result.method,
        "iterations": result.iterations, "start": getattr(result, "start", None),
        "rms_px": result.rms, "num_observations": result.num_observations,
        "num_views": len(views), "num_free": result.num_free,
        "num_outliers": sum(len(v["outliers"]) for v in views),
        "condition": _number(result.condition), "params": params, "views": views,
        "skipped_images": dict(skipped or {}),
        "coverage": None if coverage is None else coverage.to_dict(),
        "fov_source": fov_source, "fov_note": fov_note,
        "near_degenerate": [{"name": n, "partner": p, "correlation": _number(c)}
                            for n, p, c in getattr(result, "near_degenerate", [])],
        "resampling": None if resampling is None else resampling.to_dict(),
    }
    if invpol is not None:
        report["ocamcalib_inverse_polynomial"] = invpol
    return report


def _px(value) -> str:
    return "inf px" if value is None or not math.isfinite(value) else f"{value:.3f} px"


def report_markdown(report: dict) -> str:
    """A short Markdown page of `fit_report`'s report."""
    h, w = report["image_size"]
    lines = [f"# Calibration: {report['model']}", "",
             f"- source: {report['source'] or '-'}" + (f" (board {report['board']})"
                                                      if report["board"] else ""),
             f"- image: {w} x {h} pixels (W x H)",
             f"- {'converged' if report['converged'] else 'NOT converged'}: {report['reason']}",
             f"- RMS reprojection error {report['rms_px']:.4f} px over "
             f"{report['num_observations']} corners in {report['num_views']} views"
             + (f", {report['num_outliers']} outliers dropped" if report["num_outliers"] else "")]
    cov = report.get("coverage")
    if cov is not None:
        std = cov["max_pixel_std"]
        lines += ["", "## Coverage", "",
                  "well constrained" if cov["ok"] else "**POORLY CONSTRAINED**", "",
                  f"- corners in {100 * cov['cells']:.0f}% of the image's cells (limit "
                  f"{100 * cov['thresholds']['min_cells']:.0f}%), convex hull "
                  f"{100 * cov['hull']:.0f}% of the area",
                  f"- corners up to {cov['angle_deg']:.1f} deg off axis of "
                  f"{cov['half_fov_deg']:.1f} deg ({100 * cov['angle_share']:.0f}%, limit "
                  f"{100 * cov['thresholds']['min_angle']:.0f}%)",
                  f"- predicted pixel error (RMS distance from the truth where the corners "
                  f"reach, median of its distribution): " + _px(cov["pixel_error"])
                  + f" (limit {cov['thresholds']['max_pixel_error']:g} px; root mean square "
                  + _px(cov["pixel_rms"]) + "); per pixel (1 sigma) largest " + _px(std)
                  + ", over the whole field of view up to " + _px(cov["max_pixel_std_fov"])
                  + "; map in `uncertainty.png`"]
        if report.get("resampling"):
            lines.append("- leave-one-view-out (jackknife RMS where the corners reach): "
                         + _px(report["resampling"]["pixel_error"]) + ", against "
                         + _px(cov["pixel_rms"]) + " predicted")
        if report.get("fov_source"):
            lines.append(f"- field of view ({cov['half_fov_deg'] * 2:.1f} deg) from: "
                         f"{report['fov_source']}" + (f" ({report['fov_note']})"
                                                      if report.get("fov_note") else ""))
        lines += [f"- warning: {line}" for line in cov["warnings"]]
    lines += ["", "## Parameters", "", "| name | value | std | |", "|---|---|---|---|"]
    for name, p in report["params"].items():
        std = "inf" if p["std"] is None else f"{p['std']:.3g}"
        lines.append(f"| {name} | {p['value']:.9g} | {std} | {'' if p['free'] else 'held'} |")
    lines += ["", "## Views", "", "| view | corners | kept | RMS px | max px | outliers |",
              "|---|---|---|---|---|---|"]
    for v in report["views"]:
        lines.append(f"| {v['name']} | {v['points']} | {v['kept']} | {v['rms_px']:.4f} | "
                     f"{v['max_px']:.4f} | {', '.join(map(str, v['outliers'])) or '-'} |")
    if report["skipped_images"]:
        lines += ["", "## Images skipped", ""]
        lines += [f"- {name}: {why}" for name, why in report["skipped_images"].items()]
    inv = report.get("ocamcalib_inverse_polynomial")
    if inv is not None:
        lines += ["", f"OCamCalib inverse polynomial (`calib_results.txt`): largest error "
                      f"{inv['max_error_px']:.3g} px (target {inv['target_px']:g} px)"]
        if inv.get("warning"):
            lines.append(f"- warning: {inv['warning']}")
    lines += ["", "Plots: `residuals.png` (residual vectors and their histogram), "
                  "`uncertainty.png` (predicted pixel error)." if report.get("plots")
              else "", ""]
    return "\n".join(lines)


def write_ocamcalib_file(camera, path: str | Path) -> dict:
    """Write OCamCalib's ``calib_results.txt`` whose inverse polynomial (OCamCalib's fast
    ``world2cam``) may miss OCamCalib's 0.01 px: the loosest target of ``INVPOL_LADDER`` that
    the degrees up to 20 reach is used instead of failing the calibration (``camera.json`` is
    exact; only OCamCalib's own projection code uses that polynomial).

    Returns:
        ``{"max_error_px", "target_px", "warning"}`` (``warning`` None when within 0.01 px).
    """
    from ..cameras.formats import fit_invpol

    for target in (INVPOL_TARGET, *INVPOL_LADDER):
        with _warnings.catch_warnings():
            # numpy's RankWarning on the high degrees tried: the error measured says it all
            _warnings.simplefilter("ignore")
            try:
                _, error = fit_invpol(camera, max_error=target)
            except ValueError:
                continue
            camera.to_ocamcalib(path, max_error=target)
        warning = None if target == INVPOL_TARGET else (
            f"calib_results.txt: OCamCalib's inverse polynomial fits the camera within "
            f"{error:.3g} px only (target {INVPOL_TARGET:g} px): OCamCalib's world2cam is off "
            f"by up to that much (camera.json and ot.Camera are exact); this happens where the "
            f"fitted polynomial folds inside the image, beyond the corners")
        return {"max_error_px": error, "target_px": INVPOL_TARGET, "warning": warning}
    raise ValueError("calib_results.txt: no inverse polynomial could be fitted")  # unreachable


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------

def _figure(width: float, height: float):
    """A matplotlib ``Figure`` on an Agg canvas (no pyplot, no global backend)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return atomic_write_bytes(path, buffer.getvalue())


def plot_residuals(result, image_points: Sequence[Tensor], image_size: tuple[int, int],
                   path: str | Path, names: Sequence[str] | None = None) -> Path:
    """``residuals.png``: the residual vectors at the observed pixels (arrows scaled so that
    the largest is 5% of the image; one colour per view; outliers in black) and the histogram
    of the residual distances."""
    h, w = image_size
    fig = _figure(12, 5)
    ax, hist = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    outliers = getattr(result, "outliers", None) or [None] * len(result.residuals)
    res = [r.detach().double() for r in result.residuals]
    largest = max((float(torch.linalg.vector_norm(r, dim=-1).max()) for r in res if len(r)),
                  default=0.0)
    scale = 0.05 * max(h, w) / largest if largest > 0 else 1.0
    cmap = _colormap("tab20")
    kept_dist, dropped_dist = [], []
    for k, (pix, r, drop) in enumerate(zip(image_points, res, outliers)):
        pix = pix.detach().double()
        mask = torch.ones(len(r), dtype=torch.bool)
        if drop is not None and len(drop):
            mask[torch.as_tensor(drop, dtype=torch.long)] = False
        colour = cmap(k % 20)
        ax.quiver(pix[mask, 0], pix[mask, 1], r[mask, 0] * scale, r[mask, 1] * scale,
                  angles="xy", scale_units="xy", scale=1, color=colour, width=0.002,
                  label=None if names is None else names[k])
        if bool((~mask).any()):
            ax.quiver(pix[~mask, 0], pix[~mask, 1], r[~mask, 0] * scale, r[~mask, 1] * scale,
                      angles="xy", scale_units="xy", scale=1, color="black", width=0.003)
        dist = torch.linalg.vector_norm(r, dim=-1)
        kept_dist.append(dist[mask])
        dropped_dist.append(dist[~mask])
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"residuals (projected - detected) x {scale:.3g}; RMS {result.rms:.3f} px")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    kept = torch.cat(kept_dist) if kept_dist else torch.zeros(0)
    dropped = torch.cat(dropped_dist) if dropped_dist else torch.zeros(0)
    hist.hist(kept.numpy(), bins=40, color="tab:blue", label="kept")
    if len(dropped):
        hist.hist(dropped.numpy(), bins=40, color="black", label="outliers")
        hist.legend()
    hist.set_xlabel("residual distance (px)")
    hist.set_ylabel("corners")
    hist.set_title("residual distances")
    fig.tight_layout()
    return _save(fig, Path(path))


def _colormap(name: str):
    import matplotlib

    return matplotlib.colormaps[name]


def uncertainty_map(coverage: Coverage, camera=None) -> tuple[Tensor, float]:
    """What ``uncertainty.png`` draws: the predicted pixel error at ``coverage.grid`` with NaN
    where no camera sees (outside the calibrated area: the image circle or ``fov``; inside
    ``camera.blind_fov``, a catadioptric camera's blind spot), and the top of its colour
    scale: the largest error over the area the corners reach (``coverage.max_pixel_std``),
    at least 1.2 times the limit, so that the extrapolated rim does not turn the covered area
    black (errors above it are drawn in the top colour)."""
    std = coverage.std_map.clone()
    if camera is not None and (camera.fov, camera.blind_fov) != (None, None):
        with torch.no_grad():
            rays, _ = camera.model.unproject(coverage.grid.to(camera.params.dtype),
                                             camera.params.detach())
        std[~camera.within_fov(rays)] = math.nan
    limit = coverage.thresholds["max_pixel_error"]
    finite = std[torch.isfinite(std)]
    reach = coverage.max_pixel_std if math.isfinite(coverage.max_pixel_std) else (
        float(finite.max()) if finite.numel() else 1.0)
    return std, max(reach, 1.2 * limit)


def plot_uncertainty(coverage: Coverage, image_points: Sequence[Tensor],
                     image_size: tuple[int, int], path: str | Path, *, camera=None) -> Path:
    """``uncertainty.png``: the predicted pixel error over the calibrated area (colour, scaled
    to the area the corners reach, `uncertainty_map`; grey where the camera sees
    nothing: outside its image circle, inside ``camera.blind_fov``), the limit's contour,
    the corners (dots) and the coverage figures in the title."""
    h, w = image_size
    fig = _figure(8, 8 * h / w + 1)
    ax = fig.add_subplot(1, 1, 1)
    import numpy as np

    std, top = uncertainty_map(coverage, camera)
    finite = std[torch.isfinite(std)]
    limit = coverage.thresholds["max_pixel_error"]
    std = torch.where(torch.isinf(std), torch.full_like(std, top), std)
    gh, gw = std.shape
    cmap = _colormap("magma").with_extremes(bad="0.6")
    image = ax.imshow(std.numpy(), extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap=cmap,
                      vmin=0, vmax=top, interpolation="nearest")
    fig.colorbar(image, ax=ax, label="predicted pixel error, 1 sigma (px)", shrink=0.8,
                 extend="max" if finite.numel() and float(finite.max()) > top else "neither")
    grid = coverage.grid
    if gh > 1 and gw > 1 and finite.numel() and float(finite.min()) < limit < top:
        # the limit's contour, outside the area masked (no line along its edge)
        ax.contour(grid[..., 0].numpy(), grid[..., 1].numpy(),
                   np.ma.masked_invalid(std.numpy()), levels=[limit], colors="cyan",
                   linewidths=1.0)
    corners = torch.cat([p.detach().double().reshape(-1, 2) for p in image_points])
    ax.plot(corners[:, 0].numpy(), corners[:, 1].numpy(), ".", color="lime", markersize=2)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    verdict = "well constrained" if coverage.ok else "POORLY CONSTRAINED"
    ax.set_title(f"{verdict}: {coverage.pixel_error:.3g} px (limit "
                 f"{limit:g}), largest {coverage.max_pixel_std:.3g} px, cells "
                 f"{100 * coverage.cells:.0f}%, angle {math.degrees(coverage.angle):.0f}/"
                 f"{math.degrees(coverage.half_fov):.0f} deg", fontsize=9)
    fig.tight_layout()
    return _save(fig, Path(path))


# --------------------------------------------------------------------------------------------
# Every file of a fit
# --------------------------------------------------------------------------------------------

def write_fit_files(folder: str | Path, result, data: Correspondences, *,
                    coverage: Coverage | None = None, source: str | None = None,
                    board: str | None = None, skipped: dict[str, str] | None = None,
                    write_points: bool = False, plots: bool = True,
                    fov_source: str | None = None,
                    fov_note: str | None = None, resampling=None
                    ) -> tuple[list[Path], dict]:
    """Write every file of a fit into ``folder`` (module docstring).

    Args:
        folder: an existing folder (the staging folder).
        result: the converged ``FitResult``.
        data: the correspondences it was fitted to.
        coverage: the coverage figures (``assess_coverage``).
        source: for the report (`fit_report`).
        board: for the report (`fit_report`).
        skipped: for the report (`fit_report`).
        write_points: also write ``correspondences.txt`` (corners detected in images).
        plots: draw ``residuals.png`` and ``uncertainty.png`` (skipped without matplotlib).
        fov_source: for the report (`fit_report`).
        fov_note: for the report (`fit_report`).
        resampling: for the report (`fit_report`).

    Returns:
        The paths written, and the report (with ``"plots"`` and ``"warnings"``: lines to show).
    """
    folder = Path(folder)
    camera = result.camera
    files, notes = [], []
    invpol = None
    if camera.model.name == "scaramuzza":
        invpol = write_ocamcalib_file(camera, folder / "calib_results.txt")
        files.append(folder / "calib_results.txt")
        if invpol["warning"]:
            notes.append(invpol["warning"])
    report = fit_report(result, data.names, data.image_size, coverage=coverage,
                        model=camera.model.name, source=source, board=board, skipped=skipped,
                        invpol=invpol, fov_source=fov_source, fov_note=fov_note,
                        resampling=resampling)
    summary = result.to_dict()
    extra = {} if coverage is None else {"coverage": coverage.to_dict()}
    if fov_source is not None:   # the camera's fov_deg: where it came from
        extra["fov_source"] = fov_source
    files.insert(0, save_result(camera, {**summary, **extra}, "fit", folder / "camera.json"))
    drawn = False
    if plots:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            notes.append("matplotlib is missing: residuals.png and uncertainty.png were not "
                         "drawn (pip install matplotlib)")
        else:
            with _warnings.catch_warnings():
                _warnings.simplefilter("ignore")   # tight_layout's and contour's chatter
                files.append(plot_residuals(result, data.image_points, data.image_size,
                                            folder / "residuals.png", data.names))
                if coverage is not None:
                    files.append(plot_uncertainty(coverage, data.image_points,
                                                  data.image_size, folder / "uncertainty.png",
                                                  camera=camera))
            drawn = True
    report["plots"] = drawn
    report["warnings"] = ([] if coverage is None else list(coverage.warnings)) + notes
    if write_points:
        files.append(write_correspondences(folder / "correspondences.txt", Correspondences(
            data.object_points, data.image_points, data.image_size, data.names)))
    files.append(atomic_write_text(folder / "report.json", json.dumps(
        _finite(report), indent=2, allow_nan=False, default=_json_default) + "\n"))
    files.append(atomic_write_text(folder / "report.md", report_markdown(report)))
    return files, report


def _finite(value):
    """``value`` with every NaN or infinite float replaced by None (JSON has neither)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _json_default(value):
    if isinstance(value, Tensor):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
