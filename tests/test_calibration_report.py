"""What ``omniscape-torch fit`` writes and when it complains (issue 19): the coverage check,
the report, OCamCalib's inverse polynomial, and all files or none.

The coverage cases are the issue's: a checkerboard of 9 x 12 inner corners seen by a real
fisheye (the OCamCalib camera of ``../shared/data``, sensor roll e = 0) from random poses with
0.2 px of noise; 3-4 views are poorly constrained (their fits are 1-3 px off the truth), 12-15
views spread over the image are not.
"""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.calibration import (Correspondences, checkerboard, fit, random_views,
                                         write_correspondences)
from omniscape_torch.calibration import report as report_module
from omniscape_torch.calibration.coverage import THRESHOLDS, assess_coverage
from omniscape_torch.calibration.report import view_errors, write_fit_files, \
    write_ocamcalib_file

from conftest import CASES

D = torch.float64
pytestmark = pytest.mark.usefixtures("one_thread")


def _truth(model: str = "scaramuzza") -> ot.Camera:
    params, size = CASES[model][0 if model not in ("kannala_brandt", "unified") else 1]
    params = torch.tensor(params, dtype=D)
    if model == "scaramuzza":
        params[4] = 0.0   # the fit holds the sensor roll e (the poses absorb it)
    return ot.Camera(model, params, size)


def _area(camera: ot.Camera) -> float:
    """Where random_views puts boards: the full angle of the calibrated area, radians."""
    return 2 * min(0.8 * float(camera.max_angle()), math.radians(85))


def _views(n: int, model: str = "scaramuzza", seed: int = 0):
    camera = _truth(model)
    board = checkerboard(9, 12, 0.04)
    pixels, _, _ = random_views(camera, board, n, noise=0.2,
                                generator=torch.Generator().manual_seed(seed))
    return camera, board, pixels


def _corr_file(tmp_path: Path, n: int, seed: int = 0) -> Path:
    camera, board, pixels = _views(n, seed=seed)
    path = tmp_path / f"corr{n}.txt"
    write_correspondences(path, Correspondences([board] * n, pixels, camera.image_size,
                                                [f"v{i}" for i in range(n)]))
    return path


# --------------------------------------------------------------------------------------------
# coverage
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
@pytest.mark.parametrize("model, n, seed, ok", [
    ("scaramuzza", 3, 0, False), ("scaramuzza", 3, 1, False), ("scaramuzza", 4, 0, False),
    ("scaramuzza", 4, 1, False), ("scaramuzza", 12, 0, True), ("scaramuzza", 15, 1, True),
    ("kannala_brandt", 3, 0, False), ("kannala_brandt", 12, 0, True),
])
def test_coverage_flags_few_views_and_passes_spread_views(model, n, seed, ok):
    camera, board, pixels = _views(n, model, seed)
    result = fit(board, pixels, model, camera.image_size)
    assert result.converged, result.reason
    coverage = assess_coverage(result.camera, result.covariance, pixels, fov=_area(camera))
    assert coverage.ok == ok, coverage.to_dict()
    if not ok:
        assert coverage.warnings and coverage.cells < THRESHOLDS["min_cells"]
        return
    assert coverage.pixel_error < THRESHOLDS["max_pixel_error"]
    assert coverage.cells >= THRESHOLDS["min_cells"]
    # and a fit it passes is good: against the truth, over the area the corners reach, within
    # the limit it applied to the predicted error
    grid = coverage.grid.reshape(-1, 2)
    rays, valid = ot.Camera(model, camera.params, camera.image_size,
                            fov=2 * coverage.angle).unproject(grid)
    pixels_fit, _ = result.camera.project(rays[valid])
    err = (pixels_fit - grid[valid]).norm(dim=-1)
    assert float(err.pow(2).mean().sqrt()) < THRESHOLDS["max_pixel_error"], float(err.max())


def test_coverage_of_an_undetermined_fit():
    """A covariance that is not finite (degenerate views) is an undetermined calibration."""
    camera = _truth("equidistant")
    cov = torch.full((4, 4), math.inf, dtype=D)
    pixels = [torch.tensor([[300.0, 300.0], [340.0, 300.0], [300.0, 340.0]], dtype=D)]
    coverage = assess_coverage(camera, cov, pixels)
    assert not coverage.ok and math.isinf(coverage.max_pixel_std)
    assert math.isinf(coverage.pixel_error) and math.isinf(coverage.pixel_rms)
    assert any("undetermined" in w for w in coverage.warnings)
    assert coverage.to_dict()["max_pixel_std"] is None   # JSON has no inf
    assert coverage.to_dict()["pixel_error"] is None


