"""The CPU fast path (``omniscape_torch.render.fast``) against the reference path (``grid_sample``).

Every fast path must give ``F.grid_sample(atlas, grid, align_corners=False)``'s output to
float32 rounding: ``sample_cube`` (no atlas), ``sample_atlas``, the lookup table of a frozen
camera, and ``OmniProjection`` with ``fast=True`` (against ``fast=False``) for RGB, depth and
labels, with and without rotations, and without a C++ compiler (the layer's reference path);
gradients still come from ``grid_sample``.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F_nn

import omniscape_torch as ot
from omniscape_torch import cubemap as cm
from omniscape_torch.cubemap import grid as fastgrid
from omniscape_torch.render import kernels
from omniscape_torch.render.kernels import build as extension, cube as fastsample

f32, f64 = torch.float32, torch.float64
#: Rounding of a blend of 4 texels in [0, 1]. float32: the weights are grid_sample's bit for bit,
#: the sums may be rounded in another order (grid_sample uses fused multiply-adds): a few ulps.
#: float64: the pixel coordinate ``fma(g + 1, n / 2, -0.5)`` is rounded twice (nothing wider to
#: emulate the fma in): one ulp of a coordinate below 128 (the test atlases) moves the blend by
#: up to 128 eps.
ATOL = {f32: 4 * torch.finfo(f32).eps, f64: 128 * torch.finfo(f64).eps}


def grid_rounding(face_size: int, pad: int, dtype=f32) -> float:
    """Texels by which a normalised grid point of the atlas (``6 n`` rows for ``2`` units of
    the grid, ``n = F + 2 pad``) may miss the atlas pixel it was made from: an ulp of a grid
    coordinate in ``[-1, 1]`` (at most eps) is ``3 n`` eps rows. ``fast.sample_rays`` computes
    bilinear taps from the atlas pixel directly, so it differs from the image of the grid by up
    to this much of a texel step (and lies closer to the exact image:
    ``test_sample_rays_is_closer_to_the_exact_image_than_the_grid``)."""
    return 3 * (face_size + 2 * pad) * torch.finfo(dtype).eps


def make_cube(batch: int, channels: int, size: int, dtype=f32, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 6, channels, size, size, generator=gen, dtype=dtype)


def make_grid(batch: int, dtype=f32, seed: int = 1, h: int = 23, w: int = 17) -> torch.Tensor:
    """Atlas grid over the whole atlas and a little beyond, with some invalid pixels (-2, -2)
    and exact texel centres and seams of an 8-texel, pad-1 atlas (ties for nearest)."""
    gen = torch.Generator().manual_seed(seed)
    grid = torch.rand(batch, h, w, 2, generator=gen, dtype=dtype) * 2.3 - 1.15
    grid[:, ::5, ::3] = -2.0
    n = 10  # 8 + 2 * 1
    grid[:, 1, :n, 0] = (2 * torch.arange(n, dtype=dtype) + 1) / n - 1  # texel centres
    grid[:, 2, :n, 1] = (2 * torch.arange(n, dtype=dtype) * 6) / (6 * n) - 1  # face seams
    return grid


def reference(atlas: torch.Tensor, grid: torch.Tensor, mode: str) -> torch.Tensor:
    return F_nn.grid_sample(atlas, grid.expand(atlas.shape[0], -1, -1, -1), mode=mode,
                            padding_mode="zeros", align_corners=False)


def copied_atlas(cube: torch.Tensor, pad: int) -> torch.Tensor:
    """The naive atlas: every face padded with its own edge texels."""
    f = cube.shape[-1]
    idx = (torch.arange(f + 2 * pad) - pad).clamp(0, f - 1)
    return cm.faces_to_atlas(cube[..., idx, :][..., idx])


#: Width (in levels) of the band around a rounding tie (x.5) where an 8-bit image may differ by
#: one level from the rounded float image: both blend the same float32 numbers (levels are exact
#: in float32) with the same weights, in another order or with fused multiply-adds, a few ulps
#: of 255 (1.5e-5 each) apart.
TIE = 1e-3


def assert_rounded(got: torch.Tensor, ref: torch.Tensor, what: str = "") -> None:
    """``got`` (uint8) is ``ref`` (float levels) rounded to nearest and saturated, except within
    ``TIE`` of a tie, where it may be one level off."""
    assert got.dtype == torch.uint8 and got.shape == ref.shape, (got.dtype, got.shape, ref.shape)
    assert bool(torch.isfinite(ref).all())
    levels = ref.double().clamp(0, 255)
    diff = got.double() - torch.floor(levels + 0.5)
    near_tie = (levels - torch.floor(levels) - 0.5).abs() <= TIE
    wrong = (diff != 0) & ~near_tie | (diff.abs() > 1)
    assert not bool(wrong.any()), (
        f"{what}: {int(wrong.sum())} of {wrong.numel()} pixels not the rounded float image, "
        f"e.g. at {tuple(torch.nonzero(wrong)[0].tolist())}: got "
        f"{int(got[wrong][0])}, float {float(ref[wrong][0]):.6f}")


# ------------------------------------------------------------------------------------------
# sample_cube / sample_atlas against grid_sample on the atlas
# ------------------------------------------------------------------------------------------
#: size, pad, channels, batch, grid batch, border of the cubes sampled against grid_sample
CUBE_CASES = [
    (8, 1, 3, 2, 1, "bilinear"),  # one grid for the batch (a frozen camera)
    (7, 2, 1, 2, 2, "nearest"),  # odd size, pad 2, a grid per sample
    (5, 1, 5, 1, 1, "copied"),  # 5 channels, each face padded with its own texels
    (6, 0, 2, 1, 1, "bilinear"),  # no border: taps across the stacked faces
]


@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
@pytest.mark.parametrize("dtype", [f32, f64])
@pytest.mark.parametrize("size,pad,channels,batch,grid_batch,border", CUBE_CASES)
def test_sample_cube_equals_grid_sample(mode, dtype, size, pad, channels, batch, grid_batch,
                                        border):
    cube = make_cube(batch, channels, size, dtype)
    grid = make_grid(grid_batch, dtype)
    if border == "copied":
        atlas = copied_atlas(cube, pad)
    else:
        atlas = cm.cubemap_to_atlas(cube, pad, border) if pad else cm.faces_to_atlas(cube)
    expect = reference(atlas, grid, mode)
    lut = fastsample.build_lut(grid, size, pad, mode, channels=channels)
    for got in (fastsample.sample_cube(cube, grid, mode, pad=pad, border=border),
                fastsample.sample_cube(cube, grid, mode, pad=pad, border=border, lut=lut)):
        assert got.shape == expect.shape and got.dtype == dtype
        torch.testing.assert_close(got, expect, atol=ATOL[dtype], rtol=0)
    invalid = (grid[..., 0] == -2).expand(batch, -1, -1)
    assert bool(invalid.any()) and bool((got.permute(0, 2, 3, 1)[invalid] == 0).all())
    assert bool((lut.base == -2).any()) or pad == 0  # the seam pixels were exercised


@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("size,pad,channels,batch,grid_batch,border", CUBE_CASES + [
    (8, 1, 4, 2, 2, "bilinear"),  # 4 channels (channels-last: one 4-byte load per texel)
])
def test_sample_cube_of_uint8_is_the_rounded_grid_sample(mode, channels_last, size, pad,
                                                         channels, batch, grid_batch, border):
    """An 8-bit cube (channels-first or channels-last), seams and texel centres included: the
    float cube's image rounded to nearest, one level off at most next to a tie; its float32
    output that image / 255."""
    gen = torch.Generator().manual_seed(4)
    cube = torch.randint(0, 256, (batch, 6, channels, size, size), generator=gen,
                         dtype=torch.uint8)
    grid = make_grid(grid_batch)
    if border == "copied":
        atlas = copied_atlas(cube.float(), pad)
    else:
        atlas = cm.cubemap_to_atlas(cube.float(), pad, border) if pad else \
            cm.faces_to_atlas(cube.float())
    expect = reference(atlas, grid, mode)
    given = cube.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3) \
        if channels_last else cube
    lut = fastsample.build_lut(grid, size, pad, mode, channels=channels,
                               channels_last=channels_last)
    for table in (None, lut):
        got = fastsample.sample_cube(given, grid, mode, pad=pad, border=border, lut=table)
        assert_rounded(got, expect, f"{mode} {border} table={table is not None}")
        scaled = fastsample.sample_cube(given, grid, mode, pad=pad, border=border, lut=table,
                                        out_dtype=f32)
        torch.testing.assert_close(scaled, expect / 255, atol=1e-6, rtol=0)
        if channels_last and channels > 1:   # the image in the cube's layout
            assert got.stride(1) == 1 and scaled.stride(1) == 1
    assert bool((lut.base == -2).any()) or pad == 0  # the seam pixels were exercised


def test_lookup_table_entries_and_another_grid_dtype():
    """A table's entries hold the codes and the fractions of the grid points; one built from a
    float64 grid samples a float32 cube too (its fractions converted)."""
    cube, grid = make_cube(2, 3, 8), make_grid(1, f64)
    lut = fastsample.build_lut(grid, 8, 1, channels=3)
    assert lut.table.dtype == torch.int64 and lut.table.shape == (1, 23 * 17, 3)
    n = 10   # 8 + 2 * 1
    x = ((grid[..., 0] + 1) * n - 1) / 2   # atlas pixels, align_corners=False
    y = ((grid[..., 1] + 1) * 6 * n - 1) / 2
    torch.testing.assert_close(lut.frac, torch.stack((x - x.floor(), y - y.floor())).flatten(2),
                               atol=1e-12, rtol=0)
    interior = ((x >= 1) & (x < n - 2) & (y >= 0) & (y < 6 * n)
                & (y.remainder(n) >= 1) & (y.remainder(n) < n - 2))
    j, i, k = x.floor().long() - 1, y.remainder(n).floor().long() - 1, (y / n).floor().long()
    expect = k * 3 * 64 + i * 8 + j   # face stride C F F, then the texel in the face
    assert torch.equal(lut.base.view(1, 23, 17)[interior], expect[interior])
    # the interior pixels at the table's float64 points, the edge pixels at the float32 grid's:
    # within the float32 rounding of a point (60 atlas pixels: 4e-6 pixel) of the float64 image
    atlas = cm.cubemap_to_atlas(cube.double(), 1)
    torch.testing.assert_close(fastsample.sample_cube(cube, grid, pad=1, lut=lut),
                               reference(atlas, grid, "bilinear").float(), atol=1e-5, rtol=0)


@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
def test_sample_atlas_equals_grid_sample(mode):
    atlas = cm.cubemap_to_atlas(make_cube(2, 3, 9), 1)
    grid = make_grid(2, seed=3)
    torch.testing.assert_close(fastsample.sample_atlas(atlas, grid, mode),
                               reference(atlas, grid, mode), atol=ATOL[f32], rtol=0)


def test_nearest_is_exact_for_integer_labels():
    gen = torch.Generator().manual_seed(5)
    labels = torch.randint(0, 2 ** 40, (2, 6, 1, 8, 8), generator=gen)  # beyond float precision
    grid = make_grid(1, f64)
    atlas = cm.cubemap_to_atlas(labels, 1, "nearest")
    expect = reference(atlas.double(), grid, "nearest")  # exact: ids < 2^53
    lut = fastsample.build_lut(grid, 8, 1, "nearest", channels=1)
    for table in (None, lut):   # the table computed in the pass, or a frozen camera's
        got = fastsample.sample_cube(labels, grid, "nearest", pad=1, border="nearest",
                                     lut=table)
        assert got.dtype == torch.int64
        assert torch.equal(got.double(), expect)
    small = labels.remainder(200).to(torch.uint8)   # the dtype of a label cube on disk
    got = fastsample.sample_cube(small, grid, "nearest", pad=1, border="nearest")
    assert got.dtype == torch.uint8 and torch.equal(got.double(), expect.remainder(200))


def test_half_precision_is_sampled_in_float32():
    cube = make_cube(1, 3, 8).half()
    grid = make_grid(1)
    expect = reference(cm.cubemap_to_atlas(cube.float(), 1), grid, "bilinear").half()
    got = fastsample.sample_cube(cube, grid, pad=1)
    assert got.dtype == torch.float16
    torch.testing.assert_close(got, expect, atol=torch.finfo(torch.float16).eps, rtol=0)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
def test_reference_path_without_a_compiler(monkeypatch, tmp_path, mode):
    """Where the C++ extension cannot be built (here: no compiler, nothing built), the fast
    sampler is unavailable after one warning that says why, and the layer renders through its
    reference path (``grid_sample`` on the padded atlas): ``fast=False``'s images, and the
    fast sampler's to rounding (labels exact)."""
    cube, depth = make_cube(2, 3, 8), 1 + 9 * make_cube(2, 1, 8, seed=2)
    labels = torch.randint(0, 2 ** 40, (2, 6, 1, 8, 8), generator=torch.Generator().manual_seed(2))
    rotation = rotations(2).float()

    def run(fast: bool) -> list[dict]:
        layer = ot.OmniProjection(fisheye(dtype=f32), 8, fast=fast, interpolation=mode,
                                  depth_interpolation=mode)
        with torch.no_grad():
            return [layer.render(rgb=cube, depth=depth, labels=labels),
                    layer.render(rgb=cube, depth=depth, labels=labels, rotation=rotation)]

    compiled = run(True)
    assert kernels.compile_failures() == {} and kernels.available()
    build = extension._build

    def build_without_a_compiler():
        # $CXX names no compiler while the extension is built, and only then: inductor, which
        # compiles the layer's grids, would remember a failure of its own for the process; and
        # an empty cache (a library built there loads without a compiler)
        with monkeypatch.context() as scope:
            scope.setenv("CXX", "no-such-compiler-here")
            scope.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "cache"))
            return build()

    monkeypatch.setattr(extension, "_STATE", {})
    monkeypatch.setattr(extension, "_LOADED", [])   # as in a new process: nothing loaded yet
    monkeypatch.setattr(extension, "_build", build_without_a_compiler)
    with pytest.warns(UserWarning, match="fast sampler is unavailable") as caught:
        without = run(True)
        without += run(True)   # warned once, not per call
    assert sum("fast sampler is unavailable" in str(w.message) for w in caught) == 1
    (key, why), = kernels.compile_failures().items()
    assert key == ("extension", "fastsample") and "no-such-compiler-here" in why
    assert not kernels.available() and kernels.unavailable_reason() == why
    with pytest.raises(RuntimeError, match="backend='cpp', but the C.. kernels are unavailable"):
        fastsample.sample_cube(cube, make_grid(1), mode, pad=1, backend="cpp")
    twin = fastsample.sample_cube(cube, make_grid(1), mode, pad=1)   # "auto": the torch twin
    assert torch.equal(twin, fastsample.sample_cube(cube, make_grid(1), mode, pad=1,
                                                    backend="torch"))
    reference = run(False)
    for k, (got, ref, fast) in enumerate(zip(without, reference * 2, compiled * 2)):
        assert set(got) == set(ref) == set(fast)
        for key in got:   # the reference path itself
            assert torch.equal(got[key], ref[key]), key
        assert torch.equal(got["valid"], fast["valid"])
        assert torch.equal(got["labels"], fast["labels"])   # ids beyond float precision
        rotated = k % 2 == 1 and mode == "bilinear"   # sample_rays: taps from the rays
        for key, span in (("rgb", 1.0), ("depth", 9.0)):   # the values' range
            atol = ATOL[f32] * 10 + (grid_rounding(8, 1) * span if rotated else 0.0)
            torch.testing.assert_close(got[key], fast[key], atol=atol, rtol=0)


