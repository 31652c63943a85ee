"""Calibration I/O (``omniscape_torch.cameras.formats``) against OCamCalib's own code.

* Reading the real ``calib_results.txt``: our ``scaramuzza`` camera reproduces OCamCalib's
  ``cam2world`` / ``world2cam`` (``tests/ocamcalib_reference.py``, an independent numpy
  transcription of its C code), with the axis conversion done here:
  OCamCalib (x_oc, y_oc, z_oc) = (y, x, -z) ours, pixel (row, col) = (v, u).
* Writing: the written file is read by OCamCalib's C ``get_ocam_model`` (compiled harness of
  ``tests/c_reference``) and by our reader; its refitted ``invpol`` is compared with the
  toolbox's ``findinvpoly``.
* JSON round trips for every registered model, atomic writes, and malformed files.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ocamcalib_reference as ref  # noqa: E402
from test_ocamcalib_reference import (c_cam2world, c_model, c_world2cam,  # noqa: E402,F401
                                      harness)

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.cameras.scaramuzza import scaramuzza_project  # noqa: E402
from omniscape_torch.cameras.formats import fit_invpol  # noqa: E402

#: Numerically sensitive: CI runs this module again with OMP_NUM_THREADS=1 (.ci/run).
pytestmark = pytest.mark.numerics

REAL_CALIB = (Path(__file__).resolve().parents[1].parent
              / "shared/data/ocamcalib_real/calib_results_0.txt")
needs_real = pytest.mark.skipif(not REAL_CALIB.is_file(), reason=f"missing {REAL_CALIB}")

RAY_TOL = 1e-9       # rad, same polynomial evaluated twice
PIX_TOL = 1e-6       # px, same inverse polynomial evaluated twice
ROUNDTRIP_TOL = 1e-9  # px, exact projection after exact unprojection
FIT_TOL = 0.01       # px, OCamCalib's findinvpoly target (max error at its samples)
# The file's invpol (or a refitted one) against the exact inverse, anywhere in the image: the fit
# bounds the error by 0.01 px at its samples only; beyond the last sample (127.2 deg, rho at the
# half-diagonal) up to the farthest image corner (128.1 deg) it extrapolates (~0.0125 px).
LOOSE_TOL = 0.02


# ---------------------------------------------------------------------------
# helpers (axis conversion and grids)
# ---------------------------------------------------------------------------
def ocam_to_ours(p):
    """OCamCalib (x_oc, y_oc, z_oc) -> ours (x, y, z) = (y_oc, x_oc, -z_oc)."""
    p = np.asarray(p, dtype=np.float64)
    return np.stack([p[..., 1], p[..., 0], -p[..., 2]], -1)


def ours_to_ocam(p):
    p = np.asarray(p, dtype=np.float64)
    return np.stack([p[..., 1], p[..., 0], -p[..., 2]], -1)


def ray_angle(a, b):
    """Angle (rad) between rays, row by row, accurate for tiny angles."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1))


def image_grid(h, w, step=8.0):
    """(u, v) pixels every ``step`` px over the whole image, edges (-0.5, W - 0.5) included."""
    v, u = np.meshgrid(np.arange(-0.5, h - 0.5 + 1e-9, step),
                       np.arange(-0.5, w - 0.5 + 1e-9, step), indexing="ij")
    return np.stack([u.ravel(), v.ravel()], -1)


def directions(max_angle, n_angles=400, az_step_deg=5.0):
    """Unit rays (ours) at angles 0..max_angle from +z, all azimuths; also the angles."""
    alpha = np.linspace(0.0, max_angle, n_angles)
    az = np.deg2rad(np.arange(0.0, 360.0, az_step_deg))
    a, p = np.meshgrid(alpha, az, indexing="ij")
    d = np.stack([np.sin(a) * np.cos(p), np.sin(a) * np.sin(p), np.cos(a)], -1)
    return d.reshape(-1, 3), a.ravel()