def test_pixel_std_is_the_covariance_propagated():
    """For the equidistant model a ray's pixel is (cx + fx r_x, cy + fy r_y) with r the
    normalised direction times theta: with variances only on cx and cy the predicted error is
    sqrt(var cx + var cy) everywhere."""
    from omniscape_torch.calibration.coverage import pixel_std

    camera = _truth("equidistant")
    cov = torch.diag(torch.tensor([0.0, 0.0, 0.09, 0.16], dtype=D))
    rays = torch.nn.functional.normalize(torch.randn(50, 3, dtype=D,
                                                     generator=torch.Generator().manual_seed(0))
                                         + torch.tensor([0, 0, 2.0], dtype=D), dim=-1)
    assert torch.allclose(pixel_std(camera, cov, rays), torch.full((50,), 0.5, dtype=D))


@pytest.mark.parametrize("variances, median", [
    # every pixel moves by (dcx, dcy): the RMS error over the area is |(dcx, dcy)|, whose
    # square is 0.125 chi2(2) (median 2 ln 2, exact) or 0.25 chi2(1) (median 0.45494)
    ((0.125, 0.125), math.sqrt(0.125 * 2 * math.log(2))),
    ((0.25, 0.0), math.sqrt(0.25 * 0.454936)),
])
def test_predicted_error_is_the_median_of_the_rms_error(variances, median):
    from omniscape_torch.calibration.coverage import predicted_error

    camera = _truth("equidistant")
    cov = torch.diag(torch.tensor([0.0, 0.0, *variances], dtype=D))
    rays = torch.nn.functional.normalize(torch.randn(40, 3, dtype=D,
                                                     generator=torch.Generator().manual_seed(1))
                                         + torch.tensor([0, 0, 2.0], dtype=D), dim=-1)
    got, rms = predicted_error(camera, cov, rays)
    assert rms == pytest.approx(0.5, rel=1e-9)
    assert got == pytest.approx(median, rel=0.02)   # Wilson-Hilferty's approximation


def _kb190(views: int, seed: int, noise: float = 0.3):
    """The issue's control: a Kannala-Brandt 190-degree lens on 1280 x 1024, a 9 x 6 board of
    8 cm squares (as benchmarks/calibration_uncertainty.py)."""
    truth = ot.cameras.presets.fisheye((1024, 1280), fov=math.radians(190),
                                       model="kannala_brandt",
                                       distortion=(-0.02, 0.004, -0.001, 0.0002), dtype=D)
    board = checkerboard(6, 9, 0.08)
    pixels, _, _ = random_views(truth, board, views, noise=noise,
                                generator=torch.Generator().manual_seed(seed))
    return truth, board, pixels


@pytest.mark.numerics
@pytest.mark.parametrize("views, code", [(21, 0), (3, cli.EXIT_POORLY_CONSTRAINED)])
def test_fit_passes_21_spread_views_and_flags_3(views, code, tmp_path, monkeypatch):
    """The issue's control: 21 views spread over the image circle exit 0, 3 views exit 3."""
    _quick_plots(monkeypatch)
    truth, board, pixels = _kb190(views, 0)
    path = tmp_path / "corr.txt"
    write_correspondences(path, Correspondences([board] * views, pixels, truth.image_size,
                                                [f"v{i}" for i in range(views)]))
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "kannala_brandt", "--fov", "190", "--out",
                     str(out), "--no-progress"]) == code
    report = json.loads((out / "report.json").read_text())
    assert report["converged"] and report["coverage"]["ok"] == (code == 0)


