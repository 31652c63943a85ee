"""The library on a CUDA device: the same contracts as on the CPU, and the same results.

Skipped where no CUDA device is present (CI has none; ``.ci/run`` never needs one). On a GPU
machine: ``pytest -q tests/test_cuda.py`` (the project's ``device`` checks ran it on an H200).
On CUDA the augmentation modules and ``ot.reproject`` run the exact chain (``Camera.ray_grid``,
``grid_sample``) where the CPU runs the C++ sampler, so the comparisons against the CPU allow
the rounding of two implementations: rims of the valid area may flip by a rounding of the
rays, RGB within a level. The detection contracts are checked on CUDA against the same
independent oracles as ``tests/test_detection.py`` (objects and markers rendered through the
draw, tight boxes and centroids taken in numpy).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from conftest import all_cases
from test_detection import (BOX_PX, KEYPOINT_PX, _repeat, centroids, discs, random_boxes,
                            rectangles, tight_box)

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

DEG = math.pi / 180
CUDA = torch.device("cuda")


def _rim_flips(a: torch.Tensor, b: torch.Tensor) -> float:
    """Share of pixels whose validity differs between two masks."""
    return float((a.cpu() != b.cpu()).float().mean())


@pytest.mark.parametrize("model, params, size", all_cases())
def test_camera_models_match_cpu(model, params, size):
    """project / unproject in float64 on CUDA equal the CPU's to rounding, valid sets equal."""
    gen = torch.Generator().manual_seed(0)
    h, w = size
    pixels = torch.rand(2000, 2, generator=gen, dtype=torch.float64) * torch.tensor(
        [w - 1.0, h - 1.0])
    p = torch.tensor(params, dtype=torch.float64)
    m = ot.cameras.get_model(model)
    rays, ok = m.unproject(pixels, p)
    rays_gpu, ok_gpu = m.unproject(pixels.to(CUDA), p.to(CUDA))
    assert torch.equal(ok, ok_gpu.cpu())
    torch.testing.assert_close(rays_gpu.cpu()[ok], rays[ok], atol=1e-9, rtol=0)
    back, ok2 = m.project(rays[ok], p)
    back_gpu, ok2_gpu = m.project(rays[ok].to(CUDA), p.to(CUDA))
    assert torch.equal(ok2, ok2_gpu.cpu())
    torch.testing.assert_close(back_gpu.cpu()[ok2], back[ok2], atol=1e-6, rtol=0)


@pytest.mark.parametrize("model, params", [
    # principal points off the pixel grid's symmetry: with (63.5, 63.5) the rows and columns
    # through the centre land exactly on texel edges, where nearest labels are ties that a
    # rounding of either device decides (0.3% of pixels differed on an H200)
    ("equidistant", [60.0, 60.0, 63.3, 63.8]),
    ("unified", [70.0, 70.0, 63.2, 63.7, 0.9, 0.0, 0.0, 0.0, 0.0]),
])
def test_layer_renders_and_differentiates_as_on_cpu(model, params):
    """``OmniProjection`` on CUDA: RGB, depth (a sphere's range) and labels as on the CPU
    (labels equal where both are valid), and the gradient to learnable intrinsics the CPU's."""
    gen = torch.Generator().manual_seed(1)
    face = 32
    cube = torch.rand(2, 6, 3, face, face, generator=gen)
    labels = torch.randint(0, 13, (2, 6, face, face), generator=gen)
    # a sphere of radius 5 m about the camera: planar depth 5 / |(x, y, 1)| on every face, so
    # the output range is 5 m wherever it is valid (an oracle for both devices)
    t = (torch.arange(face) - (face - 1) / 2) / (face / 2)
    depth = (5 / (1 + t[:, None] ** 2 + t[None, :] ** 2).sqrt()).expand(2, 6, face, face)
    outs, grads = [], []
    for device in ("cpu", CUDA):
        cam = ot.Camera(model, params, (128, 128), learnable=True).to(device)
        layer = ot.OmniProjection(cam, face).to(device)
        out = layer.render(rgb=cube.to(device), labels=labels.to(device),
                           depth=depth.to(device))
        (out["rgb"] * out["valid"]).square().mean().backward()
        outs.append({k: v.detach().cpu() for k, v in out.items()})
        grads.append(next(p for p in cam.parameters()).grad.cpu())
    cpu, gpu = outs
    assert _rim_flips(cpu["valid"], gpu["valid"]) < 0.005
    both = (cpu["valid"] & gpu["valid"])[:, 0]
    assert int(both.sum()) > 0.3 * both.numel()
    torch.testing.assert_close(gpu["rgb"].permute(0, 2, 3, 1)[both],
                               cpu["rgb"].permute(0, 2, 3, 1)[both], atol=1e-4, rtol=0)
    for out in (cpu, gpu):
        assert float((out["depth"][:, 0][both] - 5).abs().max()) < 0.05
    torch.testing.assert_close(gpu["depth"][:, 0][both], cpu["depth"][:, 0][both],
                               atol=1e-3, rtol=0)
    assert (gpu["labels"][both] == cpu["labels"][both]).float().mean() > 0.999
    torch.testing.assert_close(grads[1], grads[0], rtol=2e-3, atol=1e-6)


