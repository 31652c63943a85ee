"""Model conversion and model selection (issue 6, items 2, 3 and 5): ot.calibration.convert,
ot.calibration.select_model and ``omniscape-torch convert-model``."""

from __future__ import annotations

import json
import math

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.calibration import checkerboard, convert, random_views, select_model
from omniscape_torch.calibration.convert import sample_pixels

from conftest import OCAMCALIB_FILE

D = torch.float64


pytestmark = [pytest.mark.numerics, pytest.mark.usefixtures("one_thread")]

#: A polynomial lens of true degree 3 (a0, a1 = 0, a2, a3), folding near rho = 430 px.
POLY3 = [320.0, 310.0, 1.0, 0.0, 0.0, -200.0, 0.0, 1.5e-3, -3e-6]


def _camera(model, params, size=(640, 640)):
    return ot.Camera(model, torch.tensor(params, dtype=D), size)


# (source, target, the target's parameters written from the source's by the model's algebra)
NESTED = [
    pytest.param(("kannala_brandt", [200.0, 201.0, 319.5, 318.5, 0, 0, 0, 0]), "equidistant",
                 [200.0, 201.0, 319.5, 318.5], id="kannala_brandt(k=0)->equidistant"),
    pytest.param(("equidistant", [200.0, 205.0, 319.5, 299.5]), "kannala_brandt",
                 [200.0, 205.0, 319.5, 299.5, 0, 0, 0, 0], id="equidistant->kannala_brandt"),
    # double sphere with xi = 0 is the unified model with xi = alpha / (1 - alpha), f / (1 - alpha)
    pytest.param(("double_sphere", [160.0, 161.0, 319.5, 319.5, 0.0, 0.6]), "unified",
                 [400.0, 402.5, 319.5, 319.5, 1.5, 0, 0, 0, 0], id="double_sphere(xi=0)->unified"),
    # EUCM with beta = 1 is the same unified model
    pytest.param(("eucm", [260.0, 262.0, 319.5, 319.5, 0.3, 1.0]), "unified",
                 [260 / 0.7, 262 / 0.7, 319.5, 319.5, 0.3 / 0.7, 0, 0, 0, 0],
                 id="eucm(beta=1)->unified"),
    # unified with xi = 0 is the pinhole camera
    pytest.param(("unified", [400.0, 401.0, 319.5, 319.5, 0, 0, 0, 0, 0]), "pinhole",
                 [400.0, 401.0, 319.5, 319.5], id="unified(xi=0)->pinhole"),
    # a degree-3 polynomial is a degree-5 one with a4 = a5 = 0
    pytest.param(("scaramuzza", POLY3), "scaramuzza", POLY3 + [0.0, 0.0],
                 id="scaramuzza(3)->scaramuzza(5)"),
]


@pytest.mark.parametrize("source, target, expected", NESTED)
def test_conversion_between_nested_models_is_exact(source, target, expected):
    camera = _camera(*source)
    result = convert(camera, target, degree=5)
    assert result.converged, result.fit.reason
    assert result.max_px < 1e-6 and result.max_angle < 1e-8 and result.unrepresentable == 0
    expected = torch.tensor(expected, dtype=D)
    assert torch.allclose(result.fit.params, expected, rtol=1e-7, atol=1e-12 + 1e-7 * float(
        expected.abs().max()) * (target != "scaramuzza"))


def test_conversion_reports_what_the_target_cannot_represent():
    """A 200-degree equidistant lens to a pinhole camera: everything past 90 degrees is lost."""
    camera = _camera("equidistant", [100.0, 100.0, 319.5, 319.5])
    result = convert(camera, "pinhole")
    # the held-out grid: pixel centres at (i + 0.75) / 48 of each side; r = f theta
    steps = (torch.arange(48, dtype=D) + 0.75) / 48 * 640 - 0.5 - 319.5
    radius = torch.hypot(steps[:, None], steps[None, :])
    seen = radius < 100.0 * math.pi  # the source's own domain, theta < 180 degrees
    behind = float((radius[seen] >= 100.0 * math.pi / 2).double().mean())
    assert behind > 0.5
    assert abs(result.unrepresentable - behind) < 1e-9
    assert result.fit.num_invalid == 0  # the dropped samples are not fitted


#: The real OCamCalib camera (190-degree class fisheye, 1600 x 1600, whole image valid) to
#: four models. Measured (held-out grid of 48 x 48, in pixels and degrees): max / RMS pixel
#: error and max angular error; the bounds below are those figures plus about 20 percent.
REAL_BOUNDS = {
    "kannala_brandt": (2.2, 0.6, 0.19),    # measured 1.78 px, 0.48 px, 0.154 deg
    "unified": (8.2, 1.05, 0.65),          # measured 6.76 px, 0.86 px, 0.531 deg
    "double_sphere": (16.7, 2.45, 1.92),   # measured 13.8 px, 2.03 px, 1.60 deg
    "eucm": (35.5, 3.7, 6.5),              # measured 29.6 px, 3.10 px, 5.40 deg
}


@pytest.mark.parametrize("model", list(REAL_BOUNDS))
def test_real_ocamcalib_camera_to_other_models(model):
    real = ot.Camera.from_ocamcalib(OCAMCALIB_FILE)
    result = convert(real, model)
    assert result.converged, result.fit.reason
    max_px, rms_px, max_deg = REAL_BOUNDS[model]
    assert result.max_px <= max_px and result.rms_px <= rms_px
    assert math.degrees(result.max_angle) <= max_deg
    assert result.unrepresentable == 0
    # the fitted centre stays on OCamCalib's (column, row) = (798.18, 794.31)
    assert torch.allclose(result.fit.params[2:4], real.params[:2].double(), atol=0.05)