@pytest.mark.slow
@pytest.mark.numerics
def test_predicted_error_matches_the_truth_over_noise_draws():
    """One set of 4 poses, 24 noise draws (each fit started at the truth: the same minimum,
    found faster): the fitted cameras' RMS error against the truth
    where the corners reach has the mean square ``pixel_rms^2`` and the median
    ``pixel_error`` that the fits predict (independent oracle: the true camera)."""
    from omniscape_torch.calibration.coverage import covered_rays

    truth = ot.Camera("equidistant", torch.tensor([60.0, 60.0, 63.5, 47.5], dtype=D),
                      (96, 128))
    board = checkerboard(5, 6, 0.05)
    gen = torch.Generator().manual_seed(3)
    _, poses, clean = random_views(truth, board, 4, generator=gen)
    predicted, rms, true = [], [], []
    for _ in range(24):
        pixels = list((clean + 0.3 * torch.randn(clean.shape, generator=gen, dtype=D))
                      .unbind(0))
        result = fit(board, pixels, "equidistant", truth.image_size, init=truth.params,
                     poses=poses)
        coverage = assess_coverage(result.camera, result.covariance, pixels)
        grid, _ = covered_rays(result.camera, pixels)
        rays, valid = truth.unproject(grid)
        err = (result.camera.project(rays[valid])[0] - grid[valid]).square().sum(-1).mean()
        predicted.append(coverage.pixel_error)
        rms.append(coverage.pixel_rms)
        true.append(float(err.sqrt()))
    t = torch.tensor(true)
    assert 0.7 < math.sqrt(sum(r * r for r in rms) / float(t.square().sum())) < 1.4
    below = sum(a < b for a, b in zip(true, predicted)) / len(true)
    assert 0.25 < below < 0.75, below


# --------------------------------------------------------------------------------------------
# the command line
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
def test_cli_exits_3_on_few_views_unless_accepted(tmp_path, capsys):
    path = _corr_file(tmp_path, 3)
    fov = f"{math.degrees(_area(_truth())):.3f}"
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--fov", fov, "--out",
                     str(out), "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert "poorly constrained" in err and "--accept-coverage" in err and "warning:" in err
    # the files are written all the same, and say so
    assert {p.name for p in out.iterdir()} == {"camera.json", "calib_results.txt",
                                               "report.json", "report.md", "residuals.png",
                                               "uncertainty.png"}
    report = json.loads((out / "report.json").read_text())
    assert not report["coverage"]["ok"] and report["coverage"]["warnings"]
    assert "POORLY CONSTRAINED" in (out / "report.md").read_text()
    assert json.loads((out / "camera.json").read_text())["fit"]["coverage"]["ok"] is False
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--fov", fov, "--out",
                     str(out), "--no-progress", "--accept-coverage"]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "poorly constrained" not in err


def test_cli_input_errors(tmp_path, capsys):
    path = _corr_file(tmp_path, 3)
    out = str(tmp_path / "out")
    for argv, match in [
        (["fit", "--model", "scaramuzza", "--out", out], "not neither"),
        (["fit", str(path), "--images", str(tmp_path), "--board", "checkerboard:9x6:0.03",
          "--model", "scaramuzza", "--out", out], "not both"),
        (["fit", "--images", str(tmp_path), "--model", "scaramuzza", "--out", out],
         "also give --board"),
        (["fit", str(path), "--board", "checkerboard:9x6:0.03", "--model", "scaramuzza",
          "--out", out], "only with --images"),
        (["fit", "--images", str(tmp_path), "--board", "checkerboard:9x6", "--model",
          "scaramuzza", "--out", out], "expected checkerboard:COLSxROWS:SQUARE"),
        (["fit", "--images", str(tmp_path), "--board", "checkerboard:9x6:0.03", "--model",
          "scaramuzza", "--out", out], "no images"),
        (["fit", "--images", str(tmp_path / "nope"), "--board", "checkerboard:9x6:0.03",
          "--model", "scaramuzza", "--out", out], "no such folder"),
    ]:
        assert cli.main(argv) == 2, argv
        assert match in capsys.readouterr().err, argv
    assert not Path(out).exists()


# --------------------------------------------------------------------------------------------
# all files or none
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def few_views_fit(tmp_path_factory):
    """A 3-view scaramuzza fit, fitted once: the failure tests replay it."""
    folder = tmp_path_factory.mktemp("fit")
    path = _corr_file(folder, 3)
    data = ot.calibration.read_correspondences(path)
    result = fit(data.object_points, data.image_points, "scaramuzza", data.image_size)
    assert result.converged
    return path, result


