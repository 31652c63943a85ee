"""Calibration from correspondences (issue 6, items 1 and 5): ot.calibration.fit, the linear
OCamCalib solution, the correspondence file and ``omniscape-torch fit``.

The truth is synthetic: a known camera sees a checkerboard from random poses and Gaussian noise
of SIGMA pixels is added to every coordinate; a least-squares fit must then reach the noise
floor ``SIGMA sqrt((2 M - n) / (2 M))`` (M points, n free variables) and land within three of
its own standard deviations of the truth.
"""

from __future__ import annotations

import importlib
import json
import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.calibration import (Correspondences, checkerboard, default_intrinsics, fit,
                                         planar_pose, random_views, read_correspondences,
                                         scaramuzza_linear, write_correspondences)
from omniscape_torch.calibration.params import IntrinsicsMap, transform

from conftest import CASES, OCAMCALIB_FILE, fibonacci_sphere

SIGMA = 0.2  # pixels, per coordinate
D = torch.float64


pytestmark = [pytest.mark.numerics, pytest.mark.usefixtures("one_thread")]


def _truth(model: str) -> tuple[torch.Tensor, tuple[int, int]]:
    """A realistic camera of each model from conftest.CASES (the first distorted case)."""
    params, size = CASES[model][1 if model in ("kannala_brandt", "unified") else 0]
    params = torch.tensor(params, dtype=D)
    if model == "scaramuzza":
        # e is the sensor's roll about the optical axis, which the poses absorb: the fit holds
        # it (DEFAULT_FREEZE), so the comparable truth has e = 0
        params[4] = 0.0
    return params, size


def _views(model: str, n_views: int = 8, rows: int = 10, cols: int = 13, seed: int = 1,
           noise: float = SIGMA, **kwargs):
    params, size = _truth(model)
    camera = ot.Camera(model, params, size)
    board = checkerboard(rows, cols, 0.04)
    pixels, poses, clean = random_views(camera, board, n_views, noise=noise,
                                        generator=torch.Generator().manual_seed(seed), **kwargs)
    return params, size, board, pixels, poses, clean


LENS_MODELS = [m for m in ot.cameras.MODELS if m != "equirectangular"]
#: Over 2 s on 2 cores (8 views of 130 corners; the 2-D Newton of the projection's inverse in
#: the default starts); test_cli_fit_takes_the_issue_34_models is their fast test.
SLOW_FITS = ("fov", "opencv")


@pytest.mark.parametrize("model", [pytest.param(m, marks=pytest.mark.slow) if m in SLOW_FITS
                                   else m for m in LENS_MODELS])
def test_fit_reaches_the_noise_floor_and_the_truth(model):
    """Every model with intrinsics to fit (equirectangular is skipped: it is the panorama
    projection of a sphere, not a lens; there is nothing to calibrate from a board)."""
    truth, size, board, pixels, _, _ = _views(model)
    result = fit(board, pixels, model, size, degree=len(truth) - 6 if model == "scaramuzza" else 4)
    assert result.converged, result.reason
    m, n = result.num_observations, result.num_free
    assert m == 8 * 130 and n == len(result.free_names) + 6 * 8
    floor = SIGMA * math.sqrt(2) * math.sqrt((2 * m - n) / (2 * m))   # RMS distance
    # 5%: the spread of the RMS of 2M - n ~ 2000 squared Gaussians is 1.6%
    assert abs(result.rms - floor) <= 0.05 * floor, (result.rms, floor)
    free = [result.param_names.index(name) for name in result.free_names]
    err = (result.params - truth)[free]
    std = result.std[free]
    assert bool((std > 0).all()) and bool(torch.isfinite(std).all())
    assert bool((err.abs() <= 3 * std).all()), dict(zip(result.free_names, (err / std).tolist()))
    held = [i for i in range(len(truth)) if i not in free]
    assert torch.equal(result.params[held], truth[held])  # frozen at the truth (a1 = e = 0)
    assert [r.shape for r in result.residuals] == [(130, 2)] * 8


