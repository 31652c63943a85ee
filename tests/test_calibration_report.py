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
    assert coverage.max_pixel_std < THRESHOLDS["max_pixel_std"]
    assert coverage.cells >= THRESHOLDS["min_cells"]
    # and a fit it passes is good: against the truth, over the area the corners reach, within
    # the limit it applied to the predicted error
    grid = coverage.grid.reshape(-1, 2)
    rays, valid = ot.Camera(model, camera.params, camera.image_size,
                            fov=2 * coverage.angle).unproject(grid)
    pixels_fit, _ = result.camera.project(rays[valid])
    err = (pixels_fit - grid[valid]).norm(dim=-1)
    assert float(err.pow(2).mean().sqrt()) < THRESHOLDS["max_pixel_std"], float(err.max())


def test_coverage_of_an_undetermined_fit():
    """A covariance that is not finite (degenerate views) is an undetermined calibration."""
    camera = _truth("equidistant")
    cov = torch.full((4, 4), math.inf, dtype=D)
    pixels = [torch.tensor([[300.0, 300.0], [340.0, 300.0], [300.0, 340.0]], dtype=D)]
    coverage = assess_coverage(camera, cov, pixels)
    assert not coverage.ok and math.isinf(coverage.max_pixel_std)
    assert any("undetermined" in w for w in coverage.warnings)
    assert coverage.to_dict()["max_pixel_std"] is None   # JSON has no inf


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
    assert top == max(coverage.max_pixel_std, 1.2 * THRESHOLDS["max_pixel_std"])
    rays, _ = camera.model.unproject(coverage.grid, camera.params)
    theta = torch.rad2deg(torch.atan2(rays[..., :2].norm(dim=-1), rays[..., 2]))
    assert bool(std[theta <= 20].isnan().all()) and bool(std[theta > 80].isnan().all())
    seen = (theta > 20) & (theta <= 79)
    assert int(seen.sum()) > 100 and torch.equal(std[seen], coverage.std_map[seen])