def last_fit_angle(model):
    """Largest angle from the axis that OCamCalib's findinvpoly samples (rho <= half-diagonal)."""
    radius = ref.toolbox_radius(model["width"], model["height"])
    t = ref.matlab_colon(-math.pi / 2, 0.01, 1.20)
    r = ref.invFUN(model["pol"], t, radius)
    return float(t[np.isfinite(r)].max()) + math.pi / 2


@pytest.fixture(scope="module")
def real():
    """(our camera, reference model, pixel grid (u, v), reference rays (ours), image max angle)."""
    if not REAL_CALIB.is_file():
        pytest.skip(f"missing {REAL_CALIB}")
    camera = ot.Camera.from_ocamcalib(REAL_CALIB)
    model = ref.read_ocam_model(REAL_CALIB)
    uv = image_grid(model["height"], model["width"])
    rays = ocam_to_ours(ref.cam2world(uv[:, ::-1], model))
    # the largest angle OCamCalib's cam2world gives inside the image (at a corner)
    max_angle = float(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2]).max())
    return camera, model, uv, rays, max_angle


# ---------------------------------------------------------------------------
# 1. reading the real file
# ---------------------------------------------------------------------------
@needs_real
def test_read_real_file_parameters(real):
    camera, model, *_ = real
    assert camera.model.name == "scaramuzza" and camera.params.dtype == torch.float64
    assert camera.image_size == (model["height"], model["width"])
    # centre (row, col) -> (cx, cy) = (col, row); c, d, e and the direct polynomial as written
    expected = [model["yc"], model["xc"], model["c"], model["d"], model["e"], *model["pol"]]
    assert camera.params.tolist() == expected
    assert camera.invpol.tolist() == model["invpol"].tolist()


@needs_real
def test_read_real_file_cam2world(real):
    camera, model, uv, ref_rays, max_angle = real
    rays, valid = camera.unproject(torch.tensor(uv))
    err = ray_angle(rays.numpy(), ref_rays)
    compared = len(err)
    print(f"cam2world vs OCamCalib over {compared} pixels: max {err.max():.3g} rad")
    assert compared > 0 and compared == len(uv)
    assert err.max() <= RAY_TOL
    # every pixel strictly inside the image is valid (the domain covers the image)
    h, w = camera.image_size
    inner = (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < h - 0.5)
    assert inner.sum() > 0 and valid.numpy()[inner].all()
    assert float(camera.max_angle()) >= max_angle > math.radians(120)


@needs_real
def test_read_real_file_world2cam_invpol(real):
    """``scaramuzza_project(..., invpol=camera.invpol)`` is OCamCalib's world2cam."""
    camera, model, _, _, max_angle = real
    d, _ = directions(max_angle)
    pixels, valid = scaramuzza_project(torch.tensor(d), camera.params, invpol=camera.invpol)
    expected = ref.world2cam(ours_to_ocam(d), model)[:, ::-1]  # (row, col) -> (u, v)
    err = np.abs(pixels.numpy() - expected).max(-1)
    compared = len(err)
    print(f"world2cam (invpol) vs OCamCalib over {compared} directions: max {err.max():.3g} px")
    assert compared > 0
    assert valid.all()
    assert err.max() <= PIX_TOL
    # the optical axis maps to the centre in both (OCamCalib's norm == 0 branch)
    assert d[0].tolist() == [0.0, 0.0, 1.0]
    assert pixels[0].tolist() == [model["yc"], model["xc"]] == expected[0].tolist()


@needs_real
def test_read_real_file_exact_projection(real):
    """``camera.project`` inverts the direct polynomial exactly: within the invpol fit error of
    OCamCalib's world2cam, and the exact inverse of its cam2world."""
    camera, model, uv, ref_rays, max_angle = real
    d, _ = directions(max_angle)
    pixels, valid = camera.project(torch.tensor(d))
    valid = valid.numpy()
    expected = ref.world2cam(ours_to_ocam(d), model)[:, ::-1]
    err = np.abs(pixels.numpy() - expected).max(-1)[valid]
    compared = len(err)
    print(f"exact projection vs OCamCalib world2cam (file invpol) over {compared} directions "
          f"in the image: max {err.max():.4g} px")
    assert compared > 0.5 * len(d)
    assert err.max() < LOOSE_TOL
    assert err.max() > 1e-4  # the file's invpol really is an approximation

    back, valid = camera.project(torch.tensor(ref_rays))
    err = np.abs(back.numpy() - uv).max(-1)
    compared = len(err)
    print(f"pixel -> OCamCalib cam2world -> exact projection over {compared} pixels: "
          f"max {err.max():.3g} px")
    assert compared > 0 and valid.sum() > 0.95 * compared
    assert err.max() <= ROUNDTRIP_TOL


