"""End-to-end accuracy of ``generate``'s pipeline against the scene's exact ray casting, the
crash safety of ``omniscape-torch generate`` (kill, rerun, compare), and the consistency of the
dynamics it writes.

The steady-turn lean formula ``roll = atan(v^2 kappa / g)`` on the ride model itself (a long arc
at constant speed, no noise) is tested exactly in ``tests/test_ride.py``
(``test_steady_turn_lean_is_atan_v2_over_gr``, ``test_lean_lags_and_is_continuous``,
``test_velocity_is_derivative_of_location``); here the same relations are checked on the
``dynamics.json`` that ``generate`` writes (noise and lag on).
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as nnf

from omniscape_torch.cameras import presets
from omniscape_torch.data.generate import DatasetConfig, generate
from omniscape_torch.io.atomic import LOCK_NAME
from omniscape_torch.render.layer import OmniProjection
from omniscape_torch.scenes.town import Town
from omniscape_torch.render.sizing import required_face_size

GRAVITY = 9.81


# -------------------------------------------------------------------- cubemap path vs ray casting

def _pool_range(x: torch.Tensor, pad_value: float | None = None) -> tuple[torch.Tensor, ...]:
    """3 x 3 neighbourhood max and min of a (H, W) map (edges replicated, or ``pad_value``)."""
    x = x[None, None].float()
    x = nnf.pad(x, (1, 1, 1, 1), mode="replicate") if pad_value is None \
        else nnf.pad(x, (1, 1, 1, 1), value=pad_value)
    return nnf.max_pool2d(x, 3, 1)[0, 0], -nnf.max_pool2d(-x, 3, 1)[0, 0]


# A town pose on the right lane, with a motorcycle attitude: heading 8.6 deg off the road,
# nose 2.3 deg down (suspension), leaning 28.6 deg into a turn.
POSITION = torch.tensor([1.75, -1.2, 3.0])
ATTITUDE = presets.yaw_pitch_roll_to_matrix(torch.tensor(0.15, dtype=torch.float64),
                                            torch.tensor(0.04, dtype=torch.float64),
                                            torch.tensor(0.5, dtype=torch.float64))


@pytest.fixture(scope="module")
def town():
    return Town(0)


@pytest.mark.parametrize("depth_interpolation", ["nearest", "edge_aware"])
@pytest.mark.parametrize("camera_name", ["fisheye", "catadioptric"])
def test_cubemap_path_matches_direct_ray_casting(town, camera_name, depth_interpolation):
    """Cubemap (at the required face size) + OmniProjection equals ray casting the camera's own
    rays, away from object edges.

    Edges: pixels whose 3 x 3 neighbourhood in the direct render holds more than one label or a
    range jump above 5 %, or touches an invalid pixel; there the cubemap's texel and the pixel's
    ray may see different objects. Range is compared where the ray hits something: for the sky
    the direct render gives ``town.far`` along the ray but the cubemap stores ``far`` as planar
    depth (a simulator's far plane), which the projection turns into ``far / cos``.

    Measured (128 x 128, seed 0): labels agree on 100 % of the compared pixels; range within
    0.66 % (nearest; median 0.11 %) and 0.29 % (edge_aware; median 0.003 %) for the fisheye
    (F = 128), 0.65 % / 0.16 % for the catadioptric (F = 164).
    """
    if camera_name == "fisheye":
        camera, r_cam = presets.fisheye((128, 128), fov=math.radians(190)), None
    else:
        camera, r_cam = presets.catadioptric((128, 128))
    rotation = ATTITUDE if r_cam is None else ATTITUDE @ r_cam.double()   # camera -> world
    rotation = rotation.float()
    face_size = required_face_size(camera, rotation)
    cube = town.render_cubemap(POSITION, None, face_size)                 # cube axes = world
    layer = OmniProjection(camera, face_size, depth_interpolation=depth_interpolation,
                           fused_grid=False)
    with torch.no_grad():
        res = layer.render(rgb=cube["rgb"], depth=cube["depth"], labels=cube["labels"],
                           rotation=rotation)
    # the camera's own rays, turned to the world
    _, _, rays, valid = layer.camera_rays()
    d = rays.reshape(-1, 3).double() @ rotation.double().T
    d = (d / d.norm(dim=-1, keepdim=True)).float().reshape(rays.shape)
    direct = town.render_rays(POSITION, d)
    labels, rng = direct["labels"], direct["range"]

    assert torch.equal(res["valid"][0, 0], valid)
    lab_max, lab_min = _pool_range(labels)
    rng_max, rng_min = _pool_range(rng)
    _, valid_min = _pool_range(valid, pad_value=0.0)
    edge = (lab_max != lab_min) | (rng_max - rng_min > 0.05 * rng_min) | (valid_min == 0)
    compared = valid & ~edge
    assert int(compared.sum()) > 0.1 * int(valid.sum())

    label_agree = (res["labels"][0] == labels)[compared].float().mean().item()
    assert label_agree >= 0.99, f"labels agree on {label_agree:.2%} only"

    hit = compared & direct["hit"]
    assert int(hit.sum()) > 0
    rel = ((res["depth"][0, 0] - rng).abs() / rng)[hit]
    within = (rel <= 0.01).float().mean().item()
    assert within >= 0.99, (f"range within 1 % on {within:.2%} of {int(hit.sum())} pixels; "
                            f"worst {rel.max().item():.3%}")
    print(f"{camera_name}/{depth_interpolation}: F={face_size}, compared {int(compared.sum())}"
          f" (labels {label_agree:.2%}), range on {int(hit.sum())}: worst "
          f"{rel.max().item():.3%}, median {rel.median().item():.4%}")


@pytest.mark.parametrize("camera_name", ["fisheye", "catadioptric"])
def test_antialiased_cube_is_closer_to_the_pixels_area(town, camera_name):
    """``render_cubemap(antialias=2)`` and the layer's 2 x 2 rays a pixel (what ``generate``
    does with ``antialias > 1``) against the mean of 8 x 8 traced rays a pixel, at the required
    face size: a higher PSNR than the centre rays' cube, the same labels. Measured (96 x 96):
    33.5 -> 38.5 dB (fisheye, F = 95), 34.7 -> 38.2 dB (catadioptric, F = 123);
    benchmarks/bench_town.py: +3.7 and +4.3 dB at 256 x 256."""
    if camera_name == "fisheye":
        camera, r_cam = presets.fisheye((96, 96), fov=math.radians(190)), None
    else:
        camera, r_cam = presets.catadioptric((96, 96))
    rotation = (ATTITUDE if r_cam is None else ATTITUDE @ r_cam.double()).float()
    face_size = required_face_size(camera, rotation)
    probe = OmniProjection(camera, face_size, supersample=8, fused_grid=False)
    sub, valid_sub, _, valid = probe.camera_rays()
    d = sub.reshape(-1, 3).double() @ rotation.double().T
    d = (d / d.norm(dim=-1, keepdim=True)).float()
    fine = town.render_rays(POSITION, d)["rgb"].reshape(96, 8, 96, 8, 3)
    w = valid_sub.float().reshape(96, 8, 96, 8, 1)
    area = (fine * w).sum((1, 3)) / w.sum((1, 3)).clamp(min=1)

    def psnr(a, b):
        mse = (((a * 255).round() - (b * 255).round()) ** 2).mean().item()
        return 10 * math.log10(255 ** 2 / mse)

    layer = OmniProjection(camera, face_size, supersample=2, fused_grid=False)
    scores, labels = [], []
    for k in (1, 2):
        cube = town.render_cubemap(POSITION, None, face_size, antialias=k)
        with torch.no_grad():
            res = layer.render(rgb=cube["rgb"], labels=cube["labels"], rotation=rotation)
        scores.append(psnr(res["rgb"][0].permute(1, 2, 0)[valid], area[valid]))
        labels.append(res["labels"])
    assert torch.equal(labels[0], labels[1])
    assert scores[1] > scores[0] + 1.5, scores
    print(f"{camera_name}: F={face_size}, PSNR {scores[0]:.2f} -> {scores[1]:.2f} dB")


# -------------------------------------------------------------------- kill and resume

def _generate_cmd(out: Path, frames: int) -> list[str]:
    return [sys.executable, "-m", "omniscape_torch.cli", "generate", "--out", str(out),
            "--frames", str(frames), "--image-size", "32", "--max-face-size", "48",
            "--cameras", "fisheye_left", "catadioptric_left", "--weather", "clear_noon,sunset",
            "--no-progress"]


def _files(root: Path) -> dict[str, Path]:
    """The dataset's files; not the lock (``.lock`` holds the id of the last process that wrote
    the folder, not data)."""
    return {p.relative_to(root).as_posix(): p for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != LOCK_NAME}


def _run(cmd: list[str]) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr


@pytest.mark.slow
def test_killed_run_resumes_to_identical_files(tmp_path):
    """SIGKILL ``generate`` once some but not all frames are finished, rerun it to completion:
    every file equals an uninterrupted run's byte for byte (``dataset.json`` holds no timing
    or date fields, only config, versions, cameras and layout, so it is compared whole), and no
    temporary file is left."""
    interrupted = None
    for frames in (12, 24, 48):
        out = tmp_path / f"A{frames}"
        proc = subprocess.Popen(_generate_cmd(out, frames), stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)
        done_dir = out / ".done"
        try:
            while proc.poll() is None:
                n = len(list(done_dir.iterdir())) if done_dir.is_dir() else 0
                if 1 <= n < frames:
                    proc.send_signal(signal.SIGKILL)
                    proc.wait(timeout=60)
                    break
                time.sleep(0.005)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            proc.stderr.close()
        finished = len(list(done_dir.iterdir())) if done_dir.is_dir() else 0
        if proc.returncode == -signal.SIGKILL and finished < frames:
            interrupted = (out, frames, finished, proc.pid)
            break
    if interrupted is None:
        pytest.skip("generate finished every attempt before it could be killed")
    out_a, frames, finished, pid = interrupted
    assert 1 <= finished < frames
    # a kill during a write leaves the writer's temporary file (io.atomic, io.exr name them
    # .<name>.<pid>.<random>.tmp[.exr]); the kill above only sometimes lands inside a write, so
    # plant such leftovers of the killed process too: the resumed run must not leave them behind
    (out_a / ".done" / f".000000.{pid}.killed01.tmp").write_bytes(b"")
    (out_a / "fisheye_left" / "depth").mkdir(parents=True, exist_ok=True)
    (out_a / "fisheye_left" / "depth" / f".{frames - 1:06d}.exr.{pid}.killed02.tmp.exr"
     ).write_bytes(b"\x76\x2f")

    _run(_generate_cmd(out_a, frames))                   # resume
    out_b = tmp_path / "B"
    _run(_generate_cmd(out_b, frames))                   # uninterrupted
    files_a, files_b = _files(out_a), _files(out_b)
    leftovers = [f for f in files_a if any(part.startswith(".") and part != ".done"
                                           for part in f.split("/"))
                 or ".tmp" in f]
    assert not leftovers, f"temporary files left after the resumed run: {leftovers}"
    assert set(files_a) == set(files_b)
    assert len(list((out_a / ".done").iterdir())) == frames
    differ = [f for f in files_a if files_a[f].read_bytes() != files_b[f].read_bytes()]
    assert not differ, f"files differ from the uninterrupted run: {differ}"
    manifest = json.loads((out_a / "dataset.json").read_text())
    timing = [k for k in manifest if any(w in k.lower() for w in ("time", "date", "elapsed"))]
    assert not timing, f"dataset.json has timing fields {timing}: compare without them"


# -------------------------------------------------------------------- dynamics.json

@pytest.fixture(scope="module")
def dynamics(tmp_path_factory):
    """A small default run (2 fps, seed 0) along the town's road, with its S-bends."""
    out = tmp_path_factory.mktemp("dyn") / "data"
    generate(out, DatasetConfig(frames=60, image_size=(8, 8), cameras=("fisheye_left",),
                                max_face_size=8), progress=False)
    recs = json.loads((out / "dynamics.json").read_text())
    arr = lambda key: np.array([[r[key][a] for a in "xyz"] for r in recs])  # noqa: E731
    return {"t": np.array([r["timestamp"] for r in recs]), "location": arr("location"),
            "velocity": arr("velocity"), "acceleration": arr("acceleration"),
            "angular_velocity": arr("angular_velocity"),
            "speed": np.array([r["speed"] for r in recs]),
            "roll": np.array([r["rotation"]["roll"] for r in recs])}