def test_out_valid_and_fill():
    """``out`` (rows of a larger batch, any strides between planes), ``valid`` and ``fill``."""
    cube, grid = make_cube(2, 3, 8), make_grid(1)
    expect = fastsample.sample_cube(cube, grid, pad=1)
    big = torch.full((4, 3, *grid.shape[1:3]), 7.0)
    got = fastsample.sample_cube(cube, grid, pad=1, out=big[1:3])
    assert got.data_ptr() == big[1].data_ptr() and torch.equal(got, expect)
    assert bool((big[0] == 7).all()) and bool((big[3] == 7).all())
    planes = torch.zeros(3, 2, *grid.shape[1:3]).permute(1, 0, 2, 3)   # channel-major
    assert torch.equal(fastsample.sample_cube(cube, grid, pad=1, out=planes), expect)
    half = torch.zeros(2, 3, *grid.shape[1:3], dtype=torch.float16)
    fastsample.sample_cube(cube.half(), grid, pad=1, out=half)
    assert torch.equal(half, fastsample.sample_cube(cube.half(), grid, pad=1))
    # the pixels outside the atlas (grid (-2, -2) and a little beyond) and the invalid ones
    # read fill
    outside = (reference(torch.ones(1, 1, 60, 10), grid, "nearest")[0] == 0).expand(2, -1, -1)
    assert bool(outside.any()) and bool((~outside).any())
    labels = torch.randint(0, 9, (2, 6, 1, 8, 8), dtype=torch.uint8)
    ids = fastsample.sample_cube(labels, grid, "nearest", pad=1, border="nearest", fill=255)
    assert bool((ids[:, 0][outside] == 255).all()) and bool((ids[:, 0][~outside] < 9).all())
    valid = ~torch.eye(*grid.shape[1:3], dtype=torch.bool).unsqueeze(0)
    ids = fastsample.sample_cube(labels, grid, "nearest", pad=1, border="nearest", fill=255,
                                 valid=valid)
    assert bool((ids[:, 0][(outside | ~valid)] == 255).all())
    with pytest.raises(ValueError, match="fill: -1 does not fit"):
        fastsample.sample_cube(labels, grid, "nearest", pad=1, fill=-1)
    with pytest.raises(TypeError, match="fill: expected an int"):
        fastsample.sample_cube(cube, grid, pad=1, fill=0.5)
    with pytest.raises(ValueError, match="out: expected shape"):
        fastsample.sample_cube(cube, grid, pad=1, out=big)
    with pytest.raises(TypeError, match="out: expected a CPU tensor of torch.float32"):
        fastsample.sample_cube(cube, grid, pad=1, out=big.double()[:2])
    with pytest.raises(ValueError, match="valid: expected a bool tensor"):
        fastsample.sample_cube(cube, grid, pad=1, valid=valid[..., :-1])
    with pytest.raises(ValueError, match="valid: only without lut"):
        fastsample.sample_cube(cube, grid, pad=1, valid=valid,
                               lut=fastsample.build_lut(grid, 8, 1, channels=3))