# ---------------------------------------------------------------------------
# 2. writing
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def written(real, tmp_path_factory):
    camera = real[0]
    path = tmp_path_factory.mktemp("ocam_write") / "calib_results.txt"
    camera.to_ocamcalib(path)
    return path


@needs_real
def test_written_file_read_by_c_and_by_us(real, written, harness):
    camera, model, *_ = real
    cm = c_model(harness, written)
    # the direct polynomial, centre, affine part and size round-trip exactly (%.17g)
    assert cm["pol"].tolist() == model["pol"].tolist()
    for key in ("xc", "yc", "c", "d", "e", "width", "height"):
        assert cm[key] == model[key], key
    again = ot.Camera.from_ocamcalib(written)
    assert again.params.tolist() == camera.params.tolist()
    assert again.image_size == camera.image_size
    # the inverse polynomial is the refitted one, identical in C and in our reader
    invpol, _ = fit_invpol(camera)
    assert cm["invpol"].tolist() == invpol.tolist() == again.invpol.tolist()


@needs_real
def test_written_file_cam2world(real, written, harness):
    camera, model, uv, ref_rays, _ = real
    c_rays = ocam_to_ours(c_cam2world(harness, written, uv[:, ::-1]))
    err_c = ray_angle(c_rays, ref_rays)
    ours, _ = ot.Camera.from_ocamcalib(written).unproject(torch.tensor(uv))
    err_ours = ray_angle(ours.numpy(), ref_rays)
    compared = len(err_c)
    print(f"written file cam2world vs original over {compared} pixels: C {err_c.max():.3g} rad, "
          f"ours {err_ours.max():.3g} rad")
    assert compared > 0 and np.isfinite(c_rays).all()
    assert err_c.max() <= RAY_TOL and err_ours.max() <= RAY_TOL


@needs_real
def test_written_file_world2cam(real, written, harness):
    """OCamCalib's C world2cam with our refitted invpol vs our exact projection."""
    camera, model, _, _, max_angle = real
    d, alpha = directions(max_angle)
    exact, valid = camera.project(torch.tensor(d))
    valid = valid.numpy()
    c_pix = c_world2cam(harness, written, ours_to_ocam(d))[:, ::-1]
    err = np.abs(c_pix - exact.numpy()).max(-1)
    fit_domain = valid & (alpha <= last_fit_angle(model))
    compared = int(fit_domain.sum())
    print(f"C world2cam (written invpol) vs exact: max {err[fit_domain].max():.4g} px over "
          f"{compared} directions up to {math.degrees(last_fit_angle(model)):.2f} deg, "
          f"{err[valid].max():.4g} px over {valid.sum()} in the image (up to "
          f"{math.degrees(max_angle):.2f} deg)")
    assert compared > 0.5 * len(d)
    assert err[fit_domain].max() <= FIT_TOL
    assert err[valid].max() < LOOSE_TOL


@needs_real
def test_fit_invpol_matches_findinvpoly(real):
    camera, model, *_ = real
    invpol, err = fit_invpol(camera)
    radius = ref.toolbox_radius(model["width"], model["height"])
    ref_invpol, ref_err, degree = ref.findinvpoly(model["pol"], radius)
    t = np.linspace(-math.pi / 2, 1.20, 2001)
    diff = np.abs(np.polynomial.polynomial.polyval(t, invpol)
                  - np.polynomial.polynomial.polyval(t, ref_invpol))
    compared = len(t)
    print(f"fit_invpol: degree {len(invpol) - 1}, max error {err:.6g} px; findinvpoly: degree "
          f"{degree}, max error {ref_err.max():.6g} px; max |difference| {diff.max():.3g} px")
    assert compared > 0
    assert len(invpol) == len(ref_invpol) == degree + 1
    assert err <= FIT_TOL and ref_err.max() <= FIT_TOL
    assert abs(err - ref_err.max()) < 1e-8
    assert diff.max() < 1e-6