def _quick_plots(monkeypatch):
    """Stand-ins for the plots (matplotlib takes a second a figure; the staging, not the
    drawing, is tested here)."""
    def plot(*args, **kwargs):
        path = Path(args[3] if len(args) > 3 else kwargs["path"])
        path.write_bytes(b"\x89PNG stand-in")
        return path

    monkeypatch.setattr(report_module, "plot_residuals", plot)
    monkeypatch.setattr(report_module, "plot_uncertainty", plot)


def _fail(*args, **kwargs):
    raise RuntimeError("a writer broke")


def _oserror(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "somewhere")


#: (what fails, where to patch, exit code)
STEPS = [
    ("camera.json", (report_module, "save_result"), 1),
    ("calib_results.txt", (ot.Camera, "to_ocamcalib"), 1),
    ("residuals.png", (report_module, "plot_residuals"), 1),
    ("uncertainty.png", (report_module, "plot_uncertainty"), 1),
    ("report.md", (report_module, "report_markdown"), 1),
    ("report.json", (report_module, "fit_report"), 1),
]


@pytest.mark.parametrize("existing", [False, True], ids=["new", "existing"])
@pytest.mark.parametrize("step, where, code", STEPS, ids=[s[0] for s in STEPS])
def test_a_failure_at_any_step_leaves_the_output_as_it_was(tmp_path, capsys, monkeypatch,
                                                           few_views_fit, step, where, code,
                                                           existing):
    path, result = few_views_fit
    monkeypatch.setattr(ot.calibration, "fit", lambda *a, **k: result)
    _quick_plots(monkeypatch)
    out = tmp_path / "out"
    before = {}
    if existing:
        out.mkdir()
        (out / "camera.json").write_text("an earlier fit\n")
        (out / "notes.txt").write_text("mine\n")
        before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(*where, _fail)
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(out),
                     "--no-progress", "--accept-coverage"]) == code
    assert "a writer broke" in capsys.readouterr().err
    now = {p.name: p.read_bytes() for p in out.iterdir()} if out.exists() else {}
    assert now == before, step


def test_a_publish_that_fails_midway_installs_nothing(tmp_path, capsys, monkeypatch,
                                                      few_views_fit):
    """The disk fills while the files are copied into --out: none is installed, the staging
    folder that keeps them is named, exit 1."""
    import omniscape_torch.io.atomic as atomic

    path, result = few_views_fit
    monkeypatch.setattr(ot.calibration, "fit", lambda *a, **k: result)
    _quick_plots(monkeypatch)
    copies, real_copy = [], shutil.copyfile

    def copy(src, dst, *args, **kwargs):
        copies.append(src)
        if len(copies) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real_copy(src, dst)

    monkeypatch.setattr(atomic.shutil, "copyfile", copy)
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(out),
                     "--no-progress", "--accept-coverage"]) == 1
    line = [ln for ln in capsys.readouterr().err.splitlines() if "error:" in ln][0]
    assert "no space left on the device" in line
    kept = Path(line.split("the fitted camera is kept in ")[1])
    try:
        assert list(out.iterdir()) == []
        assert {"camera.json", "report.json", "report.md"} <= {p.name for p in kept.iterdir()}
    finally:
        shutil.rmtree(kept, ignore_errors=True)


@pytest.mark.parametrize("model", [m for m in ot.cameras.MODELS if m != "equirectangular"])
def test_every_model_writes_all_its_files(tmp_path, monkeypatch, model):
    """The files of a fit for every lens model (a fit from the truth on exact data, one
    iteration: the writers, not the fit, are tested here; the plots are stand-ins, drawn for
    real by the other tests)."""
    _quick_plots(monkeypatch)
    camera = _truth(model)
    board = checkerboard(5, 6, 0.04)
    pixels, poses, _ = random_views(camera, board, 3, generator=torch.Generator().manual_seed(2))
    result = fit(board, pixels, model, camera.image_size, init=camera, poses=poses,
                 max_iterations=1)
    data = Correspondences([board] * 3, pixels, camera.image_size, ["a", "b", "c"])
    coverage = assess_coverage(result.camera, result.covariance, pixels)
    files, report = write_fit_files(tmp_path, result, data, coverage=coverage, source="test",
                                    write_points=True)
    expected = {"camera.json", "report.json", "report.md", "residuals.png", "uncertainty.png",
                "correspondences.txt"} | ({"calib_results.txt"} if model == "scaramuzza"
                                          else set())
    assert {p.name for p in files} == expected == {p.name for p in tmp_path.iterdir()}
    assert ot.Camera.load_json(tmp_path / "camera.json").model.name == model
    assert json.loads((tmp_path / "report.json").read_text())["model"] == model