def _sample_in_worker(i):
    cube, grid = make_cube(2, 3, 8, seed=i), make_grid(2)
    return fastsample.sample_cube(cube, grid, pad=1)


def test_kernels_run_in_dataloader_workers():
    """The OpenMP kernels, used here first, run again in forked DataLoader workers."""
    expect = [_sample_in_worker(i) for i in range(4)]
    got = list(torch.utils.data.DataLoader(_Samples(), batch_size=None, num_workers=2))
    assert all(torch.equal(a, b) for a, b in zip(got, expect))


class _Samples(torch.utils.data.Dataset):
    def __len__(self):
        return 4

    def __getitem__(self, i):
        return _sample_in_worker(i)


@pytest.mark.parametrize("kwargs,error,match", [
    (dict(grid=torch.zeros(3, 4, 4, 2)), ValueError, "grid: expected shape"),
    (dict(grid=torch.zeros(1, 4, 4, 2, dtype=torch.int64)), TypeError, "grid: expected a float"),
    (dict(mode="cubic"), ValueError, "mode: expected one of"),
    (dict(mode="bicubic", backend="cpp"), ValueError, "mode: 'bicubic' has no C.. op"),
    (dict(border="none"), ValueError, "border: expected one of"),
    (dict(cubemap=torch.zeros(2, 6, 3, 8, 8, dtype=torch.int64)), TypeError, "bilinear"),
    (dict(cubemap=torch.zeros(2, 5, 3, 8, 8)), ValueError, "cubemap must have shape"),
])
def test_bad_input(kwargs, error, match):
    args = dict(cubemap=make_cube(2, 3, 8), grid=make_grid(1), mode="bilinear",
                border="bilinear")
    args.update(kwargs)
    with pytest.raises(error, match=match):
        fastsample.sample_cube(args.pop("cubemap"), args.pop("grid"), args.pop("mode"), pad=1,
                               **args)


