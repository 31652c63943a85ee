"""The woodscape model and WoodScape's calibration files, against WoodScape's own projection.

Oracles: an independent numpy implementation of the projection WoodScape documents
(``scripts/calibration/calibration_readme.txt``: the forward polynomial, and its inverse by the
polynomial's roots as WoodScape's ``projection.py`` takes it, ``numpy.roots``), always; and
WoodScape's ``projection.py`` itself (``read_cam_from_json``, ``Camera``,
``RadialPolyCamProjection``) where a copy of WoodScape is on the machine (``WOODSCAPE_REPO``: a
checkout, or the git mirror the project's tools fetch); neither is committed here.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.cameras.woodscape import woodscape_unproject
from omniscape_torch.render.kernels import camera as kernels

from conftest import CASES, fibonacci_sphere

F64 = torch.float64

#: valeoai/WoodScape, scripts/calibration/front.json at commit
#: 597d9dda472c09bafea58ea69853948d63197eca (MIT licence, Copyright 2021 Valeo Schalter und
#: Sensoren GmbH and contributors): its numbers, written out.
FRONT = {
    "extrinsic": {
        "quaternion": [0.5941767906169857, -0.5878843193897473, 0.3873184109007999,
                       -0.3890121040340926],
        "translation": [3.7484, 0.0, 0.6601699999999999],
    },
    "intrinsic": {
        "aspect_ratio": 1.0, "cx_offset": 3.942, "cy_offset": -3.093, "height": 966.0,
        "k1": 339.749, "k2": -31.988, "k3": 48.275, "k4": -7.201, "model": "radial_poly",
        "poly_order": 4, "width": 1280.0,
    },
    "name": "FV",
}

_MIRROR = Path("/work/.mirror/valeoai+WoodScape/repo")
_PROJECTION = "scripts/calibration/projection.py"


# --------------------------------------------------------------------------------------------
# The oracles: WoodScape's documented projection, and its projection.py where present
# --------------------------------------------------------------------------------------------

def _rotation(q):
    """Scalar-last quaternion -> matrix (scipy's ``Rotation.from_quat``, written out)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


class DocumentedCamera:
    """WoodScape's calibration_readme.txt, in numpy: vehicle-frame points <-> pixels."""

    def __init__(self, config: dict):
        intr, extr = config["intrinsic"], config["extrinsic"]
        self.k = np.array([intr[f"k{i}"] for i in range(1, 5)], dtype=np.float64)
        self.aspect = intr["aspect_ratio"]
        self.centre = np.array([intr["cx_offset"] + intr["width"] / 2 - 0.5,
                                intr["cy_offset"] + intr["height"] / 2 - 0.5])
        self.rotation = _rotation(extr["quaternion"])
        self.translation = np.asarray(extr["translation"], dtype=np.float64)

    def project_3d_to_2d(self, world):
        cam = (np.asarray(world) - self.translation) @ self.rotation   # R^T (X - t)
        chi = np.hypot(cam[:, 0], cam[:, 1])
        theta = np.pi / 2 - np.arctan2(cam[:, 2], chi)
        rho = sum(k * theta ** (i + 1) for i, k in enumerate(self.k))
        u = rho * cam[:, 0] / chi + self.centre[0]
        v = rho * cam[:, 1] / chi * self.aspect + self.centre[1]
        return np.stack((u, v), -1)

    def project_2d_to_3d(self, pixels, norm):
        lens = (np.asarray(pixels) - self.centre) / np.array([1.0, self.aspect])
        rho = np.linalg.norm(lens, axis=1)
        theta = np.zeros_like(rho)
        for i, r in enumerate(rho):   # the smallest real root in [0, pi), as WoodScape's
            roots = np.roots([*self.k[::-1], -r])
            real = roots.real[(roots.imag == 0) & (np.abs(roots.real) < np.pi)]
            theta[i] = real.min() if real.size else 0.0
        xy = (np.asarray(norm) * np.sin(theta) / rho)[:, None] * lens
        cam = np.concatenate((xy, (np.asarray(norm) * np.cos(theta))[:, None]), 1)
        return cam @ self.rotation.T + self.translation


def _woodscape_projection(tmp_dir: Path):
    """WoodScape's projection.py as a module, or None where no copy is on the machine."""
    root = os.environ.get("WOODSCAPE_REPO")
    source = None
    if root and (Path(root) / _PROJECTION).is_file():
        source = Path(root) / _PROJECTION
    elif _MIRROR.is_dir():
        done = subprocess.run(["git", f"--git-dir={_MIRROR}", "show", f"HEAD:{_PROJECTION}"],
                              capture_output=True)
        if done.returncode == 0:
            source = tmp_dir / "projection.py"
            source.write_bytes(done.stdout)
    if source is None:
        return None
    pytest.importorskip("cv2")   # projection.py imports both
    pytest.importorskip("scipy")
    spec = importlib.util.spec_from_file_location("woodscape_projection", source)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def projection(tmp_path_factory):
    module = _woodscape_projection(tmp_path_factory.mktemp("woodscape"))
    if module is None:
        pytest.skip("no copy of WoodScape here (set WOODSCAPE_REPO to a checkout)")
    return module


@pytest.fixture(params=["documented", "projection.py"])
def oracle(request, tmp_path):
    """``path -> camera`` with ``project_3d_to_2d`` / ``project_2d_to_3d`` in the vehicle
    frame: the documented projection, or WoodScape's ``read_cam_from_json``."""
    if request.param == "documented":
        return lambda path: DocumentedCamera(json.loads(Path(path).read_text()))
    return request.getfixturevalue("projection").read_cam_from_json


@pytest.fixture
def front(tmp_path) -> Path:
    path = tmp_path / "front.json"
    path.write_text(json.dumps(FRONT, indent=2))
    return path


def _vehicle_points(n: int, seed: int) -> np.ndarray:
    """``(n, 3)`` points around the car (ISO 8855, metres), none on the camera's axis."""
    gen = np.random.default_rng(seed)
    return np.stack((gen.uniform(-8, 25, n), gen.uniform(-12, 12, n), gen.uniform(-0.5, 4, n)),
                    -1)


def _ours(camera, T, world: np.ndarray):
    """Our pixels and validity of vehicle-frame points through ``T`` (camera -> vehicle)."""
    t = T.numpy()
    cam = torch.from_numpy((world - t[:3, 3]) @ t[:3, :3])
    return camera.model.project(cam, camera.params)


# --------------------------------------------------------------------------------------------
# The model against WoodScape's projection
# --------------------------------------------------------------------------------------------

def test_project_matches_woodscape_on_front_json(front, oracle):
    camera, T, name = ot.cameras.read_woodscape(front)
    world = _vehicle_points(4000, 0)
    pixels, valid = _ours(camera, T, world)
    theirs = oracle(front).project_3d_to_2d(world)
    both = valid.numpy() & np.isfinite(theirs).all(1)
    compared = int(both.sum())
    err = np.abs(pixels.numpy()[both] - theirs[both]).max()
    assert err < 1e-6, err
    assert compared > 3900


def test_project_matches_woodscape_over_the_whole_sphere(front, oracle):
    """Directions in the camera frame out to 179.9 degrees (behind the camera too)."""
    camera, T, _ = ot.cameras.read_woodscape(front)
    dirs = fibonacci_sphere(3000)
    dirs = dirs[torch.atan2(dirs[:, :2].norm(dim=-1), dirs[:, 2]) < math.radians(179.9)]
    pixels, valid = camera.model.project(dirs, camera.params)
    world = dirs.numpy() @ T[:3, :3].numpy().T + T[:3, 3].numpy()
    theirs = oracle(front).project_3d_to_2d(world)
    both = valid.numpy()
    compared = int(both.sum())
    assert np.abs(pixels.numpy()[both] - theirs[both]).max() < 1e-6
    assert compared > 0


def test_unproject_matches_woodscape_on_front_json(front, oracle):
    """Pixels over the whole image: the rays agree within 1e-9 rad."""
    camera, T, _ = ot.cameras.read_woodscape(front)
    h, w = camera.image_size
    v, u = torch.meshgrid(torch.linspace(-0.5, h - 0.5, 37, dtype=F64),
                          torch.linspace(-0.5, w - 0.5, 49, dtype=F64), indexing="ij")
    pixels = torch.stack((u, v), -1).reshape(-1, 2)
    pixels = pixels[(pixels - camera.params[:2]).norm(dim=-1) > 1e-3]   # WoodScape: 0 / 0
    rays, valid = camera.unproject(pixels)
    theirs = oracle(front).project_2d_to_3d(pixels.numpy(), norm=np.ones(len(pixels)))
    theirs = torch.from_numpy(theirs - T[:3, 3].numpy()) @ T[:3, :3]   # to the camera frame
    both = valid & torch.isfinite(theirs).all(1)
    compared = int(both.sum())
    a, b = rays[both], theirs[both]
    angle = torch.atan2(torch.linalg.vector_norm(torch.cross(a, b, dim=-1), dim=-1),
                        (a * b).sum(-1))
    assert float(angle.max()) < 1e-9, float(angle.max())
    assert compared > 1700


# --------------------------------------------------------------------------------------------
# The files
# --------------------------------------------------------------------------------------------

def test_camera_load_reads_front_json(front):
    camera = ot.Camera.load(front)
    assert camera.model.name == "woodscape" and camera.image_size == (966, 1280)
    expected = [640 - 0.5 + 3.942, 483 - 0.5 - 3.093, 1.0, 339.749, -31.988, 48.275, -7.201]
    torch.testing.assert_close(camera.params, torch.tensor(expected, dtype=F64), rtol=0,
                               atol=1e-12)
    assert list(ot.cameras.load_all(front)) == ["FV"]
    assert ot.cameras.readers.detect_format(front) == "woodscape"


def test_extrinsic_is_camera_to_vehicle_with_a_scalar_last_quaternion(front):
    """FV looks forward and down, its x axis to the vehicle's right (ISO 8855: y left), and
    sits at the file's translation."""
    _, T, name = ot.cameras.read_woodscape(front)
    assert name == "FV" and T.dtype == F64 and T.shape == (4, 4)
    axis, right = T[:3, 2], T[:3, 0]
    assert float(axis[0]) > 0.9 and -0.45 < float(axis[2]) < -0.35   # 23 degrees down
    assert float(right[1]) < -0.99
    assert torch.equal(T[:3, 3], torch.tensor(FRONT["extrinsic"]["translation"], dtype=F64))
    torch.testing.assert_close(T[:3, :3] @ T[:3, :3].T, torch.eye(3, dtype=F64), atol=1e-12,
                               rtol=0)


def test_written_file_projects_as_the_original(front, oracle, tmp_path):
    """read_woodscape, write_woodscape, then WoodScape's reader: 1,000 vehicle-frame points
    within 1e-6 px of the original file's."""
    camera, T, name = ot.cameras.read_woodscape(front)
    out = ot.cameras.write_woodscape(tmp_path / "ours.json", camera, T, name)
    written = json.loads(out.read_text())
    assert list(written) == ["extrinsic", "intrinsic", "name"]
    assert list(written["extrinsic"]) == ["quaternion", "translation"]
    assert list(written["intrinsic"]) == list(FRONT["intrinsic"])   # read by position
    assert written["intrinsic"]["cx_offset"] == 3.942 and written["name"] == "FV"
    world = _vehicle_points(1000, 1)
    before = oracle(front).project_3d_to_2d(world)
    after = oracle(out).project_3d_to_2d(world)
    assert np.abs(after - before).max() < 1e-6
    back, T2, name2 = ot.cameras.read_woodscape(out)
    torch.testing.assert_close(back.params, camera.params, rtol=0, atol=1e-12)
    torch.testing.assert_close(T2, T, rtol=0, atol=1e-14)
    assert name2 == name and not list(tmp_path.glob(".*"))   # no temporary left


def test_fov_is_kept_where_woodscape_does_not_look(front, oracle, tmp_path):
    camera, T, name = ot.cameras.read_woodscape(front, fov=math.radians(190))
    out = ot.cameras.write_woodscape(tmp_path / "fov.json", camera, T, name)
    assert json.loads(out.read_text())["fov_deg"] == pytest.approx(190)
    assert ot.Camera.load(out).fov == pytest.approx(math.radians(190))
    world = _vehicle_points(50, 2)
    assert np.abs(oracle(out).project_3d_to_2d(world)
                  - oracle(front).project_3d_to_2d(world)).max() < 1e-6


@pytest.mark.parametrize("name, carla, iso", [
    ("FV", [1.92, 0.0, 0.9], [1.92, 0.0, 0.9]),
    ("FV", [1.0, 0.5, 1.2], [1.0, -0.5, 1.2]),        # CARLA's y is to the right
    ("MVL", [0.8, 1.0, -0.9], [0.8, 0.9, 1.0]),       # y and z swapped in the mirrors' files
    ("MVR", [0.8, 1.0, 0.9], [0.8, -0.9, 1.0]),
])
def test_synwoodscape_translation_is_converted_from_carla(tmp_path, name, carla, iso):
    config = json.loads(json.dumps(FRONT))
    config["name"] = name
    config["extrinsic"] = {"quaternion": FRONT["extrinsic"]["quaternion"],
                           "translation used in CARLA (CARLA reference)": carla}
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(config))
    camera, T, got = ot.cameras.read_woodscape(path)
    _, T_front, _ = ot.cameras.read_woodscape(_write(tmp_path, FRONT))
    assert got == name and torch.equal(T[:3, :3], T_front[:3, :3])
    torch.testing.assert_close(T[:3, 3], torch.tensor(iso, dtype=F64), rtol=0, atol=0)
    assert ot.Camera.load(path).model.name == "woodscape"
    out = ot.cameras.write_woodscape(tmp_path / "back.json", camera, T, got)
    assert json.loads(out.read_text())["extrinsic"]["translation"] == pytest.approx(iso)