@pytest.mark.slow
def test_integrated_velocity_matches_location(dynamics):
    """Trapezoid rule over each frame interval: for a velocity with acceleration ``a``, its
    error is ``int K(s) a'(s) ds`` with the Peano kernel ``|K| <= dt^2 / 8``, so it is at most
    ``dt^2 / 8`` times the total variation of ``a`` within the interval. The ride's acceleration
    (longitudinal steps between accelerating and braking, the centripetal term turning with the
    heading) varies by at most ``2 max|a|`` within one interval, which bounds every interval;
    where the acceleration is smooth the error is ``dt^2 / 12 |a_{k+1} - a_k|`` and a step
    inside gives ``dt^2 / 8 |jump|``, so the bound ``dt^2 / 8 |a_{k+1} - a_k|`` holds too on
    intervals without a turn-in (checked on the median)."""
    t, loc, vel, acc = (dynamics[k] for k in ("t", "location", "velocity", "acceleration"))
    dt = np.diff(t)
    assert np.allclose(dt, 0.5)
    trapezoid = (vel[1:] + vel[:-1]) / 2 * dt[:, None]
    err = np.linalg.norm(np.diff(loc, axis=0) - trapezoid, axis=1)
    a_max = np.linalg.norm(acc, axis=1).max()
    assert np.all(err <= dt ** 2 / 8 * 2 * a_max + 1e-6), err.max()
    tight = dt ** 2 / 8 * np.linalg.norm(np.diff(acc, axis=0), axis=1) * 1.01 + 1e-6
    assert np.mean(err <= tight) >= 0.9
    # and over the whole ride the errors do not accumulate past a few intervals' worth
    total = np.linalg.norm(loc[-1] - loc[0] - trapezoid.sum(0))
    assert total <= dt[0] ** 2 / 8 * 2 * a_max * 4
    assert np.allclose(np.linalg.norm(vel, axis=1), dynamics["speed"], atol=1e-9)