def test_lut_of_another_layout_is_refused():
    cube, grid = make_cube(1, 3, 8), make_grid(1)
    lut = fastsample.build_lut(grid, 8, 1, "bilinear", channels=1)
    with pytest.raises(ValueError, match="lut: built for"):
        fastsample.sample_cube(cube, grid, pad=1, lut=lut)


# ------------------------------------------------------------------------------------------
# sample_rays: the grid of rotated rays computed in the sampling pass
# ------------------------------------------------------------------------------------------
def make_rays(batch: int, dtype=f32, seed: int = 4, h: int = 23, w: int = 17) -> torch.Tensor:
    """Rays in every direction, with the face axes, exact ties between components (the face
    choice's tie-breaking) and the zero ray."""
    gen = torch.Generator().manual_seed(seed)
    rays = torch.randn(batch, h, w, 3, generator=gen, dtype=dtype)
    special = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                            [0, 0, 0], [1, 1, 0], [1, -1, 1], [-1, -1, -1], [0, -0.5, 0.5],
                            [-0.0, 0, 0], [0.3, 0.3, -0.3]], dtype=dtype)
    rays[:, 0, :len(special)] = special[:w]
    return rays


def spec_grid(rays: torch.Tensor, rotation, size: int, pad: int, dtype) -> torch.Tensor:
    """fastgrid's fused maths run eagerly: the operations the kernel must reproduce."""
    rays = rays if rays.dim() == 4 else rays.unsqueeze(0)
    if rotation is None:
        return fastgrid._fused_plain(rays, size, pad, dtype)
    rotation = rotation if rotation.dim() == 3 else rotation.unsqueeze(0)
    return fastgrid._fused_rotated(rays, rotation, size, pad, dtype)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