def _write(tmp_path: Path, config: dict, name: str = "cal.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(config))
    return path


def _broken(edit) -> dict:
    config = json.loads(json.dumps(FRONT))
    edit(config)
    return config


@pytest.mark.parametrize("edit, match", [
    (lambda c: c["intrinsic"].pop("k3"), r"intrinsic\.k3: missing"),
    (lambda c: c["intrinsic"].update(model="pinhole"), r"intrinsic\.model: expected 'radial_poly'"),
    (lambda c: c["intrinsic"].update(poly_order=5), r"intrinsic\.poly_order"),
    (lambda c: c["intrinsic"].update(width=0), r"intrinsic\.width: expected a positive whole"),
    (lambda c: c["intrinsic"].update(cx_offset="3.9"), r"intrinsic\.cx_offset: expected a num"),
    (lambda c: c["intrinsic"].update(k1=-339.7), r"k1 of the woodscape model must be > 0"),
    (lambda c: c["intrinsic"].update(aspect_ratio=0.0), r"aspect_ratio of the woodscape model"),
    (lambda c: c["extrinsic"].update(quaternion=[0, 0, 1]), r"extrinsic\.quaternion: expected a"),
    (lambda c: c["extrinsic"].update(quaternion=[0, 0, 0, 0]), r"extrinsic\.quaternion"),
    (lambda c: c["extrinsic"].pop("translation"), r"extrinsic: expected one of 'translation'"),
    (lambda c: c["extrinsic"].update({"translation used in CARLA (CARLA reference)": [0, 0, 0]}),
     r"extrinsic: .* got both"),
    (lambda c: c.pop("name"), r"name: missing"),
])
def test_bad_files_name_the_key(tmp_path, edit, match):
    path = _write(tmp_path, _broken(edit))
    with pytest.raises(ValueError, match=match):
        ot.cameras.read_woodscape(path)
    with pytest.raises(ValueError, match=match):
        ot.Camera.load(path)


def test_write_woodscape_refuses_what_the_file_cannot_hold(front, tmp_path):
    camera, T, name = ot.cameras.read_woodscape(front)
    kb = ot.Camera("kannala_brandt", [339.7, 339.7, 643.4, 479.4, 0.0, 0.0, 0.0, 0.0],
                   (966, 1280))
    with pytest.raises(ValueError, match="convert it first"):
        ot.cameras.write_woodscape(tmp_path / "x.json", kb, T, name)
    skewed = T.clone()
    skewed[0, 1] += 0.01
    with pytest.raises(ValueError, match="T: its upper-left 3 x 3 block is not a rotation"):
        ot.cameras.write_woodscape(tmp_path / "x.json", camera, skewed, name)
    with pytest.raises(ValueError, match=r"T: expected shape \(4, 4\)"):
        ot.cameras.write_woodscape(tmp_path / "x.json", camera, T[:3], name)
    with pytest.raises(ValueError, match="name"):
        ot.cameras.write_woodscape(tmp_path / "x.json", camera, T, "")
    assert not (tmp_path / "x.json").exists()


# --------------------------------------------------------------------------------------------
# The model itself: reductions, the fold, the iteration count, the layer's tables
# --------------------------------------------------------------------------------------------

def _agree(params_ws, model, params, dirs):
    a, va = ot.cameras.get_model("woodscape").project(dirs, torch.tensor(params_ws, dtype=F64))
    b, vb = ot.cameras.get_model(model).project(dirs, torch.tensor(params, dtype=F64))
    assert torch.equal(va, vb)
    compared = int(va.sum())
    assert float((a[va] - b[va]).abs().max()) < 1e-6
    ra, _ = ot.cameras.get_model("woodscape").unproject(a[va], torch.tensor(params_ws, dtype=F64))
    rb, _ = ot.cameras.get_model(model).unproject(a[va], torch.tensor(params, dtype=F64))
    assert float((ra - rb).abs().max()) < 1e-9
    return compared


def test_reductions_to_equidistant_and_kannala_brandt():
    """k2 = k3 = k4 = 0 is the equidistant model (fy = aspect_ratio k1); k2 = k4 = 0 is
    Kannala-Brandt with fx = k1 and its k1 = k3 / k1 (the fold at sqrt(-k1 / (3 k3)) on both
    sides)."""
    dirs = fibonacci_sphere(3000)
    assert _agree([320.0, 300.0, 1.05, 200.0, 0, 0, 0], "equidistant",
                  [200.0, 210.0, 320.0, 300.0], dirs) > 0
    assert _agree([320.0, 300.0, 1.0, 200.0, 0, -30.0, 0], "kannala_brandt",
                  [200.0, 200.0, 320.0, 300.0, -0.15, 0, 0, 0], dirs) > 0
    fold = ot.cameras.get_model("woodscape").max_angle(
        torch.tensor([0.0, 0.0, 1.0, 200.0, 0.0, -30.0, 0.0], dtype=F64))
    assert float(fold) == pytest.approx(math.sqrt(200 / 90), rel=1e-12)


def test_max_angle_is_the_first_zero_of_the_slope():
    """Against numpy's roots of d rho / d theta = k1 + 2 k2 t + 3 k3 t^2 + 4 k4 t^3."""
    for params in (CASES["woodscape"][1][0], [0, 0, 1, 300.0, 20.0, -60.0, 5.0]):
        k1, k2, k3, k4 = params[3:]
        roots = np.roots([4 * k4, 3 * k3, 2 * k2, k1])
        fold = min(r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0)
        got = ot.cameras.get_model("woodscape").max_angle(torch.tensor(params, dtype=F64))
        assert float(got) == pytest.approx(min(fold, math.pi), rel=1e-12)


def test_iteration_count_is_fixed_and_non_convergence_is_invalid():
    params = torch.tensor(CASES["woodscape"][0][0], dtype=F64)
    pixels = torch.tensor([[643.442 + r, 479.407] for r in (5.0, 300.0, 600.0, 900.0)],
                          dtype=F64)
    full, valid_full = woodscape_unproject(pixels, params)
    assert bool(valid_full.all())
    few, valid_few = woodscape_unproject(pixels, params, iterations=4)
    assert not bool(valid_few.all()) and bool(torch.isfinite(few).all())
    assert bool(valid_few.any()), "four steps converge for some"
    assert float((few[valid_few] - full[valid_few]).abs().max()) < 1e-9


def test_layer_tables_follow_the_model():
    """The fast path's radius -> ray table (``render.kernels.camera.camera_rays``) of front.json at
    full size against the model's own rays, at every 16th pixel."""
    params = torch.tensor([CASES["woodscape"][0][0]], dtype=F64)
    size = CASES["woodscape"][0][1]
    if kernels.radial_table("woodscape", params, size) is None:
        pytest.fail("woodscape has no radial table")
    rays, valid = kernels.camera_rays("woodscape", params, size)
    camera = ot.Camera("woodscape", params[0], size)
    pixels = camera.pixel_grid()[::16, ::16]
    exact, ok = camera.unproject(pixels)
    assert torch.equal(valid[0, ::16, ::16], ok) and bool(ok.all())
    a, b = rays[0, ::16, ::16][ok], exact[ok]
    angle = torch.atan2(torch.linalg.vector_norm(torch.cross(a, b, dim=-1), dim=-1),
                        (a * b).sum(-1))
    assert float(angle.max()) < 1e-6, float(angle.max())   # 1e-6 rad: 3e-4 px


# --------------------------------------------------------------------------------------------
# The command line: fit, convert-model, select-model
# --------------------------------------------------------------------------------------------

@pytest.mark.numerics
@pytest.mark.usefixtures("one_thread")
def test_cli_fit_recovers_a_woodscape_camera(tmp_path, monkeypatch):
    """``fit --model woodscape`` on 12 noisy views of a board seen by front.json's lens: the
    truth within 3 standard deviations, the file WoodScape's writer takes."""
    from omniscape_torch import cli
    from omniscape_torch.calibration import (Correspondences, checkerboard, random_views,
                                             write_correspondences)
    from omniscape_torch.calibration import report as report_module

    def plot(*args, **kwargs):   # matplotlib takes a second a figure: not what is tested here
        path = Path(args[3] if len(args) > 3 else kwargs["path"])
        path.write_bytes(b"\x89PNG stand-in")
        return path

    monkeypatch.setattr(report_module, "plot_residuals", plot)
    monkeypatch.setattr(report_module, "plot_uncertainty", plot)
    params, size = CASES["woodscape"][0]
    truth = ot.Camera("woodscape", torch.tensor(params, dtype=F64), size)
    board = checkerboard(7, 9, 0.1)
    pixels, _, _ = random_views(truth, board, 12, noise=0.2,
                                generator=torch.Generator().manual_seed(3))
    path = tmp_path / "corr.txt"
    write_correspondences(path, Correspondences([board] * 12, pixels, size,
                                                [f"v{i}" for i in range(12)]))
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "--model", "woodscape", "--accept-coverage", "--out",
                     str(out), "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["converged"], report["reason"]
    fitted = ot.Camera.load_json(out / "camera.json")
    std = torch.tensor([report["params"][n]["std"] for n in fitted.param_names], dtype=F64)
    err = (fitted.params - truth.params).abs()
    assert bool((err <= 3 * std).all()), (err / std).tolist()
    written = ot.cameras.write_woodscape(tmp_path / "FV.json", fitted, torch.eye(4, dtype=F64),
                                         "FV")
    assert ot.Camera.load(written).model.name == "woodscape"


@pytest.mark.numerics
@pytest.mark.usefixtures("one_thread")
def test_cli_convert_model_and_select_model_take_woodscape(tmp_path, capsys):
    """A Kannala-Brandt lens (odd powers only) to WoodScape's quartic: converged within a small
    fraction of a pixel, its camera written; ``select-model --models woodscape`` ranks it."""
    from omniscape_torch import cli
    kb = ot.Camera("kannala_brandt", [300.0, 300.0, 319.5, 239.5, -0.02, 0.004, -0.001, 2e-4],
                   (480, 640), fov=math.radians(180))
    source = tmp_path / "kb.json"
    kb.save_json(source)
    out = tmp_path / "out"
    assert cli.main(["convert-model", "--json", str(source), "--to", "woodscape", "--grid", "24",
                     "--out", str(out)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("woodscape"))
    assert float(line.split()[2]) < 0.05, line   # max px
    converted = ot.Camera.load_json(out / "woodscape.json")
    assert converted.model.name == "woodscape"
    assert cli.main(["select-model", "--json", str(source), "--models", "woodscape", "--rms",
                     "0.05", "--grid", "24"]) == 0
    assert any(ln.startswith("woodscape") for ln in capsys.readouterr().out.splitlines())