def test_lm_at_a_minimum_it_cannot_improve_stops_converged():
    """The real lens is far from equisolid: at the best equisolid fit LM cannot lower the cost
    any more (once reported as "damping above 1e16", not converged). Converged, with the large
    error reported, and a true minimum whichever stopping rule fired first (that depends on
    the machine's rounding): a Gauss-Newton step would gain nothing (the gradient is zero in
    the metric of J^T J), and nudging any parameter raises the cost on the samples it was
    fitted to."""
    real = ot.Camera.from_ocamcalib(OCAMCALIB_FILE)
    result = convert(real, "equisolid")
    assert result.converged, result.fit.reason
    assert result.fit.gauss_newton_gain <= 1e-6   # relative to the cost: optimality_tol
    assert result.rms_px > 10   # converged is not "fits well": the error says how badly
    pixels, rays = sample_pixels(real, 48, 0.25)
    model, best = result.fit.camera.model, result.fit.params

    keep = model.project(rays, best)[1]   # the samples the fit kept, held fixed

    def cost(params):
        projected, valid = model.project(rays, params)
        assert bool(valid[keep].all())
        return float(((projected - pixels)[keep] ** 2).sum())

    base = cost(best)
    for i in range(len(best)):
        for step in (-1e-4, 1e-4):
            nudged = best.clone()
            nudged[i] += step * max(1.0, abs(float(best[i])))
            assert cost(nudged) >= base


def test_real_camera_degree_change():
    real = ot.Camera.from_ocamcalib(OCAMCALIB_FILE)
    up = convert(real, "scaramuzza", degree=6)
    down = convert(real, "scaramuzza", degree=2)
    assert up.converged and up.max_px < 1e-6
    assert down.converged and down.max_px > 1.0  # a quadratic cannot follow a quartic lens


def test_select_model_recovers_the_degree_of_a_polynomial_camera():
    camera = _camera("scaramuzza", POLY3)
    selection = select_model(camera, 1e-3)
    assert selection.best is not None
    assert (selection.best.model, selection.best.degree) == ("scaramuzza", 3)
    rows = {(c.model, c.degree): c for c in selection.table}
    assert rows[("scaramuzza", 2)].heldout_rms > 1e-3 and not rows[("scaramuzza", 2)].within
    assert rows[("scaramuzza", 4)].within  # also fits, but with a parameter more
    assert len(selection.table) == len(ot.calibration.select.DEFAULT_CANDIDATES)


def test_select_model_from_noisy_correspondences_uses_held_out_points():
    """0.2 px noise: the true degree's held-out RMS is near 0.2 px; degree 2 misses by pixels."""
    camera = _camera("scaramuzza", POLY3)
    board = checkerboard(9, 12, 0.03)
    pixels, _, _ = random_views(camera, board, 6, noise=0.2,
                                generator=torch.Generator().manual_seed(2))
    candidates = [("scaramuzza", d) for d in (2, 3, 4)]
    selection = select_model((board, pixels), 0.25, image_size=(640, 640),
                             candidates=candidates)
    assert (selection.best.model, selection.best.degree) == ("scaramuzza", 3)
    by_degree = {c.degree: c for c in selection.table}
    assert 0.15 < by_degree[3].heldout_rms < 0.25 and by_degree[2].heldout_rms > 0.5


def test_conversion_bad_input():
    camera = _camera("equidistant", [200.0, 205.0, 319.5, 299.5])
    batch = ot.Camera("equidistant", torch.tensor([[200.0, 205.0, 319.5, 299.5]] * 2), (640, 640))
    with pytest.raises(TypeError, match="camera"):
        convert("camera.json", "unified")
    with pytest.raises(ValueError, match="batch"):
        convert(batch, "unified")
    with pytest.raises(ValueError, match="unknown camera model"):
        convert(camera, "fisheye")
    with pytest.raises(ValueError, match="equirectangular"):
        convert(camera, "equirectangular")
    with pytest.raises(ValueError, match="grid"):
        convert(camera, "unified", grid=2)
    with pytest.raises(ValueError, match="tolerance"):
        select_model(camera, 0.0)
    with pytest.raises(TypeError, match="source"):
        select_model(42, 1.0)
    with pytest.raises(ValueError, match="image_size"):
        select_model((checkerboard(), [torch.zeros(108, 2, dtype=D)]), 1.0)


def test_cli_convert_model(tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["convert-model", "--ocamcalib", str(OCAMCALIB_FILE), "--to",
                     "kannala_brandt,scaramuzza", "--degree", "5", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "kannala_brandt" in printed and "yes" in printed
    camera = ot.Camera.load_json(out / "kannala_brandt.json")
    assert camera.model.name == "kannala_brandt"
    report = json.loads((out / "kannala_brandt.json").read_text())["conversion"]
    assert report["converged"] and report["max_px"] < REAL_BOUNDS["kannala_brandt"][0]
    assert ot.Camera.from_ocamcalib(out / "calib_results.txt").params.shape == (11,)
    with pytest.raises(SystemExit, match="no calibration file"):
        cli.main(["convert-model", "--ocamcalib", str(tmp_path / "missing.txt"), "--to", "eucm"])