@pytest.mark.parametrize("dtype", [f32, f64])
@pytest.mark.parametrize("ray_batch,rot_batch,pad,border", [
    (1, 2, 1, "bilinear"),   # one camera, a rotation per sample
    (2, 1, 2, "nearest"),    # a camera per sample, one rotation
    (2, None, 1, "copied"),  # no rotation
    (1, 1, 0, "bilinear"),   # no border
])
def test_sample_rays_is_sample_cube_of_the_grid(mode, dtype, ray_batch, rot_batch, pad, border):
    """The image of the grid of fastgrid's maths: bit for bit for nearest (a tie rounds as
    grid_sample rounds it), to the grid's own rounding for bilinear (the taps come from the rays
    directly); grid_sample's to rounding."""
    cube = make_cube(2, 3, 8, dtype)
    rays = make_rays(ray_batch, dtype)
    rotation = None if rot_batch is None else rotations(rot_batch).to(dtype)
    valid = torch.rand(1, 23, 17, generator=torch.Generator().manual_seed(2)) > 0.2
    grid = spec_grid(rays, rotation, 8, pad, dtype)
    got = fastsample.sample_rays(cube, rays, rotation, mode, pad=pad, border=border,
                                 valid=valid)
    assert got.dtype == dtype and got.shape == (2, 3, 23, 17)
    of_grid = fastsample.sample_cube(cube, grid, mode, pad=pad, border=border, valid=valid)
    atol = ATOL[dtype] + (grid_rounding(8, pad, dtype) if mode == "bilinear" else 0.0)
    if mode == "nearest":
        assert torch.equal(got, of_grid)
    else:
        torch.testing.assert_close(got, of_grid, atol=atol, rtol=0)
    if border == "copied":
        atlas = copied_atlas(cube, pad)
    else:
        atlas = cm.cubemap_to_atlas(cube, pad, border) if pad else cm.faces_to_atlas(cube)
    masked = torch.where(valid.unsqueeze(-1), grid, torch.full_like(grid, -2.0))
    torch.testing.assert_close(got, reference(atlas, masked, mode), atol=atol, rtol=0)
    if rotation is not None:   # the compiled grid (the layer's) is the same grid
        assert torch.equal(fastgrid.rotated_rays_to_grid(rays, rotation, 8, pad), grid)


@pytest.mark.parametrize("face_size,pad", [(8, 1), (64, 2), (512, 2)])
def test_sample_rays_is_closer_to_the_exact_image_than_the_grid(face_size, pad):
    """Bilinear taps straight from float32 rays miss the exact image (float64 rays, grid and
    cube) by less than the image of the float32 grid does: the normalised grid rounds each
    atlas row by up to ``3 n`` eps (:func:`grid_rounding`), the rays path by ``n`` eps."""
    cube = make_cube(2, 3, face_size)
    rays, rotation = make_rays(1, h=64, w=64), rotations(2).float()
    exact = fastsample.sample_cube(cube.double(), spec_grid(rays.double(), rotation.double(),
                                                            face_size, pad, f64), pad=pad)
    of_grid = fastsample.sample_cube(cube, spec_grid(rays, rotation, face_size, pad, f32),
                                     pad=pad)
    got = fastsample.sample_rays(cube, rays, rotation, pad=pad)
    error = (got.double() - exact).abs().max()
    assert error < (of_grid.double() - exact).abs().max()
    assert error <= grid_rounding(face_size, pad) + ATOL[f32]