def test_kannala_brandt_fit_matches_opencv_fisheye_calibrate():
    """The same data through cv2.fisheye.calibrate (same model for z > 0, same cost): the two
    minima agree to a small fraction of the estimate's standard deviation."""
    cv2 = pytest.importorskip("cv2")
    truth, size, board, pixels, _, _ = _views("kannala_brandt", rows=6, cols=8,
                                              max_angle=math.radians(60))
    ours = fit(board, pixels, "kannala_brandt", size)
    assert ours.converged, ours.reason
    k = np.array([[200.0, 0, 319.5], [0, 200.0, 319.5], [0, 0, 1]])
    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | cv2.CALIB_USE_INTRINSIC_GUESS
    _, k, dist, _, _ = cv2.fisheye.calibrate(
        [board.numpy().reshape(1, -1, 3)] * len(pixels),
        [p.numpy().reshape(1, -1, 2) for p in pixels], size[::-1], k, np.zeros(4),
        flags=flags, criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-14))
    theirs = torch.tensor([k[0, 0], k[1, 1], k[0, 2], k[1, 2], *dist.ravel()], dtype=D)
    assert bool(((ours.params - theirs).abs() <= 1e-3 * ours.std).all()), \
        ((ours.params - theirs) / ours.std).tolist()


def test_linear_solution_is_exact_on_noise_free_data():
    """OCamCalib's linear solution recovers a camera with the centre at the image centre and
    no affine part exactly (checks the sign and axis conventions against the truth)."""
    truth = torch.tensor([319.5, 239.5, 1.0, 0.0, 0.0, -180.0, 0.0, 1.2e-3, -1.5e-6, 2e-9],
                         dtype=D)
    camera = ot.Camera("scaramuzza", truth, (480, 640))
    board = checkerboard(6, 8, 0.05)
    pixels, poses, _ = random_views(camera, board, 5, generator=torch.Generator().manual_seed(3))
    params, est = scaramuzza_linear([board] * 5, pixels, (480, 640), degree=4)
    assert torch.allclose(params, truth, rtol=1e-9, atol=1e-12)
    assert torch.allclose(est, poses, atol=1e-9)


def test_planar_pose_batched_and_masked_is_the_per_view_pose():
    """Views of one size in one batched call, and points masked out by ``valid``, give the pose
    of the per-view call on the kept points (to rounding); noise-free rays give the truth."""
    truth, size, board, pixels, poses, _ = _views("equidistant", n_views=4, rows=6, cols=8,
                                                  noise=0.0)
    model = ot.cameras.get_model("equidistant")
    rays = torch.stack([model.unproject(p, truth)[0] for p in pixels])
    valid = torch.ones(4, 48, dtype=torch.bool)
    valid[1, ::3] = False
    batched = planar_pose(board.expand(4, -1, -1), rays, valid)
    for i in range(4):
        alone = planar_pose(board[valid[i]], rays[i][valid[i]])
        assert torch.allclose(batched[i], alone, atol=1e-12)
    assert torch.allclose(batched, poses, atol=1e-9)


def test_linear_method_is_reported_as_unrefined_and_lm_improves_on_it():
    truth, size, board, pixels, _, _ = _views("scaramuzza", n_views=5, rows=6, cols=8)
    linear = fit(board, pixels, "scaramuzza", size, method="linear")
    refined = fit(board, pixels, "scaramuzza", size)
    assert linear.converged and linear.iterations == 0 and "not refined" in linear.reason
    assert refined.converged
    assert refined.rms < linear.rms


@pytest.mark.slow
def test_lbfgs_reaches_the_lm_minimum():
    _, size, board, pixels, _, _ = _views("equidistant", n_views=3, rows=6, cols=8)
    lm = fit(board, pixels, "equidistant", size)
    lbfgs = fit(board, pixels, "equidistant", size, method="lbfgs", max_iterations=1500)
    assert lm.converged and lbfgs.converged, lbfgs.reason
    assert lbfgs.cost <= lm.cost * (1 + 1e-8)
    assert bool(((lbfgs.params - lm.params).abs() <= 1e-2 * lm.std).all())


