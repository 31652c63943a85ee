"""The C++ antialiasing of perspective sources (``fast.mip_image``, ``RandomReproject``'s fast
path): its documented rule against an independent PyTorch model of it (``avg_pool2d``
pyramid, ``antialias.footprint``, bilinear taps written out), a uniform 4x minification
against the exact 4 x 4 box average, and the pixels that do not minify left bit for bit."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

import omniscape_torch as ot
from omniscape_torch.render import antialias
from omniscape_torch.render.kernels import available
from omniscape_torch.render.kernels import image as fast
from omniscape_torch.render.kernels.cube import work_dtype

pytestmark = pytest.mark.skipif(not available(), reason="C++ kernels unavailable")


def _bilinear(level: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``level (C, H, W)`` at level pixels ``x, y (N,)`` (centres at integers), clamped to the
    level: ``(C, N)``."""
    h, w = level.shape[-2:]
    x = x.clamp(0, w - 1)
    y = y.clamp(0, h - 1)
    j, i = x.floor().long(), y.floor().long()
    fx, fy = x - j, y - i
    j1, i1 = (j + 1).clamp(max=w - 1), (i + 1).clamp(max=h - 1)
    return ((1 - fy) * ((1 - fx) * level[:, i, j] + fx * level[:, i, j1]) +
            fy * ((1 - fx) * level[:, i1, j] + fx * level[:, i1, j1]))


def _rule(image: torch.Tensor, pixels: torch.Tensor, valid: torch.Tensor
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """The documented filter of ``fast.mip_image`` in float64: ``(values (C, h, w), mask)``,
    one image ``(C, H, W)`` and its pixels ``(h, w, 2)``."""
    du, dv = antialias.footprint(pixels[None], valid[None])
    du, dv = du[0], dv[0]
    a, b = du.square().sum(-1), dv.square().sum(-1)
    mask = valid & ((a > antialias.MINIFIES ** 2) | (b > antialias.MINIFIES ** 2))
    levels = [image.double()]
    while max(levels[-1].shape[-2:]) > 1:
        levels.append(F.avg_pool2d(levels[-1][None], 2, ceil_mode=True)[0])
    # k = floor(log2(rho / 2)): frexp's exponent e of rho^2 = m 2^e, m in [0.5, 1)
    k = (torch.frexp(torch.maximum(a, b))[1] - 1).div(2, rounding_mode="floor") - 1
    k = k.clamp(0, len(levels) - 1)
    out = torch.zeros(image.shape[0], *valid.shape, dtype=torch.float64)
    for level in k[mask].unique().tolist():
        sel = mask & (k == level)
        p, ju, jv = pixels[sel], du[sel], dv[sel]
        scale = 2.0 ** -level
        acc = 0
        for sa in (-0.25, 0.25):
            for sb in (-0.25, 0.25):
                at = p + sa * ju + sb * jv
                acc = acc + _bilinear(levels[level], (at[:, 0] + 0.5) * scale - 0.5,
                                      (at[:, 1] + 0.5) * scale - 0.5)
        out[:, sel] = acc / 4
    return out, mask


def _fisheye_case(dtype: torch.dtype, channels_last: bool, chans: int, focal: float,
                  angle: float):
    """A 96 x 160 source (pinhole, fx = 90) seen by a 48 x 48 equidistant fisheye of
    ``focal`` pixels a radian turned by ``angle`` about the vertical."""
    gen = torch.Generator().manual_seed(7)
    src = torch.rand(1, chans, 96, 160, generator=gen, dtype=torch.float64)
    image = (src * 255).round().to(torch.uint8) if dtype == torch.uint8 else src.to(dtype)
    if channels_last:
        image = image.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    work = work_dtype(image.dtype)
    rays, ok = ot.Camera("equidistant", torch.tensor([focal, focal, 23.5, 23.5]),
                         (48, 48)).ray_grid()
    rot = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                        [-math.sin(angle), 0, math.cos(angle)]])
    k = torch.tensor([[90.0, 90.0, 79.5, 47.5]])
    rays, rot, k = rays[None].to(work), rot[None].to(work), k.to(work)
    out, seen = fast.sample_image(image, rays, rot, k, valid=ok[None])
    src_rays = torch.einsum("ij,hwj->hwi", rot[0].double(), rays[0].double())
    pixels = src_rays[..., :2] / src_rays[..., 2:] * k[0, :2].double() + k[0, 2:].double()
    return image, rays, rot, k, out, seen, pixels