def test_uint8_ids_sampled_into_int64():
    """8-bit class ids (label images) sampled nearest straight into int64, as the layer's label
    images are: the ids of the uint8 image widened, on every path (table, grid, rays) and for
    edge pixels too, with a fill the uint8 ids could not hold (an ignore index of -1)."""
    ids = torch.randint(0, 200, (2, 6, 1, 8, 8), generator=torch.Generator().manual_seed(6),
                        dtype=torch.uint8)
    grid = make_grid(2)
    lut = fastsample.build_lut(grid, 8, 1, "nearest", channels=1)
    rays, rotation = make_rays(1), rotations(2).float()
    valid = torch.rand(1, 23, 17, generator=torch.Generator().manual_seed(7)) > 0.2
    calls = [lambda **k: fastsample.sample_cube(ids, grid, "nearest", pad=1, border="nearest",
                                                **k),
             lambda **k: fastsample.sample_cube(ids, grid, "nearest", pad=1, border="nearest",
                                                lut=lut, **k),
             lambda **k: fastsample.sample_rays(ids, rays, rotation, "nearest", pad=1,
                                                border="nearest", valid=valid, **k)]
    for call in calls:
        narrow = call(fill=255)
        wide = call(fill=-1, out_dtype=torch.int64)
        assert wide.dtype == torch.int64 and bool((narrow == 255).any())
        assert torch.equal(wide, torch.where(narrow == 255, -1, narrow.long()))
    with pytest.raises(TypeError, match="out_dtype: expected one of"):
        fastsample.sample_cube(ids, grid, "bilinear", pad=1, out_dtype=torch.int64)


def test_sample_rays_of_labels_and_half_precision():
    """Integer ids through float32 rays (exact, the ignore index outside); float16 sampled in
    float32; rays in another dtype than the grid's: the grid is built first, same image."""
    rays, rotation = make_rays(1), rotations(2).float()
    valid = torch.rand(1, 23, 17, generator=torch.Generator().manual_seed(3)) > 0.2
    labels = torch.randint(0, 2 ** 40, (2, 6, 1, 8, 8), generator=torch.Generator().manual_seed(5))
    grid = spec_grid(rays, rotation, 8, 1, f32)
    for ids, fill in ((labels, -1), (labels.remainder(200).to(torch.uint8), 255)):
        got = fastsample.sample_rays(ids, rays, rotation, "nearest", pad=1, border="nearest",
                                     valid=valid, fill=fill)
        assert got.dtype == ids.dtype and bool((got[:, 0][~valid.expand(2, -1, -1)] == fill).all())
        assert torch.equal(got, fastsample.sample_cube(ids, grid, "nearest", pad=1,
                                                       border="nearest", valid=valid, fill=fill))
    cube = make_cube(2, 3, 8)
    half = fastsample.sample_rays(cube.half(), rays, rotation, pad=1)
    assert half.dtype == torch.float16
    assert torch.equal(half, fastsample.sample_rays(cube.half().float(), rays, rotation,
                                                    pad=1).half())
    assert fastsample.reads_rays(torch.float16, f32) and not fastsample.reads_rays(f32, f64)
    assert torch.equal(fastsample.sample_rays(cube, rays.double(), rotation, pad=1),
                       fastsample.sample_cube(cube, spec_grid(rays.double(), rotation, 8, 1, f32),
                                              pad=1))


def test_kernel_face_table_is_cubemap_faces(monkeypatch):
    """The C++ kernel's face table is generated from the one cubemap.faces gives, and passed to
    the build (``-DOS_FACE_CASES``), so another table makes another build; the kernel's grid is
    the Python maths' bit for bit (``test_sample_rays_is_sample_cube_of_the_grid``)."""
    (flag,) = extension.face_case_flags()
    define, values = flag.split("=")
    table = torch.tensor([int(v) for v in values.split(",")], dtype=torch.int32)
    assert define == "-DOS_FACE_CASES"
    assert table.view(7, 5).tolist() == [list(case) for case in (*fastgrid._CASES,
                                                                  fastgrid._ZERO_CASE)]
    name = extension.name()
    monkeypatch.setattr(fastgrid, "_CASES", fastgrid._CASES[::-1])
    assert extension.face_case_flags() != [flag] and extension.name() != name


@pytest.mark.parametrize("kwargs,error,match", [
    (dict(rays=torch.zeros(4, 4, 2)), ValueError, "rays must have shape"),
    (dict(rays=torch.zeros(3, 4, 4, 3)), ValueError, "batch 3 does not match"),
    (dict(rotation=torch.eye(3).expand(3, 3, 3)), ValueError, "batch 3 does not match"),
    (dict(rotation=torch.zeros(2, 3, 4)), ValueError, "rotation must have shape"),
    (dict(rays=torch.zeros(1, 4, 4, 3, dtype=torch.int64)), TypeError, "rays"),
    (dict(valid=torch.ones(1, 4, 5, dtype=torch.bool)), ValueError, "valid: expected"),
    (dict(mode="cubic"), ValueError, "mode: expected one of"),
    (dict(mode="bicubic", backend="cpp"), ValueError, "mode: 'bicubic' has no C.. op"),
])
def test_sample_rays_bad_input(kwargs, error, match):
    args = dict(rays=make_rays(1, h=4, w=4), rotation=None)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        fastsample.sample_rays(make_cube(2, 3, 8), args.pop("rays"), args.pop("rotation"),
                               pad=1, **args)