@pytest.mark.parametrize("method", ["lbfgs", "adam"])
def test_a_method_stopped_early_says_it_did_not_converge(method):
    _, size, board, pixels, _, _ = _views("equidistant", n_views=3, rows=6, cols=8)
    lm = fit(board, pixels, "equidistant", size)
    for iterations in (5, 200):
        short = fit(board, pixels, "equidistant", size, method=method,
                    max_iterations=iterations)
        assert not short.converged and f"{iterations} iterations" in short.reason
        assert "not at a minimum" in short.reason and short.cost > lm.cost
        assert short.camera is not None  # the result is there to inspect, flagged


def test_frozen_groups_stay_put_with_zero_std():
    truth, size, board, pixels, _, _ = _views("kannala_brandt", n_views=4, rows=6, cols=8)
    start = truth.clone()
    start[4:] = 0.0
    result = fit(board, pixels, "kannala_brandt", size, init=start,
                 freeze=("center", "distortion"))
    assert result.free_names == ("fx", "fy")
    assert torch.equal(result.params[2:], start[2:])
    assert torch.equal(result.std[2:], torch.zeros(6, dtype=D))
    assert bool((result.std[:2] > 0).all())
    # the same, by name (issue 46: std was an unnamed tensor)
    assert list(result.std_by_name) == ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"]
    assert result.std_by_name["fx"] == float(result.std[0]) > 0 == result.std_by_name["k4"]
    assert result.params_by_name["cx"] == float(start[2])
    with pytest.raises(ValueError, match="freeze: 'lens'"):
        fit(board, pixels, "kannala_brandt", size, freeze=("lens",))


@pytest.mark.parametrize("model", ["unified", "eucm", "double_sphere"])
def test_reparametrisation_keeps_any_free_vector_in_the_model_range(model):
    params = torch.tensor(CASES[model][1][0], dtype=D)  # inside the ranges, off their edges
    mapping = IntrinsicsMap(ot.cameras.get_model(model), params, (640, 640))
    z = 30 * torch.randn(200, len(mapping.free), generator=torch.Generator().manual_seed(0),
                         dtype=D)
    for row in z:
        natural = mapping.natural(row)
        if bool(torch.isfinite(natural).all()):  # exp may overflow: that is not a range error
            mapping.model.validate_params(natural)
    assert torch.allclose(mapping.natural(mapping.z0()), params)


@pytest.mark.parametrize("model", sorted(CASES))
def test_the_written_out_jacobian_of_the_reparametrisation_is_autograd_s(model):
    """``IntrinsicsMap.jacobian`` (derivatives written out, every kind: log, softplus, sigmoid,
    tanh, shifts) against ``torch.func.jacrev`` of ``natural``, with some parameters held."""
    gen = torch.Generator().manual_seed(1)
    for params, size in CASES[model]:
        params = torch.tensor(params, dtype=D)
        for frozen in ([], [0, 2]):
            mapping = IntrinsicsMap(ot.cameras.get_model(model), params, size, frozen)
            z = mapping.z0() + 0.3 * torch.randn(len(mapping.free), generator=gen, dtype=D)
            expected = torch.func.jacrev(mapping.natural)(z)
            assert torch.allclose(mapping.jacobian(z), expected, rtol=1e-13, atol=0)


def test_robust_losses_resist_gross_outliers():
    truth, size, board, pixels, _, _ = _views("equidistant", n_views=6, rows=6, cols=8)
    gen = torch.Generator().manual_seed(5)
    corrupted = []
    for p in pixels:
        bad = torch.rand(len(p), generator=gen) < 0.05
        corrupted.append(p + bad[:, None] * 40.0 * torch.sign(torch.randn(p.shape, generator=gen,
                                                                          dtype=D)))
    plain = fit(board, corrupted, "equidistant", size)
    clean = fit(board, pixels, "equidistant", size)
    for loss in ("huber", "cauchy"):
        robust = fit(board, corrupted, "equidistant", size, loss=loss, loss_scale=1.0)
        assert robust.converged, robust.reason
        err = (robust.params - truth).abs()
        assert bool((err <= 4 * clean.std).all()), (loss, (err / clean.std).tolist())
    assert float(((plain.params - truth).abs() / clean.std).max()) > 10