def test_roll_follows_steady_lean():
    """Once the lean target ``atan(v^2 kappa / g) = atan(v omega_yaw / g)`` has held for 2 s
    (about 12 time constants of the 1 Hz critically damped lag), the roll equals it within the
    roll noise (0.3 deg standard deviation: 1.5 deg is 5 sigma). The town's road only has
    S-bends, too short to settle, so this takes a ride with long arcs and the same noise; the
    noise-free formula is in tests/test_ride.py (test_steady_turn_lean_is_atan_v2_over_gr)."""
    from omniscape_torch.scenes import ride
    route = ride.Route([ride.straight(40.0), ride.arc(60.0, 120.0), ride.straight(60.0),
                        ride.arc(40.0, -120.0), ride.straight(40.0)])
    frames = ride.simulate(route, 2.0, seed=0)
    t = frames["time"].numpy()
    speed = frames["speed"].numpy()
    roll = frames["rotation"][:, 0].numpy()
    yaw_rate = np.radians(frames["angular_velocity"][:, 2].numpy())  # CARLA: deg/s about z up
    target = np.degrees(np.arctan(speed * yaw_rate / GRAVITY))
    window = 4                                                   # 2 s at 2 fps
    settled = np.array([k >= window and np.ptp(target[k - window:k + 1]) < 0.2
                        for k in range(len(t))])
    curve = settled & (np.abs(target) > 5.0)
    assert curve.sum() >= 5, "no settled curve in the ride"
    assert np.abs(roll[curve] - target[curve]).max() < 1.5
    straight = settled & (np.abs(target) < 0.2)
    assert straight.sum() >= 5 and np.abs(roll[straight]).max() < 1.5