@pytest.mark.parametrize("focal,angle", [(14.0, 0.2), (110.0, 0.6)])
@pytest.mark.parametrize("dtype,channels_last,chans", [
    (torch.uint8, True, 3), (torch.uint8, False, 3), (torch.uint8, True, 4),
    (torch.uint8, False, 1), (torch.float32, True, 3), (torch.float64, False, 2)])
def test_mip_image_is_its_documented_rule(dtype, channels_last, chans, focal, angle):
    """Against the float64 model of the rule, footprints of 4 to 16 source pixels (levels
    1-3, the whole image, its rim) and of 0.8 to 1.6 (a view part magnified, part not):
    float64 to rounding (1e-9); float32 within 1e-4; uint8 within 2 levels (levels rounded
    half up at each halving, then the output rounded). Pixels that do not minify: the point
    samples, bit for bit."""
    image, rays, rot, k, out, seen, pixels = _fisheye_case(dtype, channels_last, chans, focal,
                                                           angle)
    before = out.clone()
    fast.mip_image(image, rays, rot, k, seen, out)
    expected, mask = _rule(image[0].double(), pixels, seen[0])
    assert int(mask.sum()) >= 200
    assert focal < 50 or bool((seen[0] & ~mask).any())
    m = mask[None, None].expand_as(out)
    assert torch.equal(out[~m], before[~m])
    got = out[0].double()
    tol = {torch.uint8: 2.0, torch.float32: 1e-4, torch.float64: 1e-9}[dtype]
    assert float((got - expected)[:, mask].abs().max()) <= tol


@pytest.mark.parametrize("focal,angle", [(14.0, 0.2), (110.0, 0.6)])
def test_the_torch_path_is_the_same_rule(focal, angle):
    """``antialias.minified`` (what CUDA, gradients and ``ot.reproject`` run) is the rule of the
    C++ op, to float64 rounding: one module gives one image on every device and path."""
    image, rays, rot, k, out, seen, pixels = _fisheye_case(torch.float64, False, 3, focal,
                                                           angle)
    expected, mask = _rule(image[0], pixels, seen[0])
    values, where = antialias.minified(image, pixels[None], seen)
    assert torch.equal(where[0, 0], mask) and int(mask.sum()) >= 200
    assert float((values[0] - expected)[:, mask].abs().max()) <= 1e-9
    fast.mip_image(image, rays, rot, k, seen, out)
    assert float((out[0] - values[0])[:, mask].abs().max()) <= 1e-9


@pytest.mark.parametrize("channels_last", [True, False])
def test_uniform_minification_is_the_box_average(channels_last):
    """A pinhole 4x coarser, its pixels on 4 x 4 blocks of the source: each output pixel is
    the block's mean (``avg_pool2d(4)``), within rounding (uint8: 1 level; float64: 1e-12),
    where point samples keep one texel's bilinear blend."""
    gen = torch.Generator().manual_seed(3)
    src = torch.rand(2, 3, 64, 96, generator=gen, dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(16.0, dtype=torch.float64),
                            torch.arange(24.0, dtype=torch.float64), indexing="ij")
    k = torch.tensor([[100.0, 100.0, 47.5, 31.5]], dtype=torch.float64)
    # output pixel (x, y) at source (4 x + 1.5, 4 y + 1.5): the centre of its 4 x 4 block
    rays = torch.stack(((4 * xs + 1.5 - 47.5) / 100, (4 * ys + 1.5 - 31.5) / 100,
                        torch.ones_like(xs)), -1)[None].double()
    box = F.avg_pool2d(src, 4)
    for dtype, tol in ((torch.uint8, 1.0), (torch.float64, 1e-12)):
        image = (src * 255).round().to(torch.uint8) if dtype == torch.uint8 else src
        if channels_last:
            image = image.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
        work = work_dtype(dtype)
        out, seen = fast.sample_image(image, rays.to(work), None, k.to(work))
        fast.mip_image(image, rays.to(work), None, k.to(work), seen, out)
        ref = F.avg_pool2d(image.double(), 4)
        assert bool(seen.all())
        assert float((out.double() - ref).abs().max()) <= tol
    assert float((box - src[..., 1::4, 1::4]).abs().max()) > 0.3   # point samples differ