def _ray_rms(camera, truth, poses, board) -> float:
    """RMS pixel distance between ``camera``'s and ``truth``'s projections of the truth's rays
    on a 32 x 32 grid, within the largest angle off the axis the boards covered (as
    ``benchmarks/calibration_stability.py`` measures it)."""
    h, w = truth.image_size
    v, u = torch.meshgrid((torch.arange(32, dtype=D) + 0.5) / 32 * h - 0.5,
                          (torch.arange(32, dtype=D) + 0.5) / 32 * w - 0.5, indexing="ij")
    grid = torch.stack((u, v), -1).reshape(-1, 2)
    rays, ok = truth.unproject(grid)
    seen = transform(poses[:, None], board)
    covered = torch.atan2(seen[..., :2].norm(dim=-1), seen[..., 2]).max()
    ok = ok & (torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2]) <= covered)
    projected, valid = camera.model.project(rays[ok], camera.params)
    assert bool(valid.all())
    return float(((projected - grid[ok]) ** 2).sum(-1).mean().sqrt())


def _mei_230():
    """A Mei camera (unified with distortion) whose 230 degrees fill an 800 x 800 image."""
    camera, _ = ot.cameras.presets.catadioptric((800, 800), fov=math.radians(230),
                                                blind_fov=None, dtype=D)
    params = camera.params.clone()
    params[5:9] = torch.tensor([-0.05, 0.01, 2e-4, -1e-4], dtype=D)
    return ot.Camera("unified", params, (800, 800), fov=math.radians(230))


def test_the_default_starts_converge_where_the_single_start_did_not():
    """Issue 19: a 230-degree Mei camera, 5 views of a 9 x 6 board. The former default (one
    start, the focal of a 180-degree lens, at most 100 iterations) crawls along the xi-focal-k1
    valley and stops unconverged; the default now ranks the linear solution and several
    fields of view by a short run and finishes the best in a few tens of iterations."""
    truth = _mei_230()
    board = checkerboard(6, 9, 0.08)
    pixels, poses, _ = random_views(truth, board, 5, noise=0.3,
                                    generator=torch.Generator().manual_seed(8))
    single = fit(board, pixels, "unified", (800, 800), max_iterations=100,
                 init=default_intrinsics("unified", (800, 800)))
    assert not single.converged and "100 iterations without converging" in single.reason
    result = fit(board, pixels, "unified", (800, 800))
    assert result.converged, result.reason
    assert result.iterations < 100 and result.start in ("linear", "fov 180", "fov 120",
                                                        "fov 230")
    assert _ray_rms(result.camera, truth, poses, board) < 1.0
    assert result.cost < single.cost


def test_levenberg_marquardt_goes_on_while_the_cost_falls(monkeypatch):
    """Without max_iterations, LM runs in rounds (LM_ROUND) and starts another while the last
    lowered the cost by more than LM_PROGRESS; an explicit max_iterations is a hard limit."""
    fit_module = importlib.import_module("omniscape_torch.calibration.fit")  # not the function
    truth, size, board, pixels, _, _ = _views("unified", n_views=4, rows=6, cols=8)
    init = torch.tensor([250.0, 250.0, 319.5, 319.5, 1.0, 0.0, 0.0, 0.0, 0.0], dtype=D)
    monkeypatch.setattr(fit_module, "LM_ROUND", 3)
    monkeypatch.setattr(fit_module, "LM_PROGRESS", 1e-12)
    rounds = fit(board, pixels, "unified", size, init=init)
    assert rounds.converged and rounds.iterations > 3, rounds.reason
    assert [h["iteration"] for h in rounds.history if h["accepted"]] == list(
        range(1, rounds.iterations + 1))
    capped = fit(board, pixels, "unified", size, init=init, max_iterations=3)
    assert not capped.converged and capped.iterations == 3
    monkeypatch.setattr(fit_module, "LM_PROGRESS", math.inf)  # no round lowers the cost enough
    stalled = fit(board, pixels, "unified", size, init=init)
    assert not stalled.converged and stalled.iterations == 3
    assert "3 iterations without converging (the last 3 lowered the cost by" in stalled.reason