@pytest.mark.parametrize("dtype, channels_last", [(torch.float32, False), (torch.uint8, True)])
def test_random_omni_camera_on_cuda(dtype, channels_last):
    """``RandomOmniCamera`` on CUDA, float and ``uint8`` channels-last cubes: the CPU's draws
    (drawn on the CPU), outputs on the cube's device, RGB within a level (uint8) / 1e-4."""
    gen = torch.Generator().manual_seed(2)
    face = 32
    cube = torch.rand(3, 6, 3, face, face, generator=gen)
    if dtype == torch.uint8:
        cube = (cube * 255).round().to(torch.uint8)
    if channels_last:
        cube = cube.permute(0, 1, 3, 4, 2).contiguous()
    labels = torch.randint(0, 13, (3, 6, face, face), generator=gen)
    aug = ot.augment.RandomOmniCamera((96, 96), face, mode="mixed", seed=3,
                                      channels_last=channels_last)
    params = aug.forward_parameters(3)
    cpu = aug(cube, labels, params=params)
    gpu = aug(cube.to(CUDA), labels.to(CUDA), params=params)
    assert gpu["rgb"].is_cuda and gpu["valid"].is_cuda and gpu["labels"].is_cuda
    assert gpu["rgb"].dtype == cpu["rgb"].dtype and gpu["rgb"].shape == cpu["rgb"].shape
    assert _rim_flips(cpu["valid"], gpu["valid"]) < 0.01
    both = (cpu["valid"] & gpu["valid"].cpu())[:, 0]
    rgb_c, rgb_g = cpu["rgb"], gpu["rgb"].cpu()
    if not channels_last:
        rgb_c, rgb_g = rgb_c.permute(0, 2, 3, 1), rgb_g.permute(0, 2, 3, 1)
    diff = (rgb_g[both].double() - rgb_c[both].double()).abs()
    assert float(diff.max()) <= (1.0 if dtype == torch.uint8 else 1e-4)
    assert (gpu["labels"].cpu()[both] == cpu["labels"][both]).float().mean() > 0.999


def test_random_reproject_on_cuda_matches_cpu():
    """``RandomReproject`` on CUDA (uint8 RGB, antialiased where it minifies, labels, boxes,
    keypoints), the CPU's draws: the same valid area up to rims, RGB within the rounding of
    the CPU's 8-bit pyramid levels (the same filter rule on both), labels agreeing, boxes and
    keypoints the CPU's to a hundredth of a pixel."""
    gen = torch.Generator().manual_seed(4)
    size = (192, 256)   # into 80 x 80: most pixels minify
    rgb = (torch.rand(2, 3, *size, generator=gen) * 255).round().to(torch.uint8)
    labels = torch.randint(0, 13, (2, *size), generator=gen)
    boxes = [random_boxes(5, size, gen) for _ in range(2)]
    kp = torch.rand(2, 7, 2, generator=gen) * torch.tensor([250.0, 186.0]) + 2
    aug = ot.augment.RandomReproject((80, 80), source_fov=90 * DEG, seed=5,
                                     fisheye_models=("equidistant", "unified"))
    params = aug.forward_parameters(2)
    sample = {"rgb": rgb, "labels": labels, "boxes": boxes, "keypoints": kp}
    cpu = aug(sample, params=params)
    gpu = aug({"rgb": rgb.to(CUDA), "labels": labels.to(CUDA),
               "boxes": [b.to(CUDA) for b in boxes], "keypoints": kp.to(CUDA)}, params=params)
    assert gpu["rgb"].is_cuda and gpu["rgb"].dtype == torch.uint8
    assert _rim_flips(cpu["valid"], gpu["valid"]) < 0.01
    both = (cpu["valid"] & gpu["valid"].cpu())[:, 0]
    diff = (gpu["rgb"].cpu().permute(0, 2, 3, 1)[both].int() -
            cpu["rgb"].permute(0, 2, 3, 1)[both].int()).abs()
    # (a level or two of the 8-bit pyramid; the rare pixel whose footprint is a power of two
    # within rounding reads the neighbouring level: tests/test_mip_image.py)
    assert float((diff > 2).float().mean()) < 1e-3 and float((diff > 1).float().mean()) < 0.01
    assert (gpu["labels"].cpu()[both] == cpu["labels"][both]).float().mean() > 0.995
    for i in range(2):
        assert torch.equal(gpu["box_index"][i].cpu(), cpu["box_index"][i])
        torch.testing.assert_close(gpu["boxes"][i].cpu(), cpu["boxes"][i], atol=0.01, rtol=0)
    assert torch.equal(gpu["keypoints_valid"].cpu(), cpu["keypoints_valid"])
    ok = cpu["keypoints_valid"]
    torch.testing.assert_close(gpu["keypoints"].cpu()[ok], cpu["keypoints"][ok], atol=0.01,
                               rtol=0)


