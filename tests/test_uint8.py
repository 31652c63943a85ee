"""8-bit, half-precision and channels-last images through ``OmniProjection`` (issue 16).

The oracle of a ``uint8`` render is the same layer on the same cube converted to float32 (levels
0..255), rounded to nearest: the ``uint8`` image must equal it, except next to a rounding tie,
where the two may land on either side (one level apart), on every pixel (valid and invalid),
for every interpolation, border, supersampling, camera model and attitude, on the fast and the
reference path. ``out_dtype=torch.float32`` is that float path divided by 255; half precision is
the float32 path rounded once; a channels-last cube gives the same values as a channels-first
one. The C++ kernel's SSE path for 8-bit channels-last texels of 3 or 4 channels (4-byte loads
and stores) is checked against its scalar path on row segments of odd lengths, next to the end
of the cube, and into outputs whose pixels are wider than their channels.
"""

from __future__ import annotations

import math

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cubemap as cm
from omniscape_torch.cameras import presets
from omniscape_torch.render.kernels import cube as fastsample
from omniscape_torch.render import layer as projection

from test_fastpath import assert_rounded, make_grid, reference
from test_projection import edge_distance, ref_face_uv

u8, f16, bf16, f32, f64 = torch.uint8, torch.float16, torch.bfloat16, torch.float32, torch.float64
F = 8   # texels per face side
# The 8-bit oracle is ``test_fastpath.assert_rounded``: the float image rounded, one level off
# at most within ``TIE`` (1e-3 levels) of a tie; supersampled 8-bit images, averaged in [0, 1]
# before they are rounded, are as close.
#: float32 images of 8-bit cubes against the float path / 255: a few ulps of 1.
ATOL_SCALED = 1e-6
#: Mantissa bits of the half-precision dtypes (their ulp at x: 2 ** (floor(log2 |x|) - bits)).
MANTISSA = {f16: 10, bf16: 7}


# ------------------------------------------------------------------------------------------
# Cubes, cameras, attitudes
# ------------------------------------------------------------------------------------------
def random_cube(batch: int, channels: int, seed: int = 0, size: int = F) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (batch, 6, channels, size, size), generator=gen, dtype=u8)


def checker_cube(batch: int, channels: int, size: int = F) -> torch.Tensor:
    """0 / 255 texels in a checkerboard (the phase flips per face, channel and sample): every
    bilinear blend spans the whole range, the worst case for rounding and saturation."""
    i = torch.arange(size)
    parity = (i[:, None] + i[None, :]) % 2
    phase = (torch.arange(batch)[:, None, None] + torch.arange(6)[None, :, None]
             + torch.arange(channels)[None, None, :]) % 2
    return ((parity + phase[..., None, None]) % 2 * 255).to(u8)


CUBES = {"random": random_cube, "checker": lambda b, c: checker_cube(b, c)}


def camera(name: str) -> ot.Camera:
    """Small cameras of odd sizes (row segments end on odd pixels), float32 parameters (the
    fast path computes the grid from the rays) or float64 ones (a grid is built first)."""
    if name == "equidistant":
        return presets.fisheye((37, 45))
    if name == "equidistant64":
        return presets.fisheye((33, 37), fov=math.radians(200), dtype=f64)
    if name == "unified":   # a catadioptric camera with its blind centre
        return presets.catadioptric((41, 39))[0]
    if name == "eucm":
        return presets.fisheye((35, 35), model="eucm")
    raise ValueError(name)


MODELS = ("equidistant", "equidistant64", "unified", "eucm")


def random_rotations(batch: int, seed: int = 11) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(batch, 3, 3, generator=gen, dtype=f64))
    return (q * torch.linalg.det(q)[:, None, None]).float()   # proper rotations