def test_to_ocamcalib_rejects_other_models(tmp_path):
    camera = ot.Camera("equidistant", torch.tensor([300.0, 300.0, 319.5, 239.5],
                                                   dtype=torch.float64), (480, 640))
    with pytest.raises(ValueError, match="scaramuzza"):
        camera.to_ocamcalib(tmp_path / "calib_results.txt")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------
# 3. JSON
# ---------------------------------------------------------------------------
SAMPLE_PARAMS = {
    "pinhole": [500.0, 510.0, 319.5, 239.5],
    "equidistant": [300.0, 301.0, 319.5, 239.5],
    "equisolid": [280.0, 281.0, 320.25, 240.75],
    "stereographic": [200.0, 199.0, 319.5, 239.5],
    "orthographic": [310.0, 310.0, 319.5, 239.5],
    "kannala_brandt": [300.0, 300.5, 319.5, 239.5, 0.01, -0.002, 3e-4, -1e-5],
    "unified": [400.0, 401.0, 319.5, 239.5, 0.9, -0.1, 0.01, 1e-4, -2e-4],
    "eucm": [350.0, 351.0, 319.5, 239.5, 0.6, 1.1],
    "double_sphere": [300.0, 301.0, 319.5, 239.5, -0.2, 0.6],
    "scaramuzza": [319.5, 239.5, 1.0003, -2e-4, 3e-4, -250.0, 0.0, 1.5e-3, -1e-6],
    "equirectangular": [1 / (2 * math.pi) * 640, 1 / math.pi * 320, 319.5, 159.5],
    "fov": [500.0, 505.0, 319.5, 239.5, 0.9],
    "division": [400.0, 402.0, 320.0, 240.0, -0.3],
    "opencv": [500.0, 502.0, 320.3, 239.7, -0.28, 0.07, 1e-3, -5e-4, 0.01, 0.9, 0.0, 0.0, 1e-3,
               -2e-4, 5e-4, 1e-4],
    "thin_prism_fisheye": [285.0, 286.0, 319.5, 239.5, -0.0134, 0.0513, 1e-3, -2e-3, -0.0437,
                           0.0089, 5e-4, -3e-4],
    "fisheye624": [240.0, 241.0, 320.2, 239.6, -0.02, 0.003, -2e-4, 1e-5, 0.0, 0.0, 4e-4, -3e-4,
                   2e-4, 1e-5, -3e-4, 2e-5],
    "woodscape": [321.4, 236.9, 1.0002, 339.7, -32.0, 48.3, -7.2],
}


def _camera(name, batch, fov):
    base = torch.tensor(SAMPLE_PARAMS[name], dtype=torch.float64)
    if batch is None:
        params = base
    else:  # distinct cameras: scale the first two parameters (focal, or the centre)
        n = math.prod(batch)
        scale = 1 + torch.arange(n, dtype=torch.float64) / 7
        params = base.expand(n, -1).clone()
        params[:, :2] = params[:, :2] * scale[:, None]
        params = params.reshape(*batch, -1)
    return ot.Camera(name, params, (480, 640), fov=fov)


def _check_same(a, b):
    assert b.model.name == a.model.name
    assert b.image_size == a.image_size
    assert b.batch_shape == a.batch_shape
    assert b.params.dtype == torch.float64
    assert torch.equal(b.params, a.params)
    if a.fov is None:
        assert b.fov is None
    else:  # stored in degrees: at most a rounding of the conversion
        assert b.fov == pytest.approx(a.fov, rel=4 * np.finfo(float).eps, abs=0)
    if a.invpol is None:
        assert b.invpol is None
    else:
        assert torch.equal(b.invpol, a.invpol)
    # and they behave the same
    pts = torch.tensor([[0.1, -0.2, 1.0], [0.5, 0.3, 0.8], [-0.3, 0.1, 0.9]], dtype=torch.float64)
    pts = pts.expand(*a.batch_shape, 3, 3)
    pa, va = a.project(pts)
    pb, vb = b.project(pts)
    assert torch.equal(va, vb) and va.any()
    assert torch.equal(pa, pb)


