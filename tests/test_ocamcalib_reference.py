"""Cross-check the numpy OCamCalib transcription against OCamCalib's own C code.

``tests/ocamcalib_reference.py`` (Python) and ``tests/c_reference/ocam_harness.c``
(verbatim OCamCalib C functions) are two independent renderings of the
published toolbox; they must agree on a real OCamCalib calibration file.
The C part is skipped when no C compiler is available.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ocamcalib_reference as ref  # noqa: E402

#: Numerically sensitive: CI runs this module again with OMP_NUM_THREADS=1 (.ci/run).
pytestmark = pytest.mark.numerics

HERE = Path(__file__).resolve().parent
HARNESS_SRC = HERE / "c_reference" / "ocam_harness.c"
REAL_CALIB = Path(__file__).resolve().parents[1].parent / "shared/data/ocamcalib_real/calib_results_0.txt"
TOL = 1e-9

needs_real = pytest.mark.skipif(not REAL_CALIB.is_file(), reason=f"missing {REAL_CALIB}")


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------
def _find_cc():
    for name in ("cc", "gcc", "clang"):
        exe = shutil.which(name)
        if exe:
            return exe
    return None


@pytest.fixture(scope="module")
def harness(tmp_path_factory):
    cc = _find_cc()
    if cc is None:
        pytest.skip("no C compiler (cc/gcc/clang) available")
    exe = tmp_path_factory.mktemp("ocam_c") / "ocam_harness"
    base = [cc, "-O2", str(HARNESS_SRC), "-o", str(exe), "-lm"]
    # no FMA contraction, so C and Python round identically
    proc = subprocess.run(base[:2] + ["-ffp-contract=off"] + base[2:], capture_output=True, text=True)
    if proc.returncode != 0:
        proc = subprocess.run(base, capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"could not compile the OCamCalib C harness: {proc.stderr[-2000:]}")
    return exe


def run_harness(exe, calib_path, queries):
    """Send 'w X Y Z' / 'c r c' / 'm' lines; return the output lines."""
    text = "".join(q + "\n" for q in queries)
    proc = subprocess.run([str(exe), str(calib_path)], input=text, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def c_world2cam(exe, calib_path, pts3):
    pts3 = np.asarray(pts3, dtype=np.float64).reshape(-1, 3)
    out = run_harness(exe, calib_path, [f"w {x!r} {y!r} {z!r}" for x, y, z in pts3.tolist()])
    assert len(out) == len(pts3)
    return np.array([[float(v) for v in line.split()] for line in out])


def c_cam2world(exe, calib_path, pts2):
    pts2 = np.asarray(pts2, dtype=np.float64).reshape(-1, 2)
    out = run_harness(exe, calib_path, [f"c {r!r} {c!r}" for r, c in pts2.tolist()])
    assert len(out) == len(pts2)
    return np.array([[float(v) for v in line.split()] for line in out])


def c_model(exe, calib_path):
    lines = run_harness(exe, calib_path, ["m"])
    assert len(lines) == 5
    pol = [float(v) for v in lines[0].split()]
    inv = [float(v) for v in lines[1].split()]
    xc, yc = (float(v) for v in lines[2].split())
    c, d, e = (float(v) for v in lines[3].split())
    height, width = (int(v) for v in lines[4].split())
    assert int(pol[0]) == len(pol) - 1 and int(inv[0]) == len(inv) - 1
    return dict(pol=np.array(pol[1:]), invpol=np.array(inv[1:]), xc=xc, yc=yc, c=c, d=d, e=e,
                width=width, height=height)


def pixel_grid(model, step=40):
    rows = np.arange(0.0, model["height"] + 1e-9, step)
    cols = np.arange(0.0, model["width"] + 1e-9, step)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    pts = np.stack([rr.ravel(), cc.ravel()], axis=-1)
    extra = np.array([[model["xc"], model["yc"]],  # exact centre (r = 0)
                      [model["xc"] + 0.25, model["yc"] - 0.75],
                      [-10.5, 1700.25], [model["height"] - 1.0, model["width"] - 1.0]])
    return np.concatenate([pts, extra])


def direction_grid():
    """Rays at angles 0..110 deg from the -z optical axis, all azimuths, plus specials."""
    ang = np.deg2rad(np.arange(0.0, 111.0, 5.0))
    az = np.deg2rad(np.arange(0.0, 360.0, 22.5))
    a, p = np.meshgrid(ang, az, indexing="ij")
    dirs = np.stack([np.sin(a) * np.cos(p), np.sin(a) * np.sin(p), -np.cos(a)], -1).reshape(-1, 3)
    scales = np.array([1.0, 0.01, 37.5])
    pts = (dirs[None] * scales[:, None, None]).reshape(-1, 3)
    special = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0],  # norm == 0 branch
                        [1e-12, 0.0, -1.0], [3.0, -4.0, 0.0], [-2.0, 1.0, 5.0]])
    return np.concatenate([pts, special])


# ---------------------------------------------------------------------------
# tests
# ---------------------------------------------------------------------------
@needs_real
def test_reader_matches_file_layout():
    m = ref.read_ocam_model(REAL_CALIB)
    assert len(m["pol"]) == 5 and len(m["invpol"]) == 10
    assert m["pol"][0] == -4.714441e02 and m["invpol"][0] == 772.405470
    assert (m["xc"], m["yc"]) == (794.308657, 798.175741)
    assert (m["c"], m["d"], m["e"]) == (1.000305, -0.000277, -0.000925)
    assert (m["height"], m["width"]) == (1600, 1600)


@needs_real
def test_reader_matches_c_get_ocam_model(harness):
    py = ref.read_ocam_model(REAL_CALIB)
    cm = c_model(harness, REAL_CALIB)
    for k in ("pol", "invpol"):
        np.testing.assert_array_equal(py[k], cm[k])
    for k in ("xc", "yc", "c", "d", "e", "width", "height"):
        assert py[k] == cm[k], k


@needs_real
def test_cam2world_matches_c(harness):
    model = ref.read_ocam_model(REAL_CALIB)
    pts = pixel_grid(model)
    py = ref.cam2world(pts, model)
    cc = c_cam2world(harness, REAL_CALIB, pts)
    compared = int(np.isfinite(cc).all(axis=1).sum())
    assert compared > 0
    np.testing.assert_allclose(py, cc, rtol=0, atol=TOL)
    np.testing.assert_allclose(np.linalg.norm(py, axis=1), 1.0, atol=1e-12)


@needs_real
def test_world2cam_matches_c(harness):
    model = ref.read_ocam_model(REAL_CALIB)
    pts = direction_grid()
    py = ref.world2cam(pts, model)
    cc = c_world2cam(harness, REAL_CALIB, pts)
    compared = int(np.isfinite(cc).all(axis=1).sum())
    assert compared > 0
    np.testing.assert_allclose(py, cc, rtol=0, atol=TOL)
    # norm == 0 branch -> centre, in both
    zero = (pts[:, 0] == 0) & (pts[:, 1] == 0)
    assert zero.sum() >= 3
    np.testing.assert_array_equal(py[zero], np.broadcast_to([model["xc"], model["yc"]], (zero.sum(), 2)))
    np.testing.assert_array_equal(cc[zero], py[zero])


@needs_real
def test_roundtrip_through_c_and_python(harness):
    """pixel -> C cam2world -> Python world2cam returns near the pixel (invpol fit error only)."""
    model = ref.read_ocam_model(REAL_CALIB)
    pts = pixel_grid(model, step=100)
    r = np.hypot(pts[:, 0] - model["xc"], pts[:, 1] - model["yc"])
    pts = pts[r < 0.5 * min(model["width"], model["height"])]
    rays = c_cam2world(harness, REAL_CALIB, pts)
    back = ref.world2cam(rays, model)
    assert len(pts) > 0
    assert np.abs(back - pts).max() < 0.5  # the file's invpol is an approximation


def test_reader_and_c_agree_on_full_precision_file(harness, tmp_path):
    """A file written like export_data.m but at %.17g, odd spacing, CRLF: same parse in C and Python."""
    pol = [-300.123456789012345, 0.0, 1.2345678901234567e-3, -2.5e-7, 3.75e-10]
    inv = [450.5, 300.25, 12.125, -3.0625, 1.5]
    text = ("#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). These are used by cam2world\r\n\r\n"
            + f"{len(pol)} " + " ".join(f"{v:.17g}" for v in pol) + " \r\n\r\n"
            + "#polynomial coefficients for the inverse mapping function\n\n\n"
            + f"{len(inv)}\t" + "  ".join(f"{v:.17g}" for v in inv) + "\n\n"
            + "#center: \"row\" and \"column\", starting from 0 (C convention)\n\n"
            + "511.75 640.125\n\n#affine parameters \"c\", \"d\", \"e\"\n\n1.0001 0.0002 -0.0003\n\n"
            + "#image size: \"height\" and \"width\"\n\n1024 1280\n\n")
    path = tmp_path / "calib_results_synth.txt"
    path.write_bytes(text.encode())
    py = ref.read_ocam_model(path)
    cm = c_model(harness, path)
    np.testing.assert_array_equal(py["pol"], pol)
    np.testing.assert_array_equal(py["invpol"], inv)
    for k in ("pol", "invpol"):
        np.testing.assert_array_equal(py[k], cm[k])
    for k in ("xc", "yc", "c", "d", "e", "width", "height"):
        assert py[k] == cm[k], k
    pts = np.array([[0.0, 0.0], [511.75, 640.125], [100.0, 1200.0], [1023.0, 3.0]])
    np.testing.assert_allclose(ref.cam2world(pts, py), c_cam2world(harness, path, pts), rtol=0, atol=TOL)
    P = direction_grid()
    np.testing.assert_allclose(ref.world2cam(P, py), c_world2cam(harness, path, P), rtol=0, atol=TOL)


@needs_real
def test_findinvpoly_on_real_file():
    """The MATLAB degree search reaches its 0.01 px target on this file's pol."""
    model = ref.read_ocam_model(REAL_CALIB)
    radius = ref.toolbox_radius(model["width"], model["height"])
    invpol, err, N = ref.findinvpoly(model["pol"], radius)
    assert len(invpol) == N + 1
    assert err.max() <= 0.01
    # its polynomial reproduces the exact inverse (invFUN) at the sampled angles
    theta = ref.matlab_colon(-math.pi / 2, 0.01, 1.20)
    r = ref.invFUN(model["pol"], theta, radius)
    ok = np.isfinite(r)
    assert ok.sum() > 100
    assert np.abs(np.polyval(invpol[::-1], theta[ok]) - r[ok]).max() <= 0.01