# --------------------------------------------------------------------------------------------
# report pieces
# --------------------------------------------------------------------------------------------

def test_view_errors_skip_the_outliers():
    """Per-view RMS and max over the corners the fit kept; the dropped ones listed with their
    distances (``FitResult.outliers``, where the fit has it)."""
    residuals = [torch.tensor([[3.0, 4.0], [0.0, 1.0], [1.0, 0.0]], dtype=D),
                 torch.tensor([[0.0, 2.0], [2.0, 0.0]], dtype=D)]
    dropped = [torch.tensor([0]), torch.tensor([], dtype=torch.long)]
    with_outliers = SimpleNamespace(residuals=residuals, outliers=dropped)
    rows = view_errors(with_outliers, [3, 2])
    assert rows[0] == {"points": 3, "kept": 2, "rms_px": 1.0, "max_px": 1.0, "outliers": [0],
                       "outlier_px": [5.0]}
    assert rows[1]["rms_px"] == 2.0 and rows[1]["outliers"] == []
    without = view_errors(SimpleNamespace(residuals=residuals), [3, 2])
    assert without[0]["kept"] == 3 and without[0]["max_px"] == 5.0
    assert without[0]["rms_px"] == pytest.approx(math.sqrt(27 / 3))


@pytest.mark.filterwarnings("ignore:The fit may be poorly conditioned")   # numpy, degree 20
def test_an_inverse_polynomial_that_misses_is_written_with_its_error(tmp_path):
    """A polynomial that folds inside the image (as a fit can beyond its corners) has no
    inverse polynomial within OCamCalib's 0.01 px: the file is written with the error it
    reaches and a warning, not a failed calibration (issue 19)."""
    from omniscape_torch.cameras.formats import fit_invpol

    camera = ot.Camera("scaramuzza", torch.tensor(
        [319.5, 239.5, 1.0, 0.0, 0.0, -200.0, 0.0, 0.0015, 0.0, -1e-8], dtype=D), (480, 640))
    with pytest.raises(ValueError, match="no inverse polynomial"):
        fit_invpol(camera)
    info = write_ocamcalib_file(camera, tmp_path / "calib_results.txt")
    assert 0.01 < info["max_error_px"] < 5 and "within" in info["warning"]
    back = ot.Camera.from_ocamcalib(tmp_path / "calib_results.txt")
    assert torch.allclose(back.params, camera.params) and back.invpol is not None
    # and a camera whose inverse polynomial is fine gets no warning
    fine = write_ocamcalib_file(_truth(), tmp_path / "fine.txt")
    assert fine["warning"] is None and fine["max_error_px"] < 0.01


# --------------------------------------------------------------------------------------------
# near-degenerate fits (issue 33)
# --------------------------------------------------------------------------------------------

def _narrow_views(tmp_path: Path) -> Path:
    """3 views of a 60-degree lens fitted with OCamCalib's polynomial: its highest
    coefficients trade off (a least-squares minimum that the views leave a direction of)."""
    truth = ot.cameras.presets.fisheye((96, 128), fov=math.radians(60), model="equidistant",
                                       dtype=D)
    board = checkerboard(5, 6, 0.05)
    pixels, _, _ = random_views(truth, board, 3, noise=0.3,
                                generator=torch.Generator().manual_seed(1))
    path = tmp_path / "narrow.txt"
    write_correspondences(path, Correspondences([board] * 3, pixels, truth.image_size,
                                                ["a", "b", "c"]))
    return path