@pytest.mark.parametrize("batch", [None, (3,), (1, 3)], ids=["single", "batch3", "batch1x3"])
@pytest.mark.parametrize("name", list(ot.cameras.MODELS))
def test_json_round_trip(name, batch, tmp_path):
    compared = 0
    for fov in (None, 3.7):  # 3.7 rad = 212 deg: radians(degrees(3.7)) != 3.7, one ulp off
        camera = _camera(name, batch, fov)
        if name == "scaramuzza" and fov is None:
            camera.invpol = torch.tensor([250.0, 300.0, 10.0, -1.5], dtype=torch.float64)
            camera.invpol = camera.invpol.expand(*camera.batch_shape, 4).clone()
        data = camera.to_dict()
        assert json.loads(json.dumps(data)) == data  # JSON-ready
        _check_same(camera, ot.Camera.from_dict(data))
        path = tmp_path / f"{name}.json"
        camera.save_json(path)
        _check_same(camera, ot.Camera.load_json(path))
        compared += 1
    assert compared > 0


@needs_real
def test_json_round_trip_real_file(real, tmp_path):
    camera = real[0]
    path = tmp_path / "cam.json"
    camera.save_json(path)
    again = ot.Camera.load_json(path)
    _check_same(camera, again)
    assert again.invpol is not None and len(again.invpol) == len(real[1]["invpol"])


def test_json_write_is_atomic(tmp_path, monkeypatch):
    camera = _camera("equidistant", None, None)
    path = tmp_path / "camera.json"
    path.write_text("old content, not JSON\n")
    camera.save_json(path)
    assert [p.name for p in tmp_path.iterdir()] == ["camera.json"]  # no temp file left
    assert json.loads(path.read_text())["model"] == "equidistant"  # the old file was replaced

    # a write that fails at the last step leaves the old file whole and no temp file
    before = path.read_text()

    def failing_replace(src, dst):
        raise OSError("simulated failure")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="simulated"):
        _camera("pinhole", None, None).save_json(path)
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["camera.json"]
    assert path.read_text() == before

    # OCamCalib files too
    if REAL_CALIB.is_file():
        ocam = tmp_path / "calib_results.txt"
        ocam.write_text("old")
        ot.Camera.from_ocamcalib(REAL_CALIB).to_ocamcalib(ocam)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["calib_results.txt", "camera.json"]
        assert ot.Camera.from_ocamcalib(ocam).image_size == (1600, 1600)


# ---------------------------------------------------------------------------
# 4. malformed files
# ---------------------------------------------------------------------------
REAL_TEXT = "\n".join([  # the real file's text, line for line (trailing blanks included)
    "#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). "
    "These are used by cam2world",
    "",
    "5 -4.714441e+02 0.000000e+00 7.356108e-04 -3.773045e-07 5.800006e-10 ",
    "",
    "#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). "
    "These are used by world2cam",
    "",
    "10 772.405470 504.754051 7.034666 45.327180 54.651570 0.458049 -7.873745 15.588713 "
    "13.743404 2.968883 ",
    "",
    '#center: "row" and "column", starting from 0 (C convention)',
    "",
    "794.308657 798.175741",
    "",
    '#affine parameters "c", "d", "e"',
    "",
    "1.000305 -0.000277 -0.000925",
    "",
    '#image size: "height" and "width"',
    "",
    "1600 1600",
    "",
]) + "\n"


def _lines():
    return REAL_TEXT.splitlines()


def _write(tmp_path, lines, name="calib_results.txt"):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_good_text_parses(tmp_path):
    """The malformed variants below start from this (the real file's text), which is fine."""
    camera = ot.Camera.from_ocamcalib(_write(tmp_path, _lines()))
    assert camera.image_size == (1600, 1600) and camera.params[5] == -4.714441e02
    if REAL_CALIB.is_file():
        assert REAL_CALIB.read_text() == REAL_TEXT