def test_mip_image_arguments():
    image = torch.rand(1, 3, 8, 8, dtype=torch.float16)
    rays = torch.zeros(1, 4, 4, 3)
    with pytest.raises(TypeError, match="image"):
        fast.mip_image(image, rays, None, torch.ones(1, 4), torch.ones(1, 4, 4, dtype=torch.bool),
                       torch.zeros(1, 3, 4, 4, dtype=torch.float16))
    with pytest.raises(RuntimeError, match="valid"):
        fast.mip_image(image.float(), rays, None, torch.ones(1, 4),
                       torch.ones(1, 5, 4, dtype=torch.bool), torch.zeros(1, 3, 4, 4))


def test_fast_and_exact_paths_of_random_reproject_agree():
    """``RandomReproject`` antialiased on its C++ path (``uint8``, no gradient) and on the
    exact one (a float image that requires a gradient: what CUDA runs too) give the same
    image to the rounding of the 8-bit pyramid levels, where most pixels minify; but for the
    rare pixel whose footprint is within rounding of a power of two, where the two pick
    neighbouring levels (the level is a step of ``rho``: 22 of 1.6 million pixels of
    ``bench_reproject``'s noise images, up to 33 levels apart)."""
    gen = torch.Generator().manual_seed(4)
    rgb = (torch.rand(2, 3, 192, 256, generator=gen) * 255).round().to(torch.uint8)
    aug = ot.augment.RandomReproject((80, 80), source_fov=math.radians(90), seed=5,
                                     fisheye_models=("equidistant", "unified"))
    params = aug.forward_parameters(2)
    fast_out = aug(rgb, params=params)
    exact = aug(rgb.float().requires_grad_(True), params=params)
    assert torch.equal(fast_out["valid"], exact["valid"])
    both = fast_out["valid"].expand_as(fast_out["rgb"])
    diff = (exact["rgb"].detach()[both] - fast_out["rgb"][both].float()).abs()
    assert float((diff > 2).float().mean()) < 1e-3 and float(diff.mean()) < 0.5
    # the draws minify (the filter matters: point samples differ by tens of levels)
    point = ot.augment.RandomReproject((80, 80), source_fov=math.radians(90), seed=5,
                                       fisheye_models=("equidistant", "unified"),
                                       antialias=False)(rgb, params=params)
    assert float((point["rgb"][both].float() - fast_out["rgb"][both].float()).abs().max()) > 20


@pytest.mark.parametrize("dtype,channels_last", [(torch.uint8, True), (torch.uint8, False),
                                                 (torch.float32, False), (torch.float64, True)])