def test_outlier_rejection_lists_the_gross_outliers_and_refits_without_them():
    """Three corners moved by 20 px among 288: the robust fit, then the 3-sigma rounds, drop
    exactly those and the plain refit lands within 1 px of the truth's rays."""
    truth, size = _truth("kannala_brandt")
    camera = ot.Camera("kannala_brandt", truth, size)
    board = checkerboard(6, 8, 0.08)  # large enough that 6 views pin the lens down to 1 px
    pixels, poses, _ = random_views(camera, board, 6, noise=SIGMA,
                                    generator=torch.Generator().manual_seed(1))
    moved = {(0, 5): (20.0, 0.0), (2, 17): (0.0, -20.0), (4, 40): (-14.0, 14.0)}
    pixels = [p.clone() for p in pixels]
    for (v, i), shift in moved.items():
        pixels[v][i] += torch.tensor(shift, dtype=D)
    result = fit(board, pixels, "kannala_brandt", size, reject_outliers=True)
    assert result.converged, result.reason
    assert all(o.dtype == torch.int64 for o in result.outliers) and len(result.outliers) == 6
    assert {(v, int(i)) for v, o in enumerate(result.outliers) for i in o} == set(moved)
    assert result.num_observations == 6 * 48 - 3
    assert [r.shape for r in result.residuals] == [(48, 2)] * 6  # every input point
    assert float(result.residuals[0][5].norm()) > 15  # the dropped one, at the solution
    assert _ray_rms(result.camera, camera, poses, board) < 1.0
    plain = fit(board, pixels, "kannala_brandt", size)
    assert [o.numel() for o in plain.outliers] == [0] * 6
    assert plain.rms > 2 * result.rms
    assert result.to_dict()["outliers"] == [[5], [], [17], [], [40], []]
    with pytest.raises(ValueError, match="outlier_threshold"):
        fit(board, pixels, "kannala_brandt", size, reject_outliers=True, outlier_threshold=0)
    with pytest.raises(TypeError, match="reject_outliers"):
        fit(board, pixels, "kannala_brandt", size, reject_outliers="yes")


@pytest.mark.parametrize("model, seed", [("pinhole", 1), ("scaramuzza", 0)])
def test_degenerate_views_are_reported_as_not_converged(model, seed):
    """All boards fronto-parallel: the focal length (the polynomial's scale) trades off against
    the distance, exactly for a pinhole, nearly for the polynomial lens (huge error bars)."""
    _, size, board, pixels, _, _ = _views(model, n_views=5, rows=6, cols=8, seed=seed,
                                          fronto_parallel=True)
    result = fit(board, pixels, model, size, max_iterations=30)
    assert not result.converged
    assert "degenerate data" in result.reason


def test_projections_outside_the_domain_are_counted_not_dropped():
    """A Kannala-Brandt lens folding at 111 degrees, held fixed, cannot see the points of a room
    that an equidistant camera sees up to 120 degrees all around its axis."""
    truth = ot.Camera("equidistant", torch.tensor([150.0, 150.0, 399.5, 399.5], dtype=D),
                      (800, 800))
    dirs = fibonacci_sphere(400)
    dirs = dirs[dirs[:, 2] > math.cos(math.radians(120))]
    points = 2.0 * dirs
    pixels, valid = truth.project(points)
    assert bool(valid.all())
    init = torch.tensor([150.0, 150.0, 399.5, 399.5, -0.12, 0.005, 0.0, 0.0], dtype=D)
    result = fit(points, pixels[None], "kannala_brandt", (800, 800), init=init,
                 poses=torch.zeros(1, 6, dtype=D), freeze=("distortion",))
    beyond = int((torch.atan2(dirs[:, :2].norm(dim=-1), dirs[:, 2])
                  > ot.cameras.get_model("kannala_brandt").max_angle(init)).sum())
    assert beyond > 0 and result.num_invalid >= beyond // 2
    assert not result.converged and "outside the model's domain" in result.reason


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------