# ------------------------------------------------------------------------------------------
# OmniProjection: fast=True against fast=False
# ------------------------------------------------------------------------------------------
def fisheye(size: int = 24, fov_deg: float = 190.0, learnable: bool = False,
            dtype=f64) -> ot.Camera:
    """Equidistant fisheye whose image circle (the fov edge) lies inside the image."""
    fov = math.radians(fov_deg)
    focal, centre = (size - 2) / fov, (size - 1) / 2
    return ot.Camera("equidistant", torch.tensor([focal, focal, centre, centre], dtype=dtype),
                     (size, size), fov=fov, learnable=learnable)


def rotations(batch: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(7)
    q, _ = torch.linalg.qr(torch.randn(batch, 3, 3, generator=gen, dtype=f64))
    return q * torch.linalg.det(q)[:, None, None]  # proper rotations


def render_both(kwargs: dict, inputs: dict, **render_kwargs) -> tuple[dict, dict]:
    outs = []
    for fast in (True, False):
        layer = ot.OmniProjection(fisheye(), 8, fast=fast, **kwargs)
        with torch.no_grad():
            outs.append(layer.render(**inputs, **render_kwargs))
    return outs[0], outs[1]


@pytest.mark.parametrize("batch,rotated", [(1, False), (2, False), (2, True)])
@pytest.mark.parametrize("interpolation", ["nearest", "bilinear"])
def test_layer_fast_equals_reference(batch, rotated, interpolation):
    cube = make_cube(batch, 3, 8, f64)
    depth = 1 + 9 * make_cube(batch, 1, 8, f64, seed=2)
    labels = (make_cube(batch, 1, 8, seed=3) * 13).long()
    inputs = dict(rgb=cube, depth=depth, labels=labels,
                  rotation=rotations(batch) if rotated else None)
    fast, ref = render_both(dict(interpolation=interpolation,
                                 depth_interpolation=interpolation), inputs)
    assert torch.equal(fast["valid"], ref["valid"])
    assert bool(fast["valid"].any()) and not bool(fast["valid"].all())  # the fov edge is in
    for key in ("rgb", "depth"):
        torch.testing.assert_close(fast[key], ref[key], atol=ATOL[f64] * 10, rtol=0)
        assert bool((fast[key].masked_select(~fast["valid"]) == 0).all())
    assert torch.equal(fast["labels"], ref["labels"])


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("batch,rotated", [(1, False), (2, False), (2, True)])
@pytest.mark.parametrize("interpolation", ["nearest", "bilinear"])
def test_layer_fast_equals_reference_uint8(batch, rotated, interpolation, channels_last):
    """8-bit RGB and labels: the fast path's image within a level of the reference path's
    (both the float image rounded), the labels exact."""
    gen = torch.Generator().manual_seed(batch)
    cube = torch.randint(0, 256, (batch, 6, 3, 8, 8), generator=gen, dtype=torch.uint8)
    labels = torch.randint(0, 255, (batch, 6, 8, 8), generator=gen, dtype=torch.uint8)
    rgb = cube.permute(0, 1, 3, 4, 2).contiguous() if channels_last else cube
    inputs = dict(rgb=rgb, labels=labels, rotation=rotations(batch) if rotated else None,
                  channels_last=channels_last)
    fast, ref = render_both(dict(interpolation=interpolation), inputs)
    floats, _ = render_both(dict(interpolation=interpolation),
                            dict(inputs, rgb=rgb.float()))
    assert torch.equal(fast["valid"], ref["valid"])
    assert bool(fast["valid"].any()) and not bool(fast["valid"].all())  # the fov edge is in
    assert torch.equal(fast["labels"], ref["labels"])
    assert fast["rgb"].dtype == ref["rgb"].dtype == torch.uint8
    assert fast["rgb"].shape == ref["rgb"].shape == ((batch, 24, 24, 3) if channels_last
                                                     else (batch, 3, 24, 24))
    assert_rounded(fast["rgb"], floats["rgb"], "fast")
    assert_rounded(ref["rgb"], floats["rgb"], "reference")


@pytest.mark.parametrize("supersample", [1, 2])
def test_layer_rotation_batch_in_chunks_equals_reference(monkeypatch, supersample):
    """A rotation batch is rendered a few samples at a time on the fast path
    (``projection.CHUNK_PIXELS``): here 2 samples a chunk, 5 samples, against ``grid_sample``
    on the whole batch."""
    from omniscape_torch.render import layer as projection
    monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * 24 * 24 * supersample ** 2)
    inputs = dict(rgb=make_cube(5, 3, 8), depth=1 + 9 * make_cube(5, 1, 8, seed=2),
                  labels=(make_cube(5, 1, 8, seed=3) * 13).long(), rotation=rotations(5).float())
    fast, ref = render_both(dict(supersample=supersample), inputs, soft_labels=13)
    assert torch.equal(fast["valid"], ref["valid"]) and torch.equal(fast["labels"], ref["labels"])
    for key in ("rgb", "depth", "soft_labels"):
        assert fast[key].shape == ref[key].shape
        torch.testing.assert_close(fast[key], ref[key], atol=ATOL[f32] * 10, rtol=0)