def _replace(lineno, old, new):
    lines = _lines()
    assert old in lines[lineno - 1]
    lines[lineno - 1] = lines[lineno - 1].replace(old, new, 1)
    return lines


MALFORMED = {
    # name: (lines, line number the message must name, words it must contain)
    "count_too_high_pol": (_replace(3, "5 -4.7", "6 -4.7"), 3, "6 coefficients, found 5"),
    "count_too_low_invpol": (_replace(7, "10 772", "9 772"), 7, "9 coefficients, found 10"),
    "non_numeric_pol": (_replace(3, "7.356108e-04", "7.356108e-O4"), 3, "expected numbers"),
    "non_numeric_affine": (_replace(15, "1.000305", "one"), 15, "expected numbers"),
    "nan_centre": (_replace(11, "794.308657", "nan"), 11, "finite"),
    "three_centre_values": (_replace(11, "798.175741", "798.175741 0.5"), 11, "centre"),
    "one_centre_value": (_replace(11, " 798.175741", ""), 11, "centre"),
    "two_affine_values": (_replace(15, " -0.000925", ""), 15, "affine"),
    "fractional_size": (_replace(19, "1600 1600", "1600 1600.5"), 19, "image size"),
    "empty_size_section": (_lines()[:18], 17, "image size"),  # header, no data
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_ocamcalib_names_file_and_line(case, tmp_path):
    lines, line, words = MALFORMED[case]
    path = _write(tmp_path, lines)
    with pytest.raises(ValueError) as info:
        ot.Camera.from_ocamcalib(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    assert f"line {line}:" in msg, msg
    assert words in msg, msg


@pytest.mark.parametrize("keep", [0, 4, 8, 12, 16], ids=lambda k: f"first{k}lines")
def test_truncated_ocamcalib(keep, tmp_path):
    """Whole sections missing at the end: the message says the file looks truncated."""
    path = _write(tmp_path, _lines()[:keep])
    with pytest.raises(ValueError) as info:
        ot.Camera.from_ocamcalib(path)
    msg = str(info.value)
    assert str(path) in msg and "truncated" in msg, msg


def test_a0_not_negative_names_file_and_line(tmp_path):
    path = _write(tmp_path, _replace(3, "-4.714441e+02", "4.714441e+02"))
    with pytest.raises(ValueError) as info:
        ot.Camera.from_ocamcalib(path)
    msg = str(info.value)
    assert f"{path}, line 3" in msg and "a0" in msg, msg


def test_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="no_such_calib.txt"):
        ot.Camera.from_ocamcalib(tmp_path / "no_such_calib.txt")
    with pytest.raises(FileNotFoundError, match="no_such_camera.json"):
        ot.Camera.load_json(tmp_path / "no_such_camera.json")


def test_bad_json(tmp_path):
    path = tmp_path / "camera.json"
    _camera("pinhole", None, None).save_json(path)
    text = path.read_text()
    lines = text.splitlines()
    broken_line = next(i for i, s in enumerate(lines, 1) if '"fx"' in s)
    lines[broken_line - 1] = lines[broken_line - 1].replace(":", "", 1)  # "fx" 500.0,
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError) as info:
        ot.Camera.load_json(path)
    msg = str(info.value)
    assert str(path) in msg and f"line {broken_line}:" in msg and "JSON" in msg, msg


def test_json_misordered_params(tmp_path):
    path = tmp_path / "camera.json"
    data = _camera("kannala_brandt", None, None).to_dict()
    p = data["params"]
    data["params"] = {"fy": p["fy"], "fx": p["fx"], **{k: v for k, v in p.items()
                                                      if k not in ("fx", "fy")}}
    path.write_text(json.dumps(data, indent=2))
    with pytest.raises(ValueError) as info:
        ot.Camera.load_json(path)
    msg = str(info.value)
    assert str(path) in msg and "in this order" in msg and "'fy', 'fx'" in msg, msg