def test_bad_input_raises_clear_errors():
    truth, size, board, pixels, _, _ = _views("equidistant", n_views=2, rows=4, cols=5)
    with pytest.raises(ValueError, match="not more than the 20 free parameters"):
        fit(board[:4], [p[:4] for p in pixels], "kannala_brandt", size)
    nan = [pixels[0].clone(), pixels[1]]
    nan[0][3, 1] = math.nan
    with pytest.raises(ValueError, match=r"image_points\[0\].*point 3"):
        fit(board, nan, "equidistant", size)
    with pytest.raises(ValueError, match="view 1: 20 target points but 19 pixels"):
        fit(board, [pixels[0], pixels[1][:-1]], "equidistant", size)
    with pytest.raises(ValueError, match="3 views of target points but 2 views of pixels"):
        fit([board] * 3, pixels, "equidistant", size)
    with pytest.raises(ValueError, match=r"image_points\[0\]: expected shape \(N, 2\)"):
        fit(board, [p[:, :1] for p in pixels], "equidistant", size)
    with pytest.raises(TypeError, match="image_points"):
        fit(board, "pixels", "equidistant", size)
    with pytest.raises(ValueError, match="method"):
        fit(board, pixels, "equidistant", size, method="newton")
    with pytest.raises(ValueError, match="method: 'linear'"):
        fit(board, pixels, "equidistant", size, method="linear")
    with pytest.raises(ValueError, match="loss"):
        fit(board, pixels, "equidistant", size, loss="l1")
    with pytest.raises(ValueError, match="loss_scale"):
        fit(board, pixels, "equidistant", size, loss="huber", loss_scale=0)
    with pytest.raises(ValueError, match="equirectangular"):
        fit(board, pixels, "equirectangular", size)
    with pytest.raises(ValueError, match="init"):
        fit(board, pixels, "equidistant", size, init=[200.0, -1.0, 300.0, 300.0])
    with pytest.raises(ValueError, match="planar"):
        fit(board + torch.tensor([0.0, 0.0, 1.0], dtype=D) * board[:, :1], pixels,
            "scaramuzza", size)


# --------------------------------------------------------------------------------------------
# The correspondence file and the command line
# --------------------------------------------------------------------------------------------

def _write(tmp_path, model="scaramuzza", **kwargs):
    truth, size, board, pixels, _, _ = _views(model, **kwargs)
    path = tmp_path / "corr.txt"
    write_correspondences(path, Correspondences([board] * len(pixels), pixels, size,
                                                [f"v{i}" for i in range(len(pixels))]))
    return truth, size, path


def test_correspondence_file_round_trip(tmp_path):
    truth, size, path = _write(tmp_path, n_views=3, rows=4, cols=5)
    text = path.read_text().splitlines()
    assert text[0] == "omniscape-torch correspondences 1" and text[1] == f"image_size {size[0]} " \
        f"{size[1]}" and text[2] == "view v0" and len(text[3].split()) == 5
    data = read_correspondences(path)
    assert data.image_size == size and data.names == ["v0", "v1", "v2"]
    _, _, board, pixels, _, _ = _views("scaramuzza", n_views=3, rows=4, cols=5)
    for a, b in zip(data.image_points, pixels):
        assert torch.equal(a, b)  # 17 significant digits: exact
    assert torch.equal(data.object_points[0], board)