def looking_at(direction) -> torch.Tensor:
    """``(3, 3)`` proper rotation whose optical axis (camera +z) points along ``direction``
    in the cube frame."""
    z = torch.tensor(direction, dtype=f64)
    z = z / z.norm()
    helper = torch.tensor([0.3, 1.0, 0.2], dtype=f64)
    x = torch.linalg.cross(helper, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return torch.stack((x, y, z), 1).float()


def render(layer: ot.OmniProjection, **kwargs) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        return layer.render(**kwargs)


def ulp(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """The spacing of ``dtype`` at the magnitude of ``x`` (float64)."""
    tiny = torch.finfo(dtype).smallest_normal
    mag = x.double().abs().clamp(min=tiny)
    return torch.exp2(torch.floor(torch.log2(mag)) - MANTISSA[dtype])


# ------------------------------------------------------------------------------------------
# 1. uint8 in, uint8 out: the float path rounded, everywhere
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("interpolation", ["nearest", "bilinear", "bicubic"])
@pytest.mark.parametrize("model", MODELS)
def test_uint8_is_the_rounded_float_path(model, interpolation, fast, rotated):
    layer = ot.OmniProjection(camera(model), F, interpolation=interpolation, fast=fast,
                              fused_grid=False)
    rotation = random_rotations(2) if rotated else None
    for kind, make in CUBES.items():
        cube = make(2, 3)
        got = render(layer, rgb=cube, rotation=rotation)
        ref = render(layer, rgb=cube.float(), rotation=rotation)
        assert torch.equal(got["valid"], ref["valid"])
        valid = got["valid"]
        assert bool(valid.any()) and not bool(valid.all())   # the fov edge (or blind disc)
        assert_rounded(got["rgb"], ref["rgb"], f"{model} {interpolation} {kind}")
        assert bool((got["rgb"].masked_select(~valid) == 0).all())
        # not a trivial image: random texels, or blends of a checkerboard, give many levels
        levels = got["rgb"][valid.expand_as(got["rgb"])].unique().numel()
        assert levels > 20 or (interpolation == "nearest" and kind == "checker")


@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("border,supersample,channels", [
    ("resampled", 1, 1), ("resampled", 2, 3), ("copied", 1, 4), ("copied", 2, 1),
    ("none", 1, 3), ("none", 2, 4), ("resampled", 1, 5), ("resampled", 2, 2)])
@pytest.mark.parametrize("rotated", [False, True])
def test_uint8_borders_and_supersampling(border, supersample, channels, fast, rotated):
    layer = ot.OmniProjection(camera("equidistant"), F, border=border, supersample=supersample,
                              fast=fast, fused_grid=False)
    rotation = random_rotations(2, seed=5) if rotated else None
    for kind, make in CUBES.items():
        cube = make(2, channels)
        got = render(layer, rgb=cube, rotation=rotation)
        ref = render(layer, rgb=cube.float(), rotation=rotation)
        assert got["rgb"].shape == (2, channels, 37, 45)
        assert_rounded(got["rgb"], ref["rgb"], f"{border} x{supersample} {kind}")
        # the float32 output of the same cube: the float path / 255, in the same pass
        scaled = render(layer, rgb=cube, rotation=rotation, out_dtype=f32)["rgb"]
        assert scaled.dtype == f32
        torch.testing.assert_close(scaled, ref["rgb"] / 255, atol=ATOL_SCALED, rtol=0)


def test_uint8_rotation_batch_in_chunks(monkeypatch):
    """A float64 camera under a rotation batch: a grid per sample, built a few samples at a
    time (``CHUNK_PIXELS``), 8-bit images written into the batch's outputs."""
    cam = camera("equidistant64")
    monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * 33 * 37)
    cube, rotation = random_cube(5, 3, seed=3), random_rotations(5, seed=2)
    layer = ot.OmniProjection(cam, F, fused_grid=False)
    got = render(layer, rgb=cube, rotation=rotation)
    ref = render(layer, rgb=cube.float(), rotation=rotation)
    assert_rounded(got["rgb"], ref["rgb"], "chunks")
    one = render(layer, rgb=cube[3:4], rotation=rotation[3:4])   # one sample alone: the same
    assert torch.equal(got["rgb"][3:4], one["rgb"])


# ------------------------------------------------------------------------------------------
# 2. uint8 in, float out: the float path / 255
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("interpolation", ["nearest", "bilinear", "bicubic"])
def test_uint8_into_floats_is_scaled_to_unit_range(interpolation, fast, rotated):
    cube = random_cube(2, 3, seed=4)
    layer = ot.OmniProjection(camera("unified"), F, interpolation=interpolation, fast=fast,
                              fused_grid=False)
    rotation = random_rotations(2, seed=8) if rotated else None
    ref = render(layer, rgb=cube.float(), rotation=rotation)["rgb"] / 255
    for out_dtype in (f32, f64, f16):
        got = render(layer, rgb=cube, rotation=rotation, out_dtype=out_dtype)["rgb"]
        assert got.dtype == out_dtype and bool(torch.isfinite(got).all())
        atol = ATOL_SCALED if out_dtype != f16 else 2.0 ** -11   # float16: rounded once more
        torch.testing.assert_close(got.double(), ref.double(), atol=atol, rtol=0)
        if interpolation != "bicubic":   # a convex blend of [0, 1] values (bicubic overshoots)
            assert float(got.min()) >= 0 and float(got.max()) <= 1
    # uint8 out explicitly: the default
    assert torch.equal(render(layer, rgb=cube, rotation=rotation, out_dtype=u8)["rgb"],
                       render(layer, rgb=cube, rotation=rotation)["rgb"])


# ------------------------------------------------------------------------------------------
# 3. Channels-last cubes and images
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [u8, f32, f16], ids=str)
@pytest.mark.parametrize("channels", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("fast", [True, False])
def test_channels_last_is_channels_first_permuted(dtype, channels, fast):
    cube = random_cube(2, channels, seed=channels)
    cube = cube if dtype == u8 else (cube.float() / 255).to(dtype)
    interleaved = cube.permute(0, 1, 3, 4, 2).contiguous()   # (B, 6, F, F, C)
    layer = ot.OmniProjection(camera("equidistant"), F, fast=fast, fused_grid=False)
    for rotation in (None, random_rotations(2, seed=9)):
        first = render(layer, rgb=cube, rotation=rotation)["rgb"]
        last = render(layer, rgb=interleaved, rotation=rotation, channels_last=True)["rgb"]
        assert last.shape == (2, 37, 45, channels) and last.dtype == dtype
        assert last.is_contiguous()
        assert torch.equal(last, first.permute(0, 2, 3, 1))
        # the same cube in torch's channels-last strides, as (B, 6, C, F, F): the same image
        strided = render(layer, rgb=interleaved.permute(0, 1, 4, 2, 3),
                         rotation=rotation)["rgb"]
        assert strided.shape == first.shape and torch.equal(strided, first)
        if fast and channels > 1:   # sampled without a copy, into channels-last pixels
            assert strided.stride(1) == 1


@pytest.mark.parametrize("view", ["rgba", "every_other_sample"])
@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("fast", [True, False])
def test_channels_last_views_of_larger_tensors(view, rotated, fast):
    """Channels-last cubes that are views, not contiguous in either layout: the RGB of an RGBA
    cube (pixels 4 bytes apart), every other sample of a batch. Any strides are read: the same
    image as the contiguous cube's."""
    if view == "rgba":
        base = random_cube(2, 4, seed=12).permute(0, 1, 3, 4, 2).contiguous()  # (B, 6, F, F, 4)
        cube = base[..., :3]
    else:
        base = random_cube(4, 3, seed=13).permute(0, 1, 3, 4, 2).contiguous()
        cube = base[::2]
    layer = ot.OmniProjection(camera("equidistant"), F, fast=fast, fused_grid=False)
    rotation = random_rotations(2, seed=3) if rotated else None
    before = base.clone()
    expect = render(layer, rgb=cube.contiguous(), rotation=rotation, channels_last=True)["rgb"]
    got = render(layer, rgb=cube, rotation=rotation, channels_last=True)["rgb"]
    assert got.shape == expect.shape == (2, 37, 45, 3) and got.is_contiguous()
    assert torch.equal(got, expect)
    assert torch.equal(base, before)   # the input is only read


# ------------------------------------------------------------------------------------------
# The kernel's 8-bit channels-last path (4-byte loads and stores) against its scalar path
# ------------------------------------------------------------------------------------------
def kernel_grid(width: int, seed: int = 1) -> torch.Tensor:
    """``(1, 6, width, 2)`` atlas grid of an 8-texel, pad-1 atlas: random points over the atlas
    and beyond, invalid points, texel centres and seams (``test_fastpath.make_grid``), and a row
    of points whose bilinear taps end at the last texels of the last face (the end of a sample;
    of the cube for the last one, where a 4-byte load of 3 channels would read past it, so the
    kernel must take its scalar path there)."""
    grid = make_grid(1, f32, seed=seed, h=6, w=width)
    n = F + 2
    x = torch.linspace(n - 3.0, n - 2.0, width)        # atlas pixels: the last interior taps
    y = 5 * n + torch.linspace(n - 3.0, n - 2.0, width).flip(0)
    grid[0, 5, :, 0] = (2 * x + 1) / n - 1
    grid[0, 5, :, 1] = (2 * y + 1) / (6 * n) - 1
    return grid


def interleave(cube: torch.Tensor) -> torch.Tensor:
    """``cube (B, 6, C, F, F)`` as a view of a ``(B, 6, F, F, C)`` tensor (channels innermost)."""
    return cube.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3)