def test_layer_rotation_batch_samples_through_the_rays(monkeypatch):
    """A float32 camera under a rotation batch: every fast sampler reads the rays, so the layer
    builds no grid and renders the batch in one call (no chunks); the same outputs as
    grid_sample on the whole batch."""
    from omniscape_torch.render import layer as projection
    monkeypatch.setattr(projection, "CHUNK_PIXELS", 24 * 24)   # would be a chunk per sample
    inputs = dict(rgb=make_cube(3, 3, 8), depth=1 + 9 * make_cube(3, 1, 8, seed=2),
                  labels=(make_cube(3, 1, 8, seed=3) * 13).long(), rotation=rotations(3).float())
    fast = ot.OmniProjection(fisheye(dtype=f32), 8)
    ref = ot.OmniProjection(fisheye(dtype=f32), 8, fast=False)
    renders = []

    def no_grid(*args, **kwargs):
        raise AssertionError("a grid was built")

    def counted(*args, **kwargs):
        renders.append(args)
        return projection.OmniProjection._render(fast, *args, **kwargs)

    monkeypatch.setattr(fast, "_grid", no_grid)
    monkeypatch.setattr(fast, "_render", counted)
    with torch.no_grad():
        got, expect = fast.render(**inputs), ref.render(**inputs)
    assert len(renders) == 1
    assert torch.equal(got["valid"], expect["valid"])
    assert torch.equal(got["labels"], expect["labels"])
    for key in ("rgb", "depth"):
        torch.testing.assert_close(got[key], expect[key], atol=ATOL[f32] * 10, rtol=0)


@pytest.mark.parametrize("rotated", [False, True])
def test_layer_renders_into_given_outputs(monkeypatch, rotated):
    """``render(out=...)``: the outputs are written into the given tensors (here rows of larger
    ones), equal to those it allocates; on the chunked path too."""
    from omniscape_torch.render import layer as projection
    monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * 24 * 24)
    layer = ot.OmniProjection(fisheye(), 8)
    inputs = dict(rgb=make_cube(5, 3, 8), labels=(make_cube(5, 1, 8, seed=3) * 13).long(),
                  rotation=rotations(5).float() if rotated else None)
    big = {"rgb": torch.full((7, 3, 24, 24), 7.0),
           "labels": torch.full((7, 24, 24), 7, dtype=torch.long)}
    with torch.no_grad():
        expect = layer.render(**inputs)
        got = layer.render(**inputs, out={key: value[1:6] for key, value in big.items()})
        assert set(got) == set(expect)
        for key, value in expect.items():
            assert torch.equal(got[key], value), key
        for key, value in big.items():
            assert got[key].data_ptr() == value[1].data_ptr()
            assert bool((value[0] == 7).all()) and bool((value[6] == 7).all())
        with pytest.raises(ValueError, match="out: expected a dict with keys among"):
            layer.render(**inputs, out={"depth": torch.zeros(5, 1, 24, 24)})
        with pytest.raises(ValueError, match="out\\['rgb'\\]: expected a torch.float32 tensor"):
            layer.render(**inputs, out={"rgb": big["rgb"][:3]})


@pytest.mark.parametrize("kwargs", [dict(border="copied"), dict(border="none"),
                                    dict(supersample=2), dict(interpolation="bicubic")])
def test_layer_options_fast_equals_reference(kwargs):
    cube = make_cube(2, 3, 8)
    fast, ref = render_both(kwargs, dict(rgb=cube), soft_labels=None)
    torch.testing.assert_close(fast["rgb"], ref["rgb"], atol=ATOL[f32], rtol=0)


def test_layer_half_precision_and_soft_labels():
    cube = make_cube(1, 3, 8).half()
    labels = (make_cube(1, 1, 8, seed=3) * 5).long()
    fast, ref = render_both({}, dict(rgb=cube, labels=labels), soft_labels=5)
    assert fast["rgb"].dtype == torch.float16
    torch.testing.assert_close(fast["rgb"], ref["rgb"], atol=torch.finfo(torch.float16).eps,
                               rtol=0)
    torch.testing.assert_close(fast["soft_labels"], ref["soft_labels"], atol=ATOL[f32], rtol=0)


def test_frozen_camera_lookup_table_is_cached_and_reused():
    layer = ot.OmniProjection(fisheye(), 8)
    cube = make_cube(2, 3, 8)
    with torch.no_grad():
        first, _ = layer(cube)
        (table,) = layer._lut_cache.values()
        second, _ = layer(cube)
        assert next(iter(layer._lut_cache.values())) is table
        layer(cube, rotations(2).float())  # a rotation: its table is not kept
    assert len(layer._lut_cache) == 1
    assert torch.equal(first, second)


@pytest.mark.parametrize("what", ["cube", "camera", "rotation"])
def test_gradients_flow_through_the_reference_path(what):
    cam = fisheye(learnable=what == "camera")
    cube = make_cube(1, 3, 8, f64).requires_grad_(what == "cube")
    rotation = rotations(1).requires_grad_(what == "rotation")
    grads, images = [], []
    for fast in (True, False):
        layer = ot.OmniProjection(cam, 8, fast=fast, fused_grid=False)  # no compile here
        image, _ = layer(cube, rotation)
        leaf = {"cube": cube, "camera": cam.params, "rotation": rotation}[what]
        (grad,) = torch.autograd.grad(image.square().sum(), leaf)
        grads.append(grad)
        images.append(image.detach())
    assert torch.equal(images[0], images[1])  # both took grid_sample
    assert torch.equal(grads[0], grads[1]) and bool((grads[0] != 0).any())