@pytest.mark.numerics
def test_cli_writes_a_near_degenerate_fit_with_exit_3_unless_strict(tmp_path, capsys,
                                                                  monkeypatch):
    _quick_plots(monkeypatch)
    path = _narrow_views(tmp_path)
    results = []

    def recorded(*args, **kwargs):   # the command's own fit, kept for the oracle below
        results.append(fit(*args, **kwargs))
        return results[-1]

    # the module that calls fit (the package's calibrate names the function)
    monkeypatch.setattr(sys.modules["omniscape_torch.calibration.calibrate"], "fit", recorded)
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(out),
                     "--no-progress"]) == cli.EXIT_POORLY_CONSTRAINED
    result = results[0]
    assert not result.converged and result.near_degenerate, result.reason
    err = capsys.readouterr().err
    line = next(l for l in err.splitlines() if "near-degenerate:" in l)
    # the line names each loose parameter's most correlated partner and their correlation,
    # as the covariance gives it
    cov = result.covariance
    names = list(result.param_names)
    for name, partner, _ in result.near_degenerate:
        i, j = names.index(name), names.index(partner)
        corr = float(cov[i, j] / (cov[i, i] * cov[j, j]).sqrt())
        assert abs(corr) > 0.9
        assert (f"{name} and {partner} correlated at {corr:.3f}" in line
                or f"{partner} and {name} correlated at {corr:.3f}" in line)
    assert (out / "camera.json").exists()
    report = json.loads((out / "report.json").read_text())
    assert not report["converged"] and report["near_degenerate"]
    # --strict: today's refusal
    strict = tmp_path / "strict"
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(strict),
                     "--no-progress", "--strict"]) == 1
    assert "nothing written" in capsys.readouterr().err and not strict.exists()


@pytest.mark.slow
@pytest.mark.numerics
def test_cli_leave_one_out_reports_the_resampled_error(tmp_path, monkeypatch):
    """``--leave-one-out``: the jackknife of refits without each view, beside the prediction;
    on exact data every refit is the truth (0 px), on noisy data it is of the predicted
    size."""
    _quick_plots(monkeypatch)
    truth = ot.Camera("equidistant", torch.tensor([60.0, 60.0, 63.5, 47.5], dtype=D),
                      (96, 128))
    board = checkerboard(5, 6, 0.05)
    _, _, clean = random_views(truth, board, 5, generator=torch.Generator().manual_seed(2))
    noisy = clean + 0.3 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(5),
                                      dtype=D)
    figures = []
    for name, pixels in (("exact", clean), ("noisy", noisy)):
        path = tmp_path / f"{name}.txt"
        write_correspondences(path, Correspondences([board] * 5, list(pixels.unbind(0)),
                                                    truth.image_size, list("abcde")))
        out = tmp_path / name
        assert cli.main(["fit", str(path), "--model", "equidistant", "--out", str(out),
                         "--no-progress", "--leave-one-out", "--accept-coverage"]) == 0
        report = json.loads((out / "report.json").read_text())
        assert len(report["resampling"]["moves"]) == 5
        assert "leave-one-view-out" in (out / "report.md").read_text()
        figures.append((report["resampling"]["pixel_error"], report["coverage"]["pixel_rms"]))
    assert figures[0][0] < 1e-6
    assert 1 / 3 < figures[1][0] / figures[1][1] < 3, figures


# --------------------------------------------------------------------------------------------
# uncertainty.png (issue 33)
# --------------------------------------------------------------------------------------------

def test_uncertainty_map_scales_to_the_corners_and_masks_what_no_one_sees(few_views_fit):
    """The colour scale's top is the largest predicted error where the corners reach, not the
    extrapolated rim's (3 views: the rim is worse); the map is blank (NaN) outside the
    fov and inside the blind cone, and equal to the coverage's std elsewhere."""
    from omniscape_torch.calibration.report import uncertainty_map

    path, result = few_views_fit
    data = ot.calibration.read_correspondences(path)
    coverage = assess_coverage(result.camera, result.covariance, data.image_points)
    rim = float(coverage.std_map[torch.isfinite(coverage.std_map)].max())
    assert rim > 1.5 * coverage.max_pixel_std   # the rim set the scale before issue 33
    camera = ot.Camera(result.camera.model, result.camera.params, result.camera.image_size,
                       fov=math.radians(160), blind_fov=math.radians(40))
    std, top = uncertainty_map(coverage, camera)
    assert top == max(coverage.max_pixel_std, 1.2 * THRESHOLDS["max_pixel_error"])
    rays, _ = camera.model.unproject(coverage.grid, camera.params)
    theta = torch.rad2deg(torch.atan2(rays[..., :2].norm(dim=-1), rays[..., 2]))
    assert bool(std[theta <= 20].isnan().all()) and bool(std[theta > 80].isnan().all())
    seen = (theta > 20) & (theta <= 79)
    assert int(seen.sum()) > 100 and torch.equal(std[seen], coverage.std_map[seen])
