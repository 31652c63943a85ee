"""A fixed target camera in the augmentation (issue 44, item 4): `RandomReproject(camera=...)`
and `RandomOmniCamera(camera=...)` render into one real camera (WoodScape's FV lens), with
optional jitter of its intrinsics and attitude; without jitter `RandomReproject` is
`ot.reproject` into that camera, bit for bit."""

from __future__ import annotations

import json

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.augment import RandomOmniCamera, RandomReproject
from test_woodscape import FRONT

ZERO = dict(roll_range=(0.0, 0.0), pitch_range=(0.0, 0.0), yaw_range=(0.0, 0.0))


@pytest.fixture()
def front_file(tmp_path):
    path = tmp_path / "front.json"
    path.write_text(json.dumps(FRONT))
    return path


@pytest.fixture()
def small_front(front_file):
    """WoodScape's FV lens on a quarter-size sensor (its polynomial and centre scaled)."""
    cam = ot.Camera.load(front_file)
    p = cam.params.detach().double().clone()
    p[:2] = (p[:2] + 0.5) / 8 - 0.5                 # the centre (pixel centres at integers)
    p[3:] = p[3:] / torch.tensor([8.0, 8.0, 8.0, 8.0], dtype=torch.float64)   # rho in pixels
    h, w = cam.image_size
    return ot.Camera("woodscape", p, (h // 8, w // 8))


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
def test_fixed_camera_without_jitter_is_reproject(small_front, dtype):
    g = torch.Generator().manual_seed(0)
    image = (torch.rand(2, 3, 60, 80, generator=g) * 255).to(dtype)
    labels = torch.randint(0, 19, (2, 60, 80), generator=g)
    K = torch.tensor([40.0, 40.0, 39.5, 29.5])
    aug = RandomReproject(None, camera=small_front, seed=0, **ZERO)
    out = aug({"rgb": image, "labels": labels, "intrinsics": K})
    src = ot.Camera("pinhole", K, (60, 80))
    rgb, valid = ot.reproject(image, src, small_front)
    ids, _ = ot.reproject(labels, src, small_front)
    assert out["rgb"].shape[-2:] == small_front.image_size
    assert torch.equal(out["rgb"], rgb) and torch.equal(out["valid"], valid)
    assert torch.equal(out["labels"], ids)
    assert out["params"]["model"] == ("woodscape", "woodscape")
    assert 0.05 < float(valid.float().mean()) < 0.95   # the source fills part of the lens


def test_a_calibration_file_is_a_camera(front_file):
    aug = RandomReproject(None, camera=str(front_file), seed=1, **ZERO)
    assert aug.image_size == (966, 1280) and aug.camera.model.name == "woodscape"
    params = aug.forward_parameters(2)
    want = ot.Camera.load(front_file).params.double()
    assert torch.equal(params["camera_params"][:, :7], want.expand(2, 7))


def test_jitter_moves_the_focal_the_centre_and_the_attitude(small_front):
    aug = RandomReproject(None, camera=small_front, focal_jitter=0.1, center_jitter=2.0,
                          seed=2)
    params = aug.forward_parameters(64)
    base = small_front.params.double()
    rows = params["camera_params"][:, :7]
    scale = rows[:, 3] / base[3]
    assert bool((scale >= 0.9).all()) and bool((scale <= 1.1).all()) and float(scale.std()) > 0.02
    torch.testing.assert_close(rows[:, 3:] / base[3:], scale[:, None].expand(64, 4))
    assert bool(((rows[:, :2] - base[:2]).abs() <= 2.0).all())
    assert torch.equal(rows[:, 2], base[2].expand(64))   # aspect ratio kept
    assert float(params["roll"].abs().max()) > 0.05      # the default attitude ranges


def test_omni_camera_with_a_fixed_camera_is_the_layer(small_front):
    g = torch.Generator().manual_seed(3)
    cube = torch.rand(1, 6, 3, 32, 32, generator=g)
    out = RandomOmniCamera(None, 32, camera=small_front, seed=0, **ZERO)(cube)
    rgb, valid = ot.OmniProjection(small_front, 32)(cube)
    both = out["valid"] & valid
    assert float(both.float().mean()) > 0.5 and float((out["valid"] ^ valid).float().mean()) < 0.01
    # the module's rays come from the camera's radius table: within the tables' error
    assert float((out["rgb"] - rgb).abs()[both.expand_as(rgb)].max()) < 2e-2


def test_bad_cameras_are_refused(small_front):
    with pytest.raises(TypeError, match=r"ot.presets.catadioptric returns \(camera, rotation\)"):
        RandomReproject(None, camera=ot.presets.catadioptric((32, 32)))
    with pytest.raises(ValueError, match="camera: expected one camera"):
        RandomReproject(None, camera=ot.Camera("equidistant", torch.ones(2, 4) * 8, (16, 16)))
    with pytest.raises(ValueError, match="image_size: .* differs from the camera's"):
        RandomReproject((32, 32), camera=small_front)
    with pytest.raises(ValueError, match="focal_jitter"):
        RandomReproject(None, camera=small_front, focal_jitter=1.5)