@pytest.mark.parametrize("channels", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("width", [37, 131])   # segments of 64 pixels: 37; 64 + 64 + 3
@pytest.mark.parametrize("out_dtype", [u8, f32], ids=str)
def test_kernel_channels_last_uint8(channels, width, out_dtype):
    grid = kernel_grid(width)
    lut = fastsample.build_lut(grid, F, 1, channels=channels, channels_last=True)
    # the row of points placed there reads the last face's last texels as interior taps
    assert int((lut.base.view(6, width)[5] >= 0).sum()) > width // 2
    for kind, make in CUBES.items():
        cube = make(2, channels)
        planes = fastsample.sample_cube(cube, grid, pad=1, out_dtype=out_dtype)   # scalar path
        ref = reference(cm.cubemap_to_atlas(cube.float(), 1), grid, "bilinear")
        for table in (None, lut):
            got = fastsample.sample_cube(interleave(cube), grid, pad=1, out_dtype=out_dtype,
                                         lut=table)
            assert got.dtype == out_dtype and got.shape == (2, channels, 6, width)
            if channels > 1:
                assert got.stride(1) == 1 and got.permute(0, 2, 3, 1).is_contiguous()
            assert torch.equal(got, planes), (kind, table is not None)
            if out_dtype == u8:
                assert_rounded(got, ref, f"kernel {kind}")
            else:
                torch.testing.assert_close(got, ref / 255, atol=ATOL_SCALED, rtol=0)


@pytest.mark.parametrize("channels", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("out_dtype", [u8, f32], ids=str)
@pytest.mark.parametrize("table", [False, True])
def test_kernel_writes_only_its_pixels_channels(channels, out_dtype, table):
    """Into channels-last pixels wider than the image's channels (the RGB of an RGBA buffer,
    rows of a larger batch): the image's channels are written, nothing else."""
    cube = interleave(random_cube(2, channels, seed=21))
    grid = kernel_grid(131, seed=2)
    lut = fastsample.build_lut(grid, F, 1, channels=channels, channels_last=True) \
        if table else None
    expect = fastsample.sample_cube(cube, grid, pad=1, out_dtype=out_dtype)
    big = torch.full((4, 6, 131, channels + 1), 7, dtype=out_dtype)   # (B, H, W, C + 1)
    out = big[1:3, ..., :channels].permute(0, 3, 1, 2)
    got = fastsample.sample_cube(cube, grid, pad=1, out_dtype=out_dtype, lut=lut, out=out)
    assert got.data_ptr() == big[1].data_ptr()
    assert torch.equal(got, expect)
    extra = big[..., channels]
    assert bool((extra == 7).all()), (
        f"{int((extra != 7).sum())} of {extra.numel()} elements beyond the image's "
        f"{channels} channels overwritten")
    assert bool((big[0] == 7).all()) and bool((big[3] == 7).all())


# ------------------------------------------------------------------------------------------
# 4. Half precision: the float32 path rounded once
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [f16, bf16], ids=str)
@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("interpolation,supersample", [
    ("nearest", 1), ("bilinear", 1), ("bicubic", 1), ("bilinear", 2)])
def test_half_precision_is_the_float32_path_rounded(dtype, rotated, fast, interpolation,
                                                    supersample):
    gen = torch.Generator().manual_seed(6)
    cube = torch.rand(2, 6, 3, F, F, generator=gen).to(dtype)
    layer = ot.OmniProjection(camera("eucm"), F, interpolation=interpolation, fast=fast,
                              supersample=supersample, fused_grid=False)
    rotation = random_rotations(2, seed=4) if rotated else None
    ref = render(layer, rgb=cube.float(), rotation=rotation)["rgb"]   # the same values
    # half an ulp (one rounding) of the float32 path, plus its own float32 rounding
    bound = 0.5 * ulp(ref, dtype) + 1e-6
    for channels_last in (False, True):
        given = cube.permute(0, 1, 3, 4, 2).contiguous() if channels_last else cube
        got = render(layer, rgb=given, rotation=rotation, channels_last=channels_last)["rgb"]
        if channels_last:
            got = got.permute(0, 3, 1, 2)
        assert got.dtype == dtype and got.shape == ref.shape
        assert bool(torch.isfinite(got).all())
        err = (got.double() - ref.double()).abs()
        assert bool((err <= bound).all()), float((err - bound).max())
    # a float32 image of the half cube: no rounding to half at all
    scaled = render(layer, rgb=cube, rotation=rotation, out_dtype=f32)["rgb"]
    assert scaled.dtype == f32
    torch.testing.assert_close(scaled, ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", [f16, bf16, f32], ids=str)
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("interpolation,supersample", [
    ("nearest", 1), ("bilinear", 1), ("bilinear", 2)])
def test_extremes_stay_finite(dtype, fast, interpolation, supersample):
    """Texels at the dtype's largest finite value and 0 in a checkerboard: every blend, and
    every mean of supersamples, is a convex combination, so no pixel may overflow to inf (nor be
    NaN), at seams and corners either. (bfloat16 has float32's range: float32 is checked too.)"""
    big = torch.finfo(dtype).max
    cube = (checker_cube(1, 3).float() / 255 * big).to(dtype)
    assert bool(torch.isfinite(cube).all()) and float(cube.max()) == big
    layer = ot.OmniProjection(presets.fisheye((33, 33), fov=math.radians(120)), F,
                              interpolation=interpolation, supersample=supersample, fast=fast,
                              fused_grid=False)
    for rotation in (None, looking_at((1, 1, 1)), looking_at((-1, 0, 1))):
        image = render(layer, rgb=cube, rotation=rotation)["rgb"]
        assert image.dtype == dtype
        bad = ~torch.isfinite(image)
        assert not bool(bad.any()), f"{int(bad.sum())} pixels not finite"
        assert float(image.max()) <= big and float(image.min()) >= 0


# ------------------------------------------------------------------------------------------
# 5. render(out=...): 8-bit and channels-last images into rows of larger outputs
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("out_dtype", [None, f32], ids=str)
@pytest.mark.parametrize("attitude", ["none", "batch", "chunks"])
def test_render_into_rows_of_larger_outputs(monkeypatch, channels_last, out_dtype, attitude):
    cam = camera("equidistant64" if attitude == "chunks" else "equidistant")
    h, w = cam.image_size
    if attitude == "chunks":   # a grid per sample, two samples at a time
        monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * h * w)
    layer = ot.OmniProjection(cam, F, fused_grid=False)
    cube = random_cube(5, 3, seed=7)
    labels = (random_cube(5, 1, seed=8)[:, :, 0] % 13).long()
    rotation = None if attitude == "none" else random_rotations(5, seed=6)
    rgb = cube.permute(0, 1, 3, 4, 2).contiguous() if channels_last else cube
    kwargs = dict(rgb=rgb, labels=labels, rotation=rotation, out_dtype=out_dtype,
                  channels_last=channels_last)
    dtype = u8 if out_dtype is None else out_dtype
    shape = (7, h, w, 3) if channels_last else (7, 3, h, w)
    big = {"rgb": torch.full(shape, 7, dtype=dtype),
           "labels": torch.full((7, h, w), 7, dtype=torch.int64),
           "valid": torch.zeros(7, 1, h, w, dtype=torch.bool)}
    expect = render(layer, **kwargs)
    got = render(layer, **kwargs, out={key: value[1:6] for key, value in big.items()})
    assert set(got) == set(expect) == set(big)
    for key, value in expect.items():
        assert got[key].dtype == value.dtype and got[key].shape == value.shape, key
        assert torch.equal(got[key], value), key
        assert got[key].data_ptr() == big[key][1].data_ptr(), key
    for key, value in big.items():   # the rows outside untouched
        assert torch.equal(value[0], torch.full_like(value[0], 7 if key != "valid" else 0)), key
        assert torch.equal(value[6], value[0]), key
    assert_rounded(expect["rgb"] if out_dtype is None else
                   torch.floor(expect["rgb"].double() * 255 + 0.5).to(u8),
                   render(layer, rgb=rgb.float(), rotation=rotation,
                          channels_last=channels_last)["rgb"], "out")


# ------------------------------------------------------------------------------------------
# 6. Bad input
# ------------------------------------------------------------------------------------------
def test_uint8_cube_refuses_gradients():
    """No gradient flows through 8-bit texels: a camera or attitude that asks for one is
    refused, naming rgb; without grad mode the same call renders."""
    cube = random_cube(1, 3)
    learnable = presets.fisheye((17, 17))
    learnable = ot.Camera("equidistant", learnable.params.clone(), (17, 17),
                          fov=math.radians(190), learnable=True)
    layer = ot.OmniProjection(learnable, F, fused_grid=False)
    with pytest.raises(TypeError, match="rgb"):
        layer.render(rgb=cube)
    with pytest.raises(TypeError, match="rgb"):
        layer(cube)
    rotation = random_rotations(1).requires_grad_(True)
    frozen = ot.OmniProjection(presets.fisheye((17, 17)), F, fused_grid=False)
    with pytest.raises(TypeError, match="rgb"):
        frozen.render(rgb=cube, rotation=rotation)
    with torch.no_grad():
        image = layer.render(rgb=cube)["rgb"]
        assert image.dtype == u8
        assert image.shape == (1, 3, 17, 17)
        frozen.render(rgb=cube, rotation=rotation)
    # a float cube of the same levels differentiates, and rounds to the same image
    out = layer.render(rgb=cube.float())["rgb"]
    assert out.requires_grad
    assert_rounded(image, out.detach(), "learnable")
    # labels of 8 bits with a learnable camera: no gradient asked of them, no error
    ids = layer.render(labels=cube[:, :, 0])["labels"]
    with torch.no_grad():
        assert torch.equal(ids, layer.render(labels=cube[:, :, 0])["labels"])


@pytest.mark.parametrize("rgb,out_dtype", [
    (random_cube(1, 3), torch.int32), (random_cube(1, 3), torch.int8),
    (random_cube(1, 3), torch.bool), (random_cube(1, 3), "float32"),
    (random_cube(1, 3), float), (torch.rand(1, 6, 3, F, F), u8),
    (torch.rand(1, 6, 3, F, F), torch.int64)])
def test_bad_out_dtype(rgb, out_dtype):
    layer = ot.OmniProjection(presets.fisheye((9, 9)), F)
    with pytest.raises(TypeError, match="out_dtype"):
        layer.render(rgb=rgb, out_dtype=out_dtype)
    with pytest.raises(TypeError, match="out_dtype"):
        layer(rgb, out_dtype=out_dtype)


@pytest.mark.parametrize("rgb,error,match", [
    (random_cube(1, 3), ValueError, "rgb"),                            # (B, 6, C, F, F)
    (random_cube(1, 3)[:, :, 0], ValueError, "rgb"),                   # 4 dims
    (torch.zeros(1, 6, F, F + 1, 3, dtype=u8), ValueError, "rgb"),     # not square
    (torch.zeros(1, 5, F, F, 3, dtype=u8), ValueError, "rgb"),         # 5 faces
    (torch.zeros(1, 6, 4, 4, 3, dtype=u8), ValueError, "face_size"),   # another face size
    (torch.zeros(1, 6, F, F, 3, dtype=torch.int16), TypeError, "rgb"),
])
def test_bad_channels_last_input(rgb, error, match):
    layer = ot.OmniProjection(presets.fisheye((9, 9)), F)
    with pytest.raises(error, match=match):
        layer.render(rgb=rgb, channels_last=True)


@pytest.mark.parametrize("channels_last", [False, True])
def test_bad_out_tensors(channels_last):
    layer = ot.OmniProjection(presets.fisheye((9, 11)), F)
    cube = random_cube(2, 3)
    rgb = cube.permute(0, 1, 3, 4, 2).contiguous() if channels_last else cube
    good = (2, 9, 11, 3) if channels_last else (2, 3, 9, 11)
    other = (2, 3, 9, 11) if channels_last else (2, 9, 11, 3)
    bad = [torch.zeros(good, dtype=f32),                  # the float dtype for a uint8 image
           torch.zeros(other, dtype=u8),                  # the other layout's shape
           torch.zeros((3, *good[1:]), dtype=u8),         # another batch
           torch.zeros(good, dtype=u8)[..., :-1]]         # one short on the last axis
    with torch.no_grad():
        for given in bad:
            with pytest.raises(ValueError, match=r"out\['rgb'\]"):
                layer.render(rgb=rgb, channels_last=channels_last, out={"rgb": given})
        with pytest.raises(ValueError, match=r"out\['rgb'\]"):   # float32 asked, uint8 given
            layer.render(rgb=rgb, channels_last=channels_last, out_dtype=f32,
                         out={"rgb": torch.zeros(good, dtype=u8)})
        with pytest.raises(ValueError, match=r"out\['labels'\]"):
            layer.render(labels=cube[:, :, 0], out={"labels": torch.zeros(2, 9, 11, dtype=u8)})


# ------------------------------------------------------------------------------------------
# 7. Seams and corners: every pixel next to one
# ------------------------------------------------------------------------------------------
#: Optical axes through a cube corner (three faces meet; (1, 1, 1) involves the last face,
#: "down", whose last texels end the cube in memory) and an edge's midpoint.
AXES = {"corner_down_right_front": (1.0, 1.0, 1.0), "corner_up_left_back": (-1.0, -1.0, -1.0),
        "edge_down_back": (0.0, 1.0, -1.0)}


@pytest.mark.parametrize("axis", list(AXES))
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("interpolation", ["nearest", "bilinear"])
@pytest.mark.parametrize("border", ["resampled", "copied"])
def test_uint8_at_seams_and_corners(axis, fast, interpolation, border):
    """A narrow pinhole looking at a cube corner or edge: its rays all land within a few texels
    of a seam (the edge pixels, which read the border ring). The 8-bit image is the rounded
    float image there too, channels-first or channels-last (the 4-byte path)."""
    size = 31
    focal = (size / 2) / math.tan(math.radians(25))   # 50 degrees across
    c = (size - 1) / 2
    cam = ot.Camera("pinhole", torch.tensor([focal, focal, c, c]), (size, size))
    rotation = looking_at(AXES[axis])
    layer = ot.OmniProjection(cam, F, interpolation=interpolation, fast=fast, border=border,
                              fused_grid=False)
    cube = random_cube(2, 3, seed=17)
    # the oracle's own rays and faces: most pixels within a texel of a seam
    v, u = torch.meshgrid(torch.arange(size, dtype=f64), torch.arange(size, dtype=f64),
                          indexing="ij")
    rays = torch.stack(((u - c) / focal, (v - c) / focal, torch.ones_like(u)), -1)
    _, uv = ref_face_uv(rays @ rotation.double().T, F)
    near = edge_distance(uv, F) < 1.0
    assert float(near.double().mean()) > 0.3
    ref = render(layer, rgb=cube.float(), rotation=rotation)["rgb"]
    for channels_last in (False, True):
        rgb = cube.permute(0, 1, 3, 4, 2).contiguous() if channels_last else cube
        out = render(layer, rgb=rgb, rotation=rotation, channels_last=channels_last)
        image = out["rgb"].permute(0, 3, 1, 2) if channels_last else out["rgb"]
        assert bool(out["valid"].all())
        assert_rounded(image, ref, f"{axis} channels_last={channels_last}")
        if interpolation == "bilinear":   # the pixels next to a seam: blends of several texels
            assert image[..., near].unique().numel() > 50
        # a rotation batch, one attitude per sample: the same per sample
        both = render(layer, rgb=rgb, rotation=torch.stack((rotation, rotation)),
                      channels_last=channels_last)
        assert torch.equal(both["rgb"], out["rgb"])


# ------------------------------------------------------------------------------------------
# 8. Labels of 8 bits: exact, the ignore index outside
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("supersample", [1, 2])
@pytest.mark.parametrize("model", ["equidistant64", "unified"])
def test_uint8_labels_equal_int64_labels(rotated, fast, supersample, model):
    """8-bit ids (every id but 255, the ignore index) give the ids of the same cube in int64,
    exactly, and 255 outside: through a cached grid or a rotation batch, beside an 8-bit image,
    channels-first or channels-last, and at a corner of the cube."""
    gen = torch.Generator().manual_seed(19)
    ids = torch.randint(0, 255, (2, 6, F, F), generator=gen).to(u8)
    layer = ot.OmniProjection(camera(model), F, supersample=supersample, fast=fast,
                              fused_grid=False)
    rgb = random_cube(2, 3)
    for rotation in (random_rotations(2, seed=1) if rotated else None,
                     looking_at((1.0, 1.0, 1.0))):
        wide = render(layer, labels=ids.long(), rotation=rotation)
        for channels_last in (False, True):
            small = render(layer, labels=ids, rotation=rotation, channels_last=channels_last,
                           rgb=rgb.permute(0, 1, 3, 4, 2).contiguous() if channels_last else rgb)
            labels, valid = small["labels"].long(), small["valid"][:, 0]
            assert torch.equal(small["valid"], wide["valid"])
            assert torch.equal(labels, wide["labels"])
            assert bool((labels[~valid] == 255).all())
            assert bool((labels[valid] < 255).all())
        assert bool(valid.any()) and not bool(valid.all())   # the fov edge is in
        # nearest: every valid pixel carries an id of the cube, and many different ones
        assert set(labels[valid].unique().tolist()) <= set(ids.unique().tolist())
        assert labels[valid].unique().numel() > 30


@pytest.mark.parametrize("ignore_index", [255, -1, 1000])
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("rotated", [False, True])
def test_uint8_labels_come_back_int64(ignore_index, fast, rotated):
    """``render``'s labels are int64 whatever the ids' integer dtype (its docstring, and the
    dtype ``out['labels']`` must have): an ignore index that uint8 cannot hold (-1, 1000) is
    written as itself, neither wrapped (-1 -> 255) nor refused; allocated or given, the same."""
    gen = torch.Generator().manual_seed(23)
    ids = torch.randint(0, 255, (2, 6, F, F), generator=gen).to(u8)
    layer = ot.OmniProjection(camera("equidistant"), F, fast=fast, ignore_index=ignore_index,
                              fused_grid=False)
    rotation = random_rotations(2, seed=2) if rotated else None
    wide = render(layer, labels=ids.long(), rotation=rotation)
    valid = wide["valid"][:, 0]
    assert bool((wide["labels"][~valid] == ignore_index).all()) and bool((~valid).any())
    small = render(layer, labels=ids, rotation=rotation)
    assert small["labels"].dtype == torch.int64, small["labels"].dtype
    assert torch.equal(small["labels"], wide["labels"])
    given = torch.full((4, 37, 45), 7, dtype=torch.int64)
    into = render(layer, labels=ids, rotation=rotation, out={"labels": given[1:3]})
    assert torch.equal(into["labels"], wide["labels"])
    assert bool((given[0] == 7).all()) and bool((given[3] == 7).all())