@pytest.mark.parametrize("labels_dtype", [None, torch.uint8, torch.int64])
def test_reproject_image_is_the_ops_in_turn(dtype, channels_last, labels_dtype):
    """``fast.reproject_image`` (``RandomReproject``'s fused fast path) writes what
    ``camera_rays``, ``sample_image``, ``mip_image`` and the labels' ``sample_image`` write
    in turn, bit for bit: two equidistant cameras, turned, one minifying the source, one
    magnifying it, ``valid`` included."""
    gen = torch.Generator().manual_seed(11)
    src = torch.rand(2, 3, 96, 160, generator=gen, dtype=torch.float64)
    image = (src * 255).round().to(torch.uint8) if dtype == torch.uint8 else src.to(dtype)
    if channels_last:
        image = image.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    labels = (None if labels_dtype is None else
              torch.randint(0, 19, (2, 96, 160), generator=gen).to(labels_dtype))
    work = work_dtype(image.dtype)
    cams = torch.tensor([[14.0, 14.0, 23.5, 23.5], [110.0, 110.0, 20.0, 26.0]],
                        dtype=torch.float64)
    affine, limits, table = ot.render.kernels.camera.radial_table("equidistant", cams, (48, 48))
    limits[:, 3] = math.cos(math.radians(85))
    affine, limits, table = (t.to(work).contiguous() for t in (affine, limits, table))
    rot = torch.stack([torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0],
                                     [-math.sin(a), 0, math.cos(a)]]) for a in (0.2, -0.5)])
    rot, k = rot.to(work), torch.tensor([[90.0, 90.0, 79.5, 47.5]], dtype=work).expand(2, 4)
    rays, ok = fast.camera_rays(affine, limits, table, (48, 48), work)
    want, seen = fast.sample_image(image, rays, rot, k, valid=ok)
    fast.mip_image(image, rays, rot, k, seen, want)
    out, valid = torch.empty_like(want), torch.empty_like(seen)
    out_labels = None if labels is None else torch.empty(2, 48, 48, dtype=torch.int64)
    fast.reproject_image(image, labels, affine, limits, table, rot, k, True,
                         antialias.MINIFIES, 255, out, out_labels, valid)
    assert torch.equal(out, want) and torch.equal(valid, seen)
    assert 0.2 < float(seen.float().mean()) < 1
    if labels is not None:
        ids, seen_ids = fast.sample_image(labels.unsqueeze(1), rays, rot, k, "nearest",
                                          valid=ok, fill=255, out_dtype=torch.int64)
        assert torch.equal(out_labels, ids[:, 0]) and torch.equal(seen_ids, seen)
        # labels alone: their validity written
        fast.reproject_image(None, labels, affine, limits, table, rot, k, True, 0.0, 255,
                             None, out_labels, valid.fill_(False))
        assert torch.equal(out_labels, ids[:, 0]) and torch.equal(valid, seen)


def test_reproject_image_arguments():
    """``fast.reproject_image`` names the argument that is not as documented."""
    image = torch.zeros(2, 3, 16, 16, dtype=torch.uint8)
    labels = torch.zeros(2, 16, 16, dtype=torch.int64)
    cams = torch.tensor([[4.0, 4.0, 3.0, 2.0], [3.0, 3.5, 3.5, 2.5]], dtype=torch.float64)
    affine, limits, table = (t.float() for t in ot.render.kernels.camera.radial_table(
        "equidistant", cams, (5, 7), entries=16))
    rot, k = torch.eye(3).expand(2, 3, 3), torch.tensor([[9.0, 9.5, 7.5, 7.0]])
    out, ids = torch.zeros(2, 3, 5, 7, dtype=torch.uint8), torch.zeros(2, 5, 7, dtype=torch.int64)
    valid = torch.zeros(2, 5, 7, dtype=torch.bool)
    args = [image, labels, affine, limits, table, rot, k, True, 1.001, 255, out, ids, valid]
    fast.reproject_image(*args)
    assert bool(valid.any())
    for at, value, error, match in [
            (0, image.half(), TypeError, "image: expected one of"),
            (1, labels.int(), ValueError, "labels: expected uint8 or int64"),
            (2, affine.double(), ValueError, r"affine: expected torch.float32 \(B, 6\) \(B = 2"),
            (4, table[0], ValueError, r"table: expected .* \(1 or B, 2, K\)"),
            (5, rot[:, :2], ValueError, r"rotation: expected .* \(1 or B, 3, 3\)"),
            (6, k.double(), ValueError, "intrinsics: expected torch.float32"),
            (8, -1.0, ValueError, "minifies: expected a threshold"),
            (9, 1.5, TypeError, "fill: expected an int"),
            (10, out.long(), TypeError, "out_dtype: expected one of"),
            (11, None, ValueError, "out, out_labels: expected"),
            (12, valid.float(), ValueError, "valid: expected a contiguous bool")]:
        bad = list(args)
        bad[at] = value
        with pytest.raises(error, match=match):
            fast.reproject_image(*bad)
    with pytest.raises(ValueError, match="image, labels: pass at least one"):
        fast.reproject_image(None, None, *args[2:10], None, None, valid)