def invpol_report(calib=REAL_CALIB):
    """Numbers for the brief: file invpol vs exact inverse of pol, and findinvpoly's result."""
    model = ref.read_ocam_model(calib)
    pol, inv = model["pol"], model["invpol"]
    radius = ref.toolbox_radius(model["width"], model["height"])
    # angle alpha from the optical axis (-z); elevation theta = alpha - pi/2
    alpha = np.arange(0.0, math.pi, 1e-3)
    theta = alpha - math.pi / 2
    r_exact = ref.invFUN(pol, theta, radius)
    valid = np.isfinite(r_exact)
    # largest alpha such that every alpha in [0, it] has a valid root
    last = int(np.argmin(valid)) - 1 if not valid.all() else len(alpha) - 1
    sl = slice(0, last + 1)
    r_file = np.polyval(inv[::-1], theta[sl])
    err = np.abs(r_file - r_exact[sl])
    print(f"file: pol len {len(pol)}, invpol len {len(inv)}, fit radius {radius:.3f} px")
    print(f"valid angles 0..{math.degrees(alpha[last]):.2f} deg from axis (rho up to {r_exact[last]:.2f} px)")
    print(f"file invpol vs exact inverse: max |drho| {err.max():.4g} px at {math.degrees(alpha[sl][err.argmax()]):.2f} deg")
    for lim in (90.0, 95.0, 100.0):
        m = np.degrees(alpha[sl]) <= lim
        print(f"   up to {lim:.0f} deg: max {err[m].max():.4g} px")
    t_fit_last = -math.pi / 2 + 0.01 * np.nonzero(np.isfinite(ref.invFUN(pol, ref.matlab_colon(-math.pi / 2, 0.01, 1.20), radius)))[0].max()
    m = theta[sl] <= t_fit_last
    print(f"   up to the last valid MATLAB sample ({math.degrees(t_fit_last + math.pi / 2):.2f} deg): max {err[m].max():.4g} px")
    inner = r_exact[sl] <= min(model["width"], model["height"]) / 2
    print(f"   within the inscribed circle (rho <= {min(model['width'], model['height']) / 2:.0f}): {err[inner].max():.4g} px")
    # world2cam of the reference vs exact, in 2D pixels
    P = np.stack([np.sin(alpha[sl]), np.zeros(last + 1), -np.cos(alpha[sl])], -1)
    w2c = ref.world2cam(P, model)
    exact_2d = np.stack([r_exact[sl] * model["c"] + model["xc"], r_exact[sl] * model["e"] + model["yc"]], -1)
    exact_2d[0] = (model["xc"], model["yc"])
    print(f"world2cam (file invpol) vs exact, 2D px: {np.abs(w2c - exact_2d).max():.4g}")
    t_fit = ref.matlab_colon(-math.pi / 2, 0.01, 1.20)
    r_fit = ref.invFUN(pol, t_fit, radius)
    ok = np.isfinite(r_fit)
    e_file_fit = np.abs(np.polyval(inv[::-1], t_fit[ok]) - r_fit[ok])
    print(f"file invpol on the MATLAB samples [-pi/2:0.01:1.20] ({ok.sum()} valid): max {e_file_fit.max():.4g} px")
    for start, stop, label in ((-math.pi / 2, 1.20, "[-pi/2:0.01:1.20]"), (-math.pi / 2 + 0.01, 1.4, "[-pi/2+0.01:0.01:1.4]")):
        new_inv, ferr, N = ref.findinvpoly(pol, radius, theta_start=start, theta_stop=stop)
        d = np.abs(np.polyval(new_inv[::-1], theta[sl]) - r_exact[sl])
        print(f"findinvpoly {label}: N={N} (len {len(new_inv)}), max fit err {ferr.max():.4g} px, "
              f"vs exact over valid angles {d.max():.4g} px")
        print("   invpol =", np.array2string(new_inv, precision=6, max_line_width=200))
        if len(new_inv) == len(inv):
            print("   file   =", np.array2string(inv, precision=6, max_line_width=200))
            print(f"   max |new - file| over valid angles: {np.abs(np.polyval(new_inv[::-1], theta[sl]) - r_file).max():.4g} px")


if __name__ == "__main__":
    invpol_report()
