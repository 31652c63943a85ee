"""Tests of omniscape_torch.cubemap.cone.read_texels: the texels a layer reads.

The oracle is the layer itself: a cube whose texels outside the set hold noise gives the same
images, bit for bit, as the cube itself (RGB bilinear, depth and labels nearest, the border
resampled across the seams), on the C++ route and on torch's.
"""

from __future__ import annotations

import math

import pytest
import torch

from omniscape_torch.cameras import presets
from omniscape_torch.cubemap.cone import camera_cone, cone_texels, read_texels
from omniscape_torch.render.layer import OmniProjection


def _rotation(yaw: float, pitch: float, roll: float) -> torch.Tensor:
    cy, sy, cp, sp, cr, sr = (f(a) for a in (yaw, pitch, roll) for f in (math.cos, math.sin))
    rz = torch.tensor([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    rx = torch.tensor([[1.0, 0, 0], [0, cp, -sp], [0, sp, cp]])
    ry = torch.tensor([[cy, 0, sy], [0, 1.0, 0], [-sy, 0, cy]])
    return (ry @ rx @ rz).float()


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("supersample", [1, 2])
@pytest.mark.parametrize("camera", ["fisheye", "catadioptric"])
def test_noise_outside_the_read_texels_changes_no_pixel(camera, supersample, backend):
    size, F = (40, 40), 48   # a cube finer than the image: many texels no tap reads
    cam = presets.fisheye(size) if camera == "fisheye" else presets.catadioptric(size)[0]
    layer = OmniProjection(cam, F, supersample=supersample, fused_grid=False, backend=backend)
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(1, 6, 3, F, F, generator=g)
    depth = torch.rand(1, 6, F, F, generator=g) * 50 + 1
    labels = torch.randint(0, 13, (1, 6, F, F), generator=g)
    rays_s, valid_s, rays_c, valid_c = layer.camera_rays()
    for rotation in (None, _rotation(0.3, -0.2, 0.1), _rotation(math.pi / 4, 0.0, 0.0)):
        read = read_texels(rays_s, valid_s, rotation, F, layer.pad)
        read |= read_texels(rays_c, valid_c, rotation, F, layer.pad)
        # fewer than every texel in the camera's cone, and none outside it
        axis = torch.tensor([0.0, 0.0, 1.0]) if rotation is None else rotation[:, 2]
        cone = cone_texels(F, axis, camera_cone(cam, F))
        assert not (read & ~cone).any()
        assert read.sum() < cone.sum()
        keep = read.view(1, 6, 1, F, F)
        noisy = dict(rgb=torch.where(keep, rgb, torch.rand(rgb.shape, generator=g)),
                     depth=torch.where(keep[:, :, 0], depth,
                                       torch.rand(depth.shape, generator=g) * 900),
                     labels=torch.where(keep[:, :, 0], labels, torch.randint(
                         0, 13, labels.shape, generator=g)))
        with torch.no_grad():
            a = layer.render(rgb=rgb, depth=depth, labels=labels, rotation=rotation)
            b = layer.render(rotation=rotation, **noisy)
        for key in ("rgb", "depth", "labels", "valid"):
            assert torch.equal(a[key], b[key]), (key, rotation)


def test_rays_on_a_seam_read_both_faces():
    """A ray on the edge between two faces reads texels of both (the layer may pick either)."""
    F = 8
    rays = torch.tensor([[1.0, 0.0, 1.0]])   # between +x and +z
    read = read_texels(rays, torch.ones(1, dtype=torch.bool), None, F, 1)
    assert int(read.flatten(1).any(1).sum()) == 2