@pytest.mark.parametrize("models, options", [
    (("equidistant", "kannala_brandt"), {}),
    (("unified",), dict(unified_xi_range=(0.8, 1.0))),
])
def test_detection_contracts_on_cuda(models, options):
    """On CUDA: boxes within a pixel of the tight box of their object's output pixels (the
    object rendered nearest through the same draw), keypoints within 0.75 px of their
    markers' output centroids, for fisheye and catadioptric draws."""
    size = (48, 64)
    gen = torch.Generator().manual_seed(6)
    aug = ot.augment.RandomReproject((64, 64), source_fov=100 * DEG, fisheye_models=models,
                                     interpolation="nearest", seed=7, **options)
    boxes = random_boxes(10, size, gen)
    out = aug({"rgb": torch.zeros(1, 1, *size, device=CUDA), "boxes": [boxes.to(CUDA)]})
    again = aug({"labels": rectangles(boxes, size).to(CUDA)},
                params=_repeat(out["params"], len(boxes)))
    compared = 0
    for j in range(len(boxes)):
        expected = tight_box(again["labels"][j].cpu() == 1)
        got = out["boxes"][0][out["box_index"][0] == j].cpu()
        if expected is None:
            continue
        assert len(got) == 1, f"box {j}: object has pixels, box dropped"
        assert np.abs(got[0].double().numpy() - expected).max() <= BOX_PX, (j, got, expected)
        compared += 1
    assert compared >= 6

    kp = torch.rand(6, 2, generator=gen, dtype=torch.float64) * torch.tensor([44.0, 28.0]) + 10
    marker = ot.augment.RandomReproject((96, 96), source_fov=90 * DEG, fisheye_models=models,
                                        seed=8, focal_scale_range=(1.0, 1.0), **options)
    out = marker({"rgb": discs(size, kp)[None].to(CUDA), "keypoints": kp[None].float().to(CUDA)})
    assert bool(out["keypoints_valid"].all())
    err = (out["keypoints"][0].cpu().double() - centroids(out["rgb"][0].cpu())).norm(dim=-1)
    assert float(err.max()) <= KEYPOINT_PX, err


def test_reproject_antialiased_on_cuda_matches_cpu():
    """``ot.reproject`` minifying a 1-px line grid (its antialiasing on, the default) gives the
    CPU's image on CUDA: the prefilter is the same rule on both devices."""
    grid = torch.zeros(1, 1, 240, 320)
    grid[..., ::2, :] = 1.0
    grid[..., :, ::2] = 1.0
    src = ot.Camera("pinhole", [200.0, 200.0, 159.5, 119.5], (240, 320))
    dst = ot.Camera("equidistant", [20.0, 20.0, 31.5, 31.5], (64, 64))
    cpu, ok = ot.reproject(grid, src, dst)
    gpu, ok_gpu = ot.reproject(grid.to(CUDA), src.to(CUDA), dst.to(CUDA))
    assert _rim_flips(ok, ok_gpu) < 0.01
    both = ok & ok_gpu.cpu()
    torch.testing.assert_close(gpu.cpu()[both.expand_as(cpu)], cpu[both.expand_as(cpu)],
                               atol=2e-3, rtol=0)
    # and it did filter: the grid's mean (0.75), not its lines, away from the rim
    assert abs(float(cpu[both.expand_as(cpu)].mean()) - 0.75) < 0.05
