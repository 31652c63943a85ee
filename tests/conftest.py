"""Shared test data: the real files beside the project and one parameter set list per model."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
OCAMCALIB_FILE = SHARED_DATA / "ocamcalib_real" / "calib_results_0.txt"


def _real_scaramuzza() -> list[float]:
    """The real OCamCalib calibration as scaramuzza params, read independently of the library."""
    lines = [ln.split() for ln in OCAMCALIB_FILE.read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    pol = [float(v) for v in lines[0][1:]]
    row, col = map(float, lines[2])
    c, d, e = map(float, lines[3])
    return [col, row, c, d, e, *pol]


#: DESIGN.md, "Cube faces", written out once for the tests (independently of the package):
#: (a looks along, b image down, r image right) per face, in DESIGN.md's face order.
DESIGN_TABLE = {
    "front": ((0, 0, 1), (0, 1, 0), (1, 0, 0)),
    "back": ((0, 0, -1), (0, 1, 0), (-1, 0, 0)),
    "left": ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "right": ((1, 0, 0), (0, 1, 0), (0, 0, -1)),
    "up": ((0, -1, 0), (0, 0, 1), (1, 0, 0)),
    "down": ((0, 1, 0), (0, 0, -1), (1, 0, 0)),
}
FACE_ORDER = tuple(DESIGN_TABLE)

#: (model, params, image_size (H, W)) cases covering each model's regimes: an undistorted
#: reference, realistic lenses, and the regimes where methods fail (xi > 1, folds before 180).
CASES = {
    "pinhole": [([500.0, 480.0, 319.5, 239.5], (480, 640))],
    "equidistant": [([200.0, 205.0, 319.5, 299.5], (600, 640))],
    "equisolid": [([210.0, 200.0, 320.0, 300.0], (600, 640))],
    "stereographic": [([150.0, 150.0, 319.5, 319.5], (640, 640))],
    "orthographic": [([300.0, 290.0, 319.5, 309.5], (620, 640))],
    "kannala_brandt": [
        ([200.0, 200.0, 319.5, 319.5, 0.0, 0.0, 0.0, 0.0], (640, 640)),
        ([190.0, 191.0, 320.3, 318.7, -0.02, 0.004, -0.001, 0.0002], (640, 640)),
        # folds at 111 degrees (dr/dtheta = 0 there): valid only below the fold
        ([200.0, 200.0, 319.5, 319.5, -0.12, 0.005, 0.0, 0.0], (640, 640)),
        # with the optional skew s (OpenCV fisheye's alpha = s / fx), and the fold
        ([200.0, 201.0, 319.5, 319.5, -0.12, 0.005, 0.0, 0.0, 2.5], (640, 640)),
    ],
    "unified": [
        ([400.0, 400.0, 319.5, 319.5, 0.0, 0.0, 0.0, 0.0, 0.0], (640, 640)),
        ([300.0, 305.0, 320.0, 318.0, 0.8, 0.0, 0.0, 0.0, 0.0], (640, 640)),
        ([250.0, 250.0, 319.5, 319.5, 1.0, 0.0, 0.0, 0.0, 0.0], (640, 640)),
        ([600.0, 600.0, 319.5, 319.5, 1.6, 0.0, 0.0, 0.0, 0.0], (640, 640)),
        # with the optional skew s (OpenCV omnidir's K[0, 1])
        ([300.0, 305.0, 320.0, 318.0, 0.8, 0.0, 0.0, 0.0, 0.0, -3.0], (640, 640)),
        ([330.0, 331.0, 321.0, 317.0, 0.9, -0.15, 0.02, 1e-3, -5e-4, 2.0], (640, 640)),
        ([330.0, 331.0, 321.0, 317.0, 0.9, -0.15, 0.02, 1e-3, -5e-4], (640, 640)),
    ],
    "eucm": [
        ([260.0, 262.0, 319.5, 319.5, 0.3, 1.0], (640, 640)),
        ([220.0, 221.0, 320.5, 318.5, 0.6, 1.1], (640, 640)),
    ],
    "double_sphere": [
        ([160.0, 161.0, 319.5, 319.5, -0.2, 0.6], (640, 640)),
        ([200.0, 200.0, 320.0, 320.0, 0.5, 0.3], (640, 640)),
    ],
    "scaramuzza": [
        (_real_scaramuzza(), (1600, 1600)),
        # a synthetic lens whose polynomial folds: theta stops growing near rho = 430 px,
        # inside the image corners
        ([320.0, 310.0, 1.0, 0.0, 0.0, -200.0, 0.0, 1.5e-3, -3e-6], (640, 640)),
    ],
    "equirectangular": [([256 / (2 * math.pi), 128 / math.pi, 127.5, 63.5], (128, 256))],
    "fov": [
        ([500.0, 505.0, 319.5, 239.5, 0.9], (480, 640)),
        # omega^2 < 1e-4: where COLMAP's FOV model switches to its series
        ([400.0, 401.0, 320.2, 239.7, 0.005], (480, 640)),
    ],
    "division": [
        # k < 0 (barrel): valid past 90 degrees, up to 180
        ([400.0, 402.0, 320.0, 240.0, -0.3], (480, 640)),
        # k > 0: folds at atan(1 / (2 sqrt(k))) = 42.4 degrees, outside the image
        ([420.0, 420.0, 319.5, 239.5, 0.3], (480, 640)),
    ],
    "opencv": [
        # COLMAP OPENCV's 8 parameters (k3..s4 = 0): a typical wide-angle lens, no fold
        ([500.0, 502.0, 320.3, 239.7, -0.28, 0.07, 1e-3, -5e-4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
          0.0, 0.0], (480, 640)),
        # the rational model (k4) and the thin prism: with k5, k6 the denominator's growth
        # lets the r^4 thin-prism terms fold the plane short of 90 degrees (beyond 20000 px,
        # unseen by the radial valid set), so this lens keeps them 0
        ([600.0, 601.0, 640.0, 360.0, 0.6, -0.05, 1e-3, -5e-4, 0.01, 0.9, 0.0, 0.0, 1e-3,
          -2e-4, 5e-4, 1e-4], (720, 1280)),
        # strong barrel distortion whose radius folds at 51 degrees (inside the image corners)
        ([350.0, 352.0, 320.0, 240.0, -0.35, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
          0.0], (480, 640)),
    ],
    "thin_prism_fisheye": [
        ([285.72, 286.11, 640.31, 481.17, -0.0134, 0.0513, 1e-3, -2e-3, -0.0437, 0.0089, 5e-4,
          -3e-4], (960, 1280)),
        # the Kannala-Brandt lens that folds at 111 degrees (p = s = 0)
        ([200.0, 200.0, 319.5, 319.5, -0.12, 0.005, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], (640, 640)),
    ],
    "fisheye624": [
        ([240.0, 241.0, 320.2, 239.6, -0.02, 0.003, -2e-4, 1e-5, 0.0, 0.0, 4e-4, -3e-4, 2e-4,
          1e-5, -3e-4, 2e-5], (480, 640)),
        # the Kannala-Brandt lens that folds at 111 degrees (p = s = 0, k4 = k5 = 0)
        ([200.0, 200.0, 319.5, 319.5, -0.12, 0.005, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
          0.0], (640, 640)),
    ],
    "woodscape": [
        # WoodScape's front.json (valeoai/WoodScape, scripts/calibration, MIT): cx = 1280 / 2
        # - 0.5 + cx_offset 3.942, cy = 966 / 2 - 0.5 + cy_offset -3.093; valid to 180 degrees
        ([643.442, 479.407, 1.0, 339.749, -31.988, 48.275, -7.201], (966, 1280)),
        # aspect ratio 1.02 and a fold at 95.3 degrees (346 px), inside the image corners
        ([320.2, 239.4, 1.02, 310.0, 8.0, -45.0, 2.0], (480, 640)),
    ],
}


def all_cases() -> list:
    return [pytest.param(model, params, size, id=f"{model}-{i}")
            for model, cases in CASES.items() for i, (params, size) in enumerate(cases)]


def fibonacci_sphere(n: int, dtype=torch.float64) -> torch.Tensor:
    """``(n, 3)`` nearly uniform unit directions (deterministic)."""
    i = torch.arange(n, dtype=dtype) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), -1)


def directions_at(theta: torch.Tensor, n_azimuth: int = 16) -> torch.Tensor:
    """Unit directions at angles ``theta (T,)`` from +z, ``n_azimuth`` azimuths each: (T*A, 3)."""
    phi = torch.arange(n_azimuth, dtype=theta.dtype) * (2 * math.pi / n_azimuth) + 0.1
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    return torch.stack((torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p), torch.cos(t)),
                       -1).reshape(-1, 3)


@pytest.fixture(scope="module")
def one_thread():
    """torch on one thread for a test module, restored afterwards: for fits on small matrices
    (at most ~2000 x 70), where a second OpenMP thread only adds synchronisation (5x slower on
    a loaded 2-core machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def ray_cluster():
    """A real local Ray cluster for every Ray test of the session, started once (it takes
    about 5 s and 1 GB): 2 CPUs, no dashboard, a small object store (the tasks return file
    lists). Code under test that asks for Ray finds it connected and uses it."""
    ray = pytest.importorskip("ray")
    # "local": a cluster of its own, even where `ray start` runs one on this machine
    ray.init(address="local", num_cpus=2, include_dashboard=False,
             object_store_memory=100 * 2 ** 20, logging_level="WARNING")
    yield ray
    ray.shutdown()
