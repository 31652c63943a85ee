"""Stereo rig: extrinsics, and geometry that only holds if each camera samples its own cube."""

from __future__ import annotations

import math

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.render.rig import StereoRig

F64 = torch.float64


#: An oblique wall n . X = D in the rig frame (not parallel to the baseline, so the two
#: cameras see different ranges along the same direction).
NORMAL = torch.tensor([0.3, 0.0, 1.0], dtype=F64) / math.hypot(0.3, 1.0)
D = 5.0


def _wall_depth(position, face_size):
    """Planar depth cube of the wall seen from ``position``: along a texel ray d (whose
    component along the face axis is 1) the wall is hit at t = (D - n . p) / (n . d), and the
    planar depth is t. Rays that never hit it get 1e3."""
    rays = ot.cubemap.face_rays(face_size, dtype=F64)  # (6, F, F, 3)
    t = (D - NORMAL @ position) / (rays @ NORMAL)
    return torch.where(t > 0, t, torch.full_like(t, 1e3)).unsqueeze(0)


def test_extrinsics_baseline():
    cam = ot.Camera("equidistant", torch.tensor([10.0, 10.0, 15.5, 15.5], dtype=F64), (32, 32))
    rig = StereoRig(ot.OmniProjection(cam, 16), ot.OmniProjection(cam, 16), baseline=0.4)
    ext = rig.extrinsics()
    centre_left = torch.tensor([0.0, 0.0, 0.0, 1.0])
    # the left camera's centre seen from the right camera: 0.4 m to its left (-x)
    torch.testing.assert_close(ext["T_right_left"] @ centre_left,
                               torch.tensor([-0.4, 0.0, 0.0, 1.0]))
    torch.testing.assert_close(ext["T_rig_left"][:3, 3], torch.tensor([-0.2, 0.0, 0.0]))


@pytest.mark.parametrize("yaw", [0.0, 0.3])
def test_each_camera_sees_the_wall_from_its_own_position(yaw):
    """Back-project every valid pixel with its range: in the rig frame it lies on the wall."""
    f = 20.0
    cam = ot.Camera("equidistant", torch.tensor([f, f, 31.5, 31.5], dtype=F64), (64, 64),
                    fov=math.radians(120))
    c, s = math.cos(yaw), math.sin(yaw)
    # camera -> rig rotations: the cameras turn outwards by -yaw / +yaw about the y axis
    rot = torch.tensor([[[c, 0, -s], [0, 1, 0], [s, 0, c]], [[c, 0, s], [0, 1, 0], [-s, 0, c]]],
                       dtype=F64)
    positions = torch.tensor([[-0.25, 0.0, 0.0], [0.25, 0.0, 0.0]], dtype=F64)
    layer = ot.OmniProjection(cam, 64, depth_interpolation="bilinear")
    rig = StereoRig(layer, layer, positions=positions, rotations=rot).double()
    out = rig(None, None, left_depth=_wall_depth(positions[0], 64),
              right_depth=_wall_depth(positions[1], 64))
    rays, valid = cam.ray_grid()
    compared = 0
    for i, name in enumerate(("left", "right")):
        rng = out[name]["depth"][0, 0]
        ok = valid & out[name]["valid"][0, 0]
        pts_cam = rays * rng.unsqueeze(-1)
        t = out[f"T_rig_{name}"]
        pts_rig = pts_cam @ t[:3, :3].T + t[:3, 3]
        # bilinear range on a plane: off by the interpolation error only, which grows like
        # 1 + 2 tan^2 of the incidence angle: compare where the wall is seen within 60 degrees
        # of its normal ((1 + 2 * 3) * (2 / 64)^2 / 8 = 8.5e-4)
        dirs = rays @ t[:3, :3].T
        ok = ok & ((dirs @ NORMAL).abs() > 0.5)
        err = (pts_rig @ NORMAL - D)[ok].abs() / D
        assert float(err.max()) < 1e-3
        compared += int(ok.sum())
    assert compared > 0
    # the two images differ: a shared cube would give identical depth for yaw = 0
    assert not torch.allclose(out["left"]["depth"], out["right"]["depth"])


def test_rig_rejects_bad_arguments():
    cam = ot.Camera("equidistant", [10.0, 10.0, 15.5, 15.5], (32, 32))
    layer = ot.OmniProjection(cam, 16)
    with pytest.raises(TypeError, match="left"):
        StereoRig(cam, layer)
    with pytest.raises(ValueError, match="baseline"):
        StereoRig(layer, layer, baseline=-1.0)
    with pytest.raises(ValueError, match="rotations"):
        StereoRig(layer, layer, rotations=torch.ones(2, 3, 3))
    rig = StereoRig(layer, layer)
    with pytest.raises(TypeError, match="unexpected keyword"):
        rig(torch.rand(1, 6, 3, 16, 16), torch.rand(1, 6, 3, 16, 16), depth=torch.rand(1, 6, 16, 16))


def test_rig_renders_uint8_and_channels_last_cubes():
    """uint8 cubes: within a level of the float image of their levels (rounded half up);
    channels-last: the channels-first images permuted, exactly; out_dtype for both cameras."""
    cam = ot.Camera("equidistant", [9.0, 9.0, 11.5, 11.5], (24, 24), fov=math.radians(190))
    rig = StereoRig(ot.OmniProjection(cam, 16), ot.OmniProjection(cam, 16))
    g = torch.Generator().manual_seed(0)
    left, right = (torch.randint(0, 256, (2, 6, 3, 16, 16), dtype=torch.uint8, generator=g)
                   for _ in range(2))
    yaw = torch.tensor([[0.8, 0.0, 0.6], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]])
    for rotation in (None, yaw.expand(2, 3, 3)):
        u8 = rig(left, right, rotation)
        ref = rig(left.float(), right.float(), rotation)
        last = rig(left.permute(0, 1, 3, 4, 2), right.permute(0, 1, 3, 4, 2), rotation,
                   channels_last=True)
        scaled = rig(left, right, rotation, out_dtype=torch.float32)
        for name in ("left", "right"):
            assert u8[name]["rgb"].dtype == torch.uint8
            expected = torch.floor(ref[name]["rgb"] + 0.5)
            assert float((u8[name]["rgb"].float() - expected).abs().max()) <= 1
            assert torch.equal(u8[name]["valid"], ref[name]["valid"])
            assert last[name]["rgb"].shape == (2, 24, 24, 3)
            assert torch.equal(last[name]["rgb"], u8[name]["rgb"].permute(0, 2, 3, 1))
            assert scaled[name]["rgb"].dtype == torch.float32
            torch.testing.assert_close(scaled[name]["rgb"], ref[name]["rgb"] / 255, atol=1e-6,
                                       rtol=0)
        assert not torch.equal(u8["left"]["rgb"], u8["right"]["rgb"])   # each its own cube
    # one camera's cube only: the options apply to it, the other renders depth
    out = rig(left.permute(0, 1, 3, 4, 2), None, channels_last=True,
              right_depth=torch.ones(2, 6, 16, 16))
    assert out["left"]["rgb"].shape == (2, 24, 24, 3) and "rgb" not in out["right"]
    with pytest.raises(ValueError, match="channels_last"):
        rig(None, None, channels_last=True, left_depth=torch.ones(2, 6, 16, 16))
    with pytest.raises(TypeError, match="channels_last"):
        rig(left, right, channels_last=1)
    with pytest.raises(TypeError, match="out_dtype"):
        rig(left, right, out_dtype=torch.int32)