@pytest.mark.parametrize("text, match", [
    ("# calib_results.txt\n5 -1 0 1\n", "line 2: expected the header"),
    ("omniscape-torch correspondences 1\nview a\n0 0 0 1 1\n", "no 'image_size"),
    ("omniscape-torch correspondences 1\nimage_size 10\n", "line 2: image_size"),
    ("omniscape-torch correspondences 1\nimage_size 10 10\n0 0 0 1 1\n", "line 3: a point"),
    ("omniscape-torch correspondences 1\nimage_size 10 10\nview a\n0 0 0 1\n", "line 4: expected"),
    ("omniscape-torch correspondences 1\nimage_size 10 10\nview a\n0 0 0 1 nan\n", "5 finite"),
    ("omniscape-torch correspondences 1\nimage_size 10 10\nview a\n0 0 0 1 1\n", "at least 4"),
    ("", "empty"),
])
def test_correspondence_file_in_the_wrong_format_is_refused(tmp_path, text, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_correspondences(path)


def test_cli_fit_writes_json_and_calib_results(tmp_path, capsys):
    truth, size, path = _write(tmp_path, n_views=5, rows=6, cols=8)
    out = tmp_path / "out"
    # 5 views of a 6 x 8 board leave the image poorly covered (exit 3 without the option)
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(out),
                        "--no-progress", "--accept-coverage"]) == 0
    report = json.loads((out / "camera.json").read_text())
    assert report["fit"]["converged"] and report["model"] == "scaramuzza"
    std = torch.tensor(list(report["fit"]["std"].values()), dtype=D)
    for camera in (ot.Camera.load_json(out / "camera.json"),
                   ot.Camera.from_ocamcalib(out / "calib_results.txt")):
        err = (camera.params.double() - truth).abs()
        assert bool((err <= 3 * std + 1e-12 * truth.abs()).all()), (err / std).tolist()
    assert "rms" in capsys.readouterr().out


def test_cli_fit_failure_writes_nothing(tmp_path, capsys):
    _, _, path = _write(tmp_path, n_views=3, rows=4, cols=5)
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--method", "adam",
                        "--max-iterations", "3", "--out", str(out), "--no-progress"]) == 1
    assert not out.exists() and "did not converge" in capsys.readouterr().err
    # an OCamCalib calib_results.txt is not a correspondence file
    assert cli.main(["fit", str(OCAMCALIB_FILE), "--model", "scaramuzza", "--out",
                     str(out)]) == 2
    assert "line 3: expected the header" in capsys.readouterr().err


ISSUE_34 = ["fov", "division", "opencv", "thin_prism_fisheye", "fisheye624"]


@pytest.mark.parametrize("model", ISSUE_34)
def test_issue_34_models_fit_a_small_board_to_the_noise_floor(model):
    """The fast test of issue 34's models (test_fit_reaches_the_noise_floor_and_the_truth is
    slow for some): 5 views of a 7 x 9 board from the default starts, converged at the noise
    floor (within 10 percent: 2M - n ~ 560 squared Gaussians)."""
    truth, size, board, pixels, _, _ = _views(model, n_views=5, rows=7, cols=9)
    result = fit(board, pixels, model, size)
    assert result.converged, result.reason
    m, n = result.num_observations, result.num_free
    assert m == 5 * 63 and n == len(result.free_names) + 6 * 5
    floor = SIGMA * math.sqrt(2) * math.sqrt((2 * m - n) / (2 * m))
    assert abs(result.rms - floor) <= 0.1 * floor, (result.rms, floor)


@pytest.mark.parametrize("model", ISSUE_34)
def test_cli_fit_takes_the_issue_34_models(model):
    args = cli.build_parser().parse_args(["fit", "corr.txt", "--model", model, "--out", "o"])
    assert args.model == model


def test_cli_fit_writes_an_issue_34_model(tmp_path, capsys):
    """``fit --model division`` end to end (the fastest of the five: about 1 s)."""
    truth, size, path = _write(tmp_path, "division", n_views=5, rows=7, cols=9)
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "division", "--out", str(out),
                     "--no-progress", "--accept-coverage"]) == 0
    report = json.loads((out / "camera.json").read_text())
    assert report["fit"]["converged"] and report["model"] == "division"
    camera = ot.Camera.load_json(out / "camera.json")
    for name in report["fit"]["free"]:
        i, std = camera.model.param_names.index(name), report["fit"]["std"][name]
        assert abs(float(camera.params[i]) - float(truth[i])) <= 3 * std, (name, std)
    assert "rms" in capsys.readouterr().out
