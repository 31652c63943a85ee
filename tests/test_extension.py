"""The package's C++ extension (``omniscape_torch.render.kernels.build``: the fast sampler's and the
town's kernels, one library): custom ops that pass ``torch.library.opcheck``, check their
arguments, trace under ``torch.compile``, and a build that is cached where torch caches
extensions, keyed on the CPU and the sources' content (not their path), says when it builds
and what it compiles as it goes, is safe under concurrent first uses, found without ninja on
the PATH, and whose failure is one warning for the sampler and the town together.
"""

from __future__ import annotations

import ast
import contextlib
import io
import math
import os
import re
import shutil
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.render.kernels import build as extension, camera as kernels, cube as fastsample
from omniscape_torch.render.kernels import image as kimage
from omniscape_torch.render.kernels._backend import available, compile_failures
from omniscape_torch.render.kernels import cone as cone_kernels
from omniscape_torch.render.kernels import town as town_kernels
from omniscape_torch.scenes import Town

ROOT = Path(__file__).resolve().parents[1]
f32, f64 = torch.float32, torch.float64


def ops():
    return extension.load()


def make_inputs(dtype, mode="bilinear", batch=2, size=8, pad=1, h=5, w=7, seed=0,
                channels_last=False, out_dtype=None):
    """A cube, its ring and an output buffer, as ``fast.py`` passes them to the ops."""
    gen = torch.Generator().manual_seed(seed)
    if dtype.is_floating_point:
        cube = torch.rand(batch, 6, 3, size, size, generator=gen, dtype=dtype)
    else:
        cube = torch.randint(0, 200, (batch, 6, 3, size, size), generator=gen).to(dtype)
    out = torch.empty(batch, 3, h, w, dtype=out_dtype or dtype)
    if channels_last:   # (B, 6, F, F, C) and (B, H, W, C) in memory
        cube = cube.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3)
        out = out.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    border = "bilinear" if mode == "bilinear" else "nearest"
    ring_src, ring_weight = fastsample._ring_offsets(size, pad, border, dtype,
                                                     fastsample._strides(cube))
    return cube, ring_src, ring_weight, out


def grid_dtype(dtype):
    return fastsample.work_dtype(dtype) if dtype in fastsample.BLENDED else f64


def make_grid(batch, h, w, dtype, seed=1):
    gen = torch.Generator().manual_seed(seed)
    grid = (torch.rand(batch, h, w, 2, generator=gen, dtype=f64) * 2.3 - 1.15).to(dtype)
    grid[:, 0, 0] = -2.0
    return grid


def make_rotation(batch, dtype):
    q, _ = torch.linalg.qr(torch.randn(batch, 3, 3, generator=torch.Generator().manual_seed(3),
                                       dtype=f64))
    return (q * torch.linalg.det(q)[:, None, None]).to(dtype).contiguous()


def make_valid(batch, h, w):
    return torch.rand(batch, h, w, generator=torch.Generator().manual_seed(4)) > 0.3


CASES = [(f32, "bilinear"), (f64, "bilinear"), (f32, "nearest"), (torch.uint8, "nearest"),
         (torch.int64, "nearest"), (torch.uint8, "bilinear"), (torch.float16, "bilinear"),
         (torch.bfloat16, "nearest")]
#: (cube dtype, output dtype, channels-last) for the layouts and conversions
LAYOUTS = [(f32, f32, True), (torch.uint8, torch.uint8, True), (torch.uint8, f32, False),
           (torch.uint8, f32, True), (torch.bfloat16, f32, True)]


# ------------------------------------------------------------------------------------------
# The ops
# ------------------------------------------------------------------------------------------
def test_ops_are_registered_after_a_render():
    size = 16
    focal, centre = (size - 2) / math.radians(190), (size - 1) / 2
    camera = ot.Camera("equidistant", torch.tensor([focal, focal, centre, centre]), (size, size),
                       fov=math.radians(190))
    with torch.no_grad():
        ot.OmniProjection(camera, 8)(torch.rand(1, 6, 3, 8, 8))
    assert available() and compile_failures() == {}
    for name in extension.OPS:
        assert hasattr(torch.ops.omniscape_torch, name), name
    # every op the sources (or the town's and the cone's kernels, in Python) define is listed
    # and has a fake implementation (torch.compile)
    in_cpp = {m for path in extension.SOURCES
              for m in re.findall(r'm\.def\("(\w+)\(', path.read_text(encoding="utf-8"))}
    in_python = set(town_kernels.OPS) | set(cone_kernels.OPS)
    assert not in_cpp & in_python
    defined = in_cpp | in_python
    fakes = set(extension._FAKES) | set(town_kernels._FAKES) | set(cone_kernels._FAKES)
    assert defined == set(extension.OPS) == fakes, (defined ^ set(extension.OPS), defined ^ fakes)


@pytest.mark.parametrize("dtype", [f32, f64])
def test_opcheck_build_lut(dtype):
    grid = make_grid(2, 5, 7, dtype).reshape(2, -1, 2)
    table = torch.empty(2, 35, 3, dtype=fastsample._ENTRY[dtype])
    for bilinear in (True, False):
        torch.library.opcheck(ops().build_lut, (grid, 8, 1, [3 * 64, 8, 1], bilinear, table))


@pytest.mark.parametrize("dtype,mode", CASES)
def test_opcheck_sample_lut(dtype, mode):
    cube, ring_src, ring_weight, out = make_inputs(dtype, mode)
    grid = make_grid(1, 5, 7, grid_dtype(dtype))
    lut = fastsample.build_lut(grid, 8, 1, mode, channels=3)
    torch.library.opcheck(ops().sample_lut, (cube, lut.table, lut.grid, ring_src, ring_weight, 1,
                                             list(lut.strides), mode == "bilinear", 0, out))


@pytest.mark.parametrize("dtype,out_dtype,channels_last", LAYOUTS)
def test_opcheck_layouts_and_output_dtypes(dtype, out_dtype, channels_last):
    """Channels-last cubes and outputs, and a float32 output of an 8-bit or half cube."""
    cube, ring_src, ring_weight, out = make_inputs(dtype, channels_last=channels_last,
                                                   out_dtype=out_dtype)
    grid = make_grid(1, 5, 7, f32)
    lut = fastsample.build_lut(grid, 8, 1, channels=3, channels_last=channels_last)
    torch.library.opcheck(ops().sample_lut, (cube, lut.table, lut.grid, ring_src, ring_weight, 1,
                                             list(lut.strides), True, 0, out))
    torch.library.opcheck(ops().sample_grid, (cube, make_grid(2, 5, 7, f32), None, ring_src,
                                              ring_weight, 1, True, 0, out))


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("dtype,mode", CASES)
def test_opcheck_sample_grid(dtype, mode, masked):
    cube, ring_src, ring_weight, out = make_inputs(dtype, mode)
    grid = make_grid(2, 5, 7, grid_dtype(dtype))
    valid = make_valid(1, 5, 7) if masked else None
    torch.library.opcheck(ops().sample_grid, (cube, grid, valid, ring_src, ring_weight, 1,
                                              mode == "bilinear", 0, out))


@pytest.mark.parametrize("masked,rotated", [(False, False), (True, True), (False, True)])
@pytest.mark.parametrize("dtype,mode", CASES)
def test_opcheck_sample_rays(dtype, mode, masked, rotated):
    cube, ring_src, ring_weight, out = make_inputs(dtype, mode)
    g = grid_dtype(dtype)
    rays = torch.randn(1, 5, 7, 3, generator=torch.Generator().manual_seed(5), dtype=g)
    rotation = make_rotation(2, g) if rotated else None
    valid = make_valid(2, 5, 7) if masked else None
    torch.library.opcheck(ops().sample_rays, (cube, rays, rotation, valid, ring_src, ring_weight,
                                              1, mode == "bilinear", 7, out))


@pytest.mark.parametrize("dtype", [f32, torch.float64])
def test_opcheck_camera_grid_and_camera_rays(dtype):
    params = torch.tensor([[4.0, 4.0, 3.0, 2.0], [3.0, 3.5, 3.5, 2.5]], dtype=torch.float64)
    affine, limits, table = kernels.radial_table("equidistant", params, (5, 7), entries=16)
    cameras = [t.to(dtype) for t in (affine, limits, table)]
    valid = torch.empty(2, 5, 7, dtype=torch.bool)
    torch.library.opcheck(ops().camera_grid, (*cameras, make_rotation(2, dtype), 8, 1,
                                              torch.empty(2, 5, 7, 2, dtype=dtype), valid))
    torch.library.opcheck(ops().camera_rays, (*cameras, torch.empty(2, 5, 7, 3, dtype=dtype),
                                              valid))
    with pytest.raises(RuntimeError, match="camera_rays: rays: expected \\(2, 5, 7, 3\\)"):
        ops().camera_rays(*cameras, torch.empty(2, 5, 7, 2, dtype=dtype), valid)
    with pytest.raises(RuntimeError, match="camera_rays: valid: expected bool \\(2, H, W\\)"):
        ops().camera_rays(*cameras, torch.empty(2, 5, 7, 3, dtype=dtype), valid[:1])
    with pytest.raises(RuntimeError, match="camera_rays: limits: expected shape"):
        ops().camera_rays(cameras[0], cameras[1][:1], cameras[2],
                          torch.empty(2, 5, 7, 3, dtype=dtype), valid)
    # one table shared by the cameras (1, 2, K): the rays of that table copied per camera
    shared = kernels.radial_table("equidistant", params[:1].expand(2, 4), (5, 7), entries=16)[2]
    one = [cameras[0], cameras[1], shared[:1].to(dtype)]
    rays, valid_shared = (torch.empty(2, 5, 7, 3, dtype=dtype),
                          torch.empty(2, 5, 7, dtype=torch.bool))
    torch.library.opcheck(ops().camera_rays, (*one, rays, valid_shared))
    want, want_valid = kimage.camera_rays(*cameras[:2], shared.to(dtype), (5, 7), dtype)
    got, got_valid = kimage.camera_rays(*one, (5, 7), dtype)
    assert torch.equal(got, want) and torch.equal(got_valid, want_valid)


def test_framing_ops_are_the_numpy_framing(monkeypatch):
    """framing_reach and framing_focal (what framing.reach and focal_for_coverage run) against
    those functions' NumPy arithmetic (the extension hidden), within float rounding: lenses
    turned up to 60 degrees (some axes miss the source: theta 0), off-centre pinholes, shared
    and per-sample distances to the edge, coverages beyond what a source can fill; and
    opcheck."""
    from omniscape_torch.render.kernels import framing
    g = torch.Generator().manual_seed(5)
    n, f64 = 24, torch.float64
    angles = (torch.rand(n, 3, generator=g, dtype=f64) * 2 - 1) * math.radians(60)
    rotation = ot.presets.yaw_pitch_roll_to_matrix(*angles.T).contiguous().numpy()
    intrinsics = torch.cat((20 + 40 * torch.rand(n, 2, generator=g, dtype=f64),
                            10 + 30 * torch.rand(n, 2, generator=g, dtype=f64)), 1).numpy()
    half = (1.2 + 0.6 * torch.rand(n, generator=g, dtype=f64)).numpy()
    coverage = (0.05 + torch.rand(n, generator=g, dtype=f64)).clamp_max(1.0).numpy()
    centre = (torch.rand(n, 2, generator=g, dtype=f64) * 8 + 12).numpy()
    theta = framing.reach(rotation, intrinsics, (30, 40), half, backend="cpp")
    radius = theta * 1.1                                   # a lens of radius 1.1 theta
    focal = [framing.focal_for_coverage(radius, e, coverage, (32, 36), backend="cpp")
             for e in (framing.to_edge(centre, (32, 36)), framing.to_edge(centre[:1], (32, 36)))]
    want = framing.reach(rotation, intrinsics, (30, 40), half, backend="torch")   # NumPy's
    assert (want == 0).all(1).any() and (want > 0).all(1).any()
    np_focal = [framing.focal_for_coverage(radius, e, coverage, (32, 36), backend="torch")
                for e in (framing.to_edge(centre, (32, 36)), framing.to_edge(centre[:1], (32, 36)))]
    torch.testing.assert_close(torch.from_numpy(theta), torch.from_numpy(want), rtol=0,
                               atol=1e-14)
    for got, ref in zip(focal, np_focal):
        torch.testing.assert_close(torch.from_numpy(got), torch.from_numpy(ref), rtol=1e-12,
                                   atol=0)
    t = [torch.from_numpy(a) for a in (rotation, intrinsics, half, radius, coverage)]
    cos_sin = framing.COS_SIN
    torch.library.opcheck(ops().framing_reach, (t[0], t[1], t[2], cos_sin[0], cos_sin[1], 30,
                                                40, torch.empty(n, framing.DIRECTIONS, dtype=f64)))
    torch.library.opcheck(ops().framing_focal, (t[3], torch.from_numpy(framing.to_edge(
        centre[:1], (32, 36))), t[4], 32, 36, torch.empty(n, dtype=f64)))
    with pytest.raises(RuntimeError, match="framing_focal: radius: expected float64"):
        ops().framing_focal(t[3].float(), t[3], t[4], 32, 36, torch.empty(n, dtype=f64))
    # the one-call draw: uniforms -> attitudes, rotations, reach, a radius table, focals
    from omniscape_torch.render.kernels.draw import STREAM_WIDTH
    u = torch.rand(STREAM_WIDTH * n, generator=torch.Generator().manual_seed(2), dtype=f64)
    spec = torch.tensor([2.8, 3.4, -0.2, 0.2, -0.1, 0.1, -0.4, 0.4, 0.3, 0.9, 0.5], dtype=f64)
    table = torch.linspace(0, 3, 64, dtype=f64)
    outs = (torch.zeros(n, 9, dtype=f64), torch.empty(n, dtype=f64), torch.empty(3, n, dtype=f64),
            torch.empty(n, dtype=torch.bool), torch.empty(n, 3, 3, dtype=f64),
            torch.empty(n, dtype=f64))
    edge = torch.from_numpy(framing.to_edge(centre[:1], (32, 36)))
    torch.library.opcheck(ops().frame_lens, (
        u, spec, t[1], torch.tensor([[17.5, 15.5]], dtype=f64), cos_sin[0], cos_sin[1], 30, 40,
        table, torch.full((64,), 3 / 63, dtype=f64), 63 / 2.0, edge, 32, 36, *outs))
    with pytest.raises(RuntimeError, match="frame_lens: slope: expected float64"):
        ops().frame_lens(u, spec, t[1], torch.tensor([[17.5, 15.5]], dtype=f64), cos_sin[0],
                         cos_sin[1], 30, 40, table, table[:3], 63 / 2.0, edge, 32, 36, *outs)


@pytest.mark.parametrize("dtype,mode", CASES)
def test_opcheck_sample_image(dtype, mode):
    cube = make_inputs(dtype, mode)[0]
    image = cube[:, 0].contiguous()   # (2, 3, 8, 8)
    g = grid_dtype(dtype)
    rays = torch.randn(1, 5, 7, 3, generator=torch.Generator().manual_seed(6), dtype=g)
    k = torch.tensor([[4.0, 4.5, 3.5, 3.0]], dtype=g)
    out = torch.empty(2, 3, 5, 7, dtype=cube.dtype)
    seen = torch.empty(2, 5, 7, dtype=torch.bool)
    torch.library.opcheck(ops().sample_image, (image, rays, make_rotation(2, g), k,
                                               make_valid(1, 5, 7), mode == "bilinear", 0, out,
                                               seen))
    with pytest.raises(RuntimeError, match="sample_image: intrinsics: expected 2 dimensions"):
        ops().sample_image(image, rays, None, k[0], None, mode == "bilinear", 0, out, seen)


def test_opcheck_detection_ops():
    """box_pixels: the extent of the window's pixels whose rays land in the rectangle (a
    torch reference of the same projection); outline_points and outline_reduce: opcheck, and
    arguments refused by name."""
    gen = torch.Generator().manual_seed(7)
    rays = torch.randn(2, 5, 7, 3, generator=gen, dtype=f64)
    rays[..., 2] = rays[..., 2].abs() + 0.5
    rotation, k, valid = make_rotation(2, f64), torch.tensor([[4.0, 4.5, 3.5, 3.0]], dtype=f64), \
        make_valid(2, 5, 7)
    sample = torch.tensor([0, 1, 1])
    windows = torch.tensor([[0, 0, 6, 4], [1, 1, 5, 3], [0, 0, 6, 4]])
    rects = torch.tensor([[0.0, 0, 5, 4], [1, 1, 6, 5], [-9, -9, -8, -8]], dtype=f64)
    out = torch.empty(3, 4, dtype=torch.long)
    torch.library.opcheck(ops().box_pixels, (rays, rotation, k, valid, sample, windows, rects,
                                             out))
    ops().box_pixels(rays, rotation, k, valid, sample, windows, rects, out)
    src = torch.einsum("bij,bhwj->bhwi", rotation, rays)
    u = k[0, 0] * src[..., 0] / src[..., 2] + k[0, 2]
    v = k[0, 1] * src[..., 1] / src[..., 2] + k[0, 3]
    for m, (s, (c0, r0, c1, r1), (u0, v0, u1, v1)) in enumerate(zip(
            sample.tolist(), windows.tolist(), rects.tolist())):
        hit = torch.zeros(5, 7, dtype=torch.bool)
        hit[r0:r1 + 1, c0:c1 + 1] = True
        hit &= valid[s] & (src[s, ..., 2] > 0) & (u[s] >= u0) & (u[s] <= u1) & (v[s] >= v0) & \
            (v[s] <= v1)
        rows, cols = hit.nonzero(as_tuple=True)
        expected = ([int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max())]
                    if len(rows) else [-1] * 4)
        assert out[m].tolist() == expected, m
    with pytest.raises(RuntimeError, match="box_pixels: box 0: sample or window outside"):
        ops().box_pixels(rays, rotation, k, valid, sample, windows + 3, rects, out)
    counts, owner = torch.tensor([2, 1, 3]), torch.tensor([0, 0, 1])
    points = torch.zeros(2, 16, 2, dtype=f64)
    torch.library.opcheck(ops().outline_points, (rects, counts, owner, 2, points))
    pix, ok = torch.randn(2, 16, 2, generator=gen, dtype=f64), make_valid(2, 16, 1)[..., 0]
    extents, longest, flags = (torch.empty(3, 8, dtype=f64), torch.empty(3, dtype=f64),
                               torch.empty(3, dtype=torch.long))
    torch.library.opcheck(ops().outline_reduce, (pix, ok, ok, counts, owner, 2, 7, 5, 16.0,
                                                 extents, longest, flags))
    with pytest.raises(RuntimeError, match="outline_points: the outlines of sample 1 exceed"):
        ops().outline_points(rects, torch.tensor([2, 1, 4]), owner, 2, points)
    with pytest.raises(RuntimeError, match="outline_reduce: box 1: counts must be positive and "
                                           "owners sorted"):
        ops().outline_reduce(pix, ok, ok, counts, torch.tensor([1, 0, 1]), 2, 7, 5, 16.0,
                             extents, longest, flags)


@pytest.mark.parametrize("dtype", [torch.uint8, f32, f64])
def test_opcheck_mip_image(dtype):
    gen = torch.Generator().manual_seed(8)
    image = (torch.rand(2, 3, 16, 16, generator=gen) * 255).to(dtype)
    g = grid_dtype(dtype)
    rays = torch.randn(1, 5, 7, 3, generator=gen, dtype=g)
    rays[..., 2] = 1
    k = torch.tensor([[9.0, 9.5, 7.5, 7.0]], dtype=g)
    out = torch.zeros(2, 3, 5, 7, dtype=dtype)
    valid = torch.ones(2, 5, 7, dtype=torch.bool)
    torch.library.opcheck(ops().mip_image, (image, rays, make_rotation(2, g), k, valid, 1.001,
                                            out))
    with pytest.raises(RuntimeError, match="mip_image: valid: expected one per sample"):
        ops().mip_image(image, rays, None, k, valid[:1], 1.001, out)
    with pytest.raises(RuntimeError, match="mip_image: image: expected uint8, float32"):
        ops().mip_image(image.half(), rays.float(), None, k.float(), valid, 1.001, out.half())
    # a check it shares with sample_image: a rotation has 3 rows
    with pytest.raises(RuntimeError, match=r"mip_image: rotation: expected \(1 or B, 3, 3\)"):
        ops().mip_image(image, rays, make_rotation(2, g)[:, :2].contiguous(), k, valid, 1.001,
                        out)


@pytest.mark.parametrize("dtype", [torch.uint8, f32])
def test_opcheck_reproject_image(dtype):
    gen = torch.Generator().manual_seed(9)
    image = (torch.rand(2, 3, 16, 16, generator=gen) * 255).to(dtype)
    labels = torch.randint(0, 5, (2, 16, 16), generator=gen)
    params = torch.tensor([[4.0, 4.0, 3.0, 2.0], [3.0, 3.5, 3.5, 2.5]], dtype=torch.float64)
    cameras = [t.float() for t in kernels.radial_table("equidistant", params, (5, 7),
                                                        entries=16)]
    k = torch.tensor([[9.0, 9.5, 7.5, 7.0]])
    out = torch.zeros(2, 3, 5, 7, dtype=dtype)
    out_labels = torch.zeros(2, 5, 7, dtype=torch.int64)
    valid = torch.zeros(2, 5, 7, dtype=torch.bool)
    torch.library.opcheck(ops().reproject_image, (image, labels, *cameras, make_rotation(2, f32),
                                                  k, True, 1.001, 255, out, out_labels, valid))
    torch.library.opcheck(ops().reproject_image, (None, labels, *cameras, make_rotation(2, f32),
                                                  k, True, 0.0, 255, None, out_labels, valid))
    with pytest.raises(RuntimeError, match="reproject_image: expected image with out"):
        ops().reproject_image(image, labels, *cameras, make_rotation(2, f32), k, True, 0.0, 255,
                              None, out_labels, valid)
    with pytest.raises(RuntimeError, match="reproject_image: valid: expected bool"):
        ops().reproject_image(image, None, *cameras, make_rotation(2, f32), k, True, 0.0, 255,
                              out, None, valid[:1])


def test_ops_write_what_the_python_functions_return():
    """The ops called directly give ``fast.sample_cube``'s and ``fast.sample_rays``' images."""
    cube, ring_src, ring_weight, out = make_inputs(f32)
    grid, valid = make_grid(2, 5, 7, f32), make_valid(1, 5, 7)
    ops().sample_grid(cube, grid, valid, ring_src, ring_weight, 1, True, 0, out)
    assert torch.equal(out, fastsample.sample_cube(cube, grid, pad=1, valid=valid))
    rays, rotation = torch.randn(1, 5, 7, 3), make_rotation(2, f32)
    ops().sample_rays(cube, rays, rotation, None, ring_src, ring_weight, 1, True, 0, out)
    assert torch.equal(out, fastsample.sample_rays(cube, rays, rotation, pad=1))


def test_ops_check_their_arguments():
    """Wrong dtypes, shapes and strides are refused with the argument's name, not read."""
    cube, ring_src, ring_weight, out = make_inputs(f32)
    grid, valid = make_grid(2, 5, 7, f32), make_valid(1, 5, 7)
    args = dict(cube=cube, grid=grid, valid=valid, ring_src=ring_src, ring_weight=ring_weight,
                pad=1, bilinear=True, fill=0, out=out)
    bad = [
        (dict(grid=grid.double()), "sample_grid: grid: expected Float for a Float cube"),
        (dict(grid=grid.transpose(1, 2)), "grid: expected a contiguous tensor"),
        (dict(grid=grid[:1].expand(3, -1, -1, -1).contiguous()), "grid: expected batch 1 or 2"),
        (dict(cube=cube[:, :5]), r"cube: expected shape \(B, 6, C, F, F\)"),
        (dict(cube=cube.to(torch.int32)), "cube: bilinear sampling needs float32, float64"),
        (dict(out=out[:, :2]), "out: expected shape"),
        (dict(out=out.double()), "out: expected Float, got Double"),
        (dict(cube=cube.double(), grid=grid.double(), ring_weight=ring_weight.double()),
         "out: expected Double, got Float"),
        (dict(cube=cube.to(torch.uint8), out=out.half()), "out: expected Byte or float32"),
        (dict(out=torch.empty(2, 3, 7, 5).transpose(2, 3)), "out: expected H x W planes"),
        (dict(valid=valid.float()), "valid: expected bool"),
        (dict(valid=valid[..., :6].contiguous()), "valid: expected shape"),
        (dict(ring_src=ring_src[:-1]), "ring_src: expected shape"),
        (dict(ring_weight=ring_weight.double()), "ring_weight: expected Float for a Float"),
        (dict(pad=-1), "pad: expected F >= 1 and pad >= 0"),
    ]
    for change, match in bad:
        with pytest.raises(RuntimeError, match=match):
            ops().sample_grid(**{**args, **change})
    lut = fastsample.build_lut(grid, 8, 1, channels=1)   # for a cube of 1 channel
    with pytest.raises(RuntimeError, match=r"sample_lut: table: built for the strides \(face, "
                                           r"row, texel\) \[64, 8, 1\], the cube's are \(192, "):
        ops().sample_lut(cube, lut.table, lut.grid, ring_src, ring_weight, 1, list(lut.strides),
                         True, 0, out)
    with pytest.raises(RuntimeError, match="sample_rays: rotation: expected .* rays' dtype"):
        ids, ids_src, _, ids_out = make_inputs(torch.uint8, "nearest")
        ops().sample_rays(ids, torch.randn(1, 5, 7, 3), make_rotation(1, f64), None, ids_src,
                          None, 1, False, 0, ids_out)
    with pytest.raises(RuntimeError, match="nearest sampling copies elements of 1, 2, 4 or 8"):
        ops().sample_grid(cube.to(torch.complex128), grid.double(), None, ring_src, None, 1,
                          False, 0, out.to(torch.complex128))


def test_tables_and_rings_of_any_entries_read_inside_the_cube():
    """The ops trust no table or ring: a table's codes beyond the cube read as outside
    (``fill``), ring offsets beyond it are clamped into it."""
    cube, ring_src, ring_weight, out = make_inputs(f32)
    grid = make_grid(1, 5, 7, f32).reshape(1, -1, 2)
    table = torch.randint(-2 ** 31, 2 ** 31 - 1, (1, 35, 3), dtype=torch.int32)
    table[0, :3, 0] = torch.tensor([2 ** 31 - 1, 6 * cube.stride(1), -7], dtype=torch.int32)
    ops().sample_lut(cube, table, grid, ring_src, ring_weight, 1, list(fastsample._strides(cube)),
                     False, 5, out)
    assert bool((out.flatten(2)[..., :3] == 5).all())
    wild = ring_src * 10 ** 9 - 10 ** 12
    ops().sample_grid(cube, grid.view(1, 5, 7, 2), None, wild, None, 1, True, 0, out)
    assert bool(out.isfinite().all())


def town_inputs(n=6, T=4, V=5, seed=0):
    """Rays, hits and tables as ``kernels.town.shade`` passes them to the town's ops (``T``
    triangles of ``V`` vertices, some rays hitting none), and their outputs."""
    gen = torch.Generator().manual_seed(seed)
    attr = torch.rand(14, T, generator=gen)
    attr[3] = torch.tensor([7.0, 1.0, 8.0, 6.0])[:T]   # class ids
    attr[4] = torch.tensor([0.0, 1.0, 0.0, 2.0])[:T]   # part kinds
    attr[13] = torch.tensor([0.0, 0.0, 1.0, 1.0])[:T]  # smooth normals
    hits = dict(o=torch.randn(1, 3, generator=gen),
                d=torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1),
                t=torch.rand(n, generator=gen) * 20, tri=torch.arange(n) % (T + 1) - 1,
                u=torch.rand(n, generator=gen) / 2, v=torch.rand(n, generator=gen) / 2,
                attr=attr, tris=torch.randint(0, V, (T, 3), generator=gen, dtype=torch.int32),
                vn=torch.nn.functional.normalize(torch.randn(V, 3, generator=gen), dim=-1),
                weather=torch.rand(26, generator=gen))
    shaded = dict(shadow=torch.rand(n, generator=gen) > 0.5, lamps=torch.randn(2, 3, generator=gen),
                  rgb=torch.empty(n, 3), range=torch.empty(n),
                  labels=torch.empty(n, dtype=torch.int64), normal=torch.empty(n, 3))
    return hits, shaded


@pytest.mark.slow   # about 3-7 s: opcheck traces each op (aot_dispatch_dynamic)
def test_opcheck_town_ops():
    hits, shaded = town_inputs()
    n = hits["d"].shape[0]
    torch.library.opcheck(ops().town_backfaces, (hits["d"], hits["tri"], hits["attr"],
                                                 torch.empty(n, dtype=torch.bool)))
    torch.library.opcheck(ops().town_prepare, (*hits.values(), 1e-3, 1e-5,
                                               torch.empty(n, dtype=torch.bool),
                                               torch.empty(n, 3), torch.empty(n, dtype=torch.bool)))
    torch.library.opcheck(ops().town_shade, (*hits.values(), *shaded.values()))
    P = 10
    store = (hits["d"], torch.tensor([9, 0, 3, 4, 5, 1]), 0, torch.rand(n, 3), torch.rand(n),
             torch.arange(n), torch.rand(n) > 0.5, torch.tensor([0.0, 0.0, 1.0]), 1000.0,
             torch.zeros(3, P), torch.zeros(P), torch.zeros(P), torch.zeros(P, dtype=torch.int64))
    torch.library.opcheck(ops().town_store, store)
    torch.library.opcheck(ops().town_store, (store[0], None, 4, *store[3:]))


def test_town_ops_check_their_arguments():
    """Wrong dtypes, shapes, strides and indices beyond the tables are refused with the op's
    and the argument's name, before they are read (the hits' and texels' indices before the
    loop; a triangle's corners and a ground triangle's class id as they are met)."""
    hits, shaded = town_inputs()
    n = hits["d"].shape[0]
    bad = [
        (dict(tri=hits["tri"] + 1), "town_shade: tri: expected entries in \\[-1, 4\\)"),
        (dict(tri=hits["tri"] - 1), "town_shade: tri: expected entries in"),
        (dict(tris=hits["tris"] + 5), "town_shade: tris: expected corners in \\[0, 5\\), got "
                                      "triangle 2 with corners"),
        (dict(tris=hits["tris"].long()), "town_shade: tris: expected shape .* in Int"),
        (dict(d=hits["d"].double()), "town_shade: d: expected shape .* in Float, got .* Double"),
        (dict(d=hits["d"].T.contiguous().T), "town_shade: d: expected a contiguous tensor"),
        (dict(o=hits["o"].expand(n + 1, 3).contiguous()), "town_shade: o: expected \\(1, 3\\)"),
        (dict(t=hits["t"][1:]), "town_shade: t: expected shape"),
        (dict(weather=hits["weather"][1:]), "town_shade: weather: expected shape"),
        (dict(attr=hits["attr"][:13].contiguous()), "town_shade: attr: expected shape"),
        (dict(attr=hits["attr"] * torch.tensor([1.0] * 3 + [2.0] + [1.0] * 10)[:, None]),
         "town_shade: attr: expected class ids"),
        (dict(shadow=shaded["shadow"].to(torch.uint8)), "town_shade: shadow: expected shape"),
        (dict(labels=shaded["labels"].float()), "town_shade: labels: expected shape"),
    ]
    for change, match in bad:
        args = {**hits, **shaded, **change}
        with pytest.raises(RuntimeError, match=match):
            ops().town_shade(*args.values())
    with pytest.raises(RuntimeError, match="town_backfaces: out: expected shape"):
        ops().town_backfaces(hits["d"], hits["tri"], hits["attr"], torch.empty(n, 1))
    with pytest.raises(RuntimeError, match="town_prepare: tris: expected corners in"):
        ops().town_prepare(*{**hits, "tris": hits["tris"] - 9}.values(), 1e-3, 1e-5,
                           torch.empty(n, dtype=torch.bool), torch.empty(n, 3),
                           torch.empty(n, dtype=torch.bool))
    with pytest.raises(RuntimeError, match="town_prepare: origin: expected shape"):
        ops().town_prepare(*hits.values(), 1e-3, 1e-5, torch.empty(n, dtype=torch.bool),
                           torch.empty(n, 2), torch.empty(n, dtype=torch.bool))
    P = 10
    store = [hits["d"], None, 0, torch.rand(n, 3), torch.rand(n), torch.arange(n),
             torch.rand(n) > 0.5, torch.tensor([0.0, 0.0, 1.0]), 1000.0, torch.zeros(3, P),
             torch.zeros(P), torch.zeros(P), torch.zeros(P, dtype=torch.int64)]
    with pytest.raises(RuntimeError, match="town_store: start: expected 0 <= start <= 4"):
        ops().town_store(*store[:2], 5, *store[3:])
    with pytest.raises(RuntimeError, match="town_store: index: expected entries in \\[0, 10\\)"):
        ops().town_store(store[0], torch.arange(n) + 5, *store[2:])
    with pytest.raises(RuntimeError, match="town_store: labels_out: expected shape"):
        ops().town_store(*store[:-1], torch.zeros(P + 1, dtype=torch.int64))


def test_town_ops_let_go_of_the_gil():
    """A call through ``torch.ops`` releases the GIL while the op runs, as ctypes did: the
    town's worker threads shade in parallel, and Python runs meanwhile. One long
    ``town_shade`` call (many lamps) on a thread: the main thread runs Python many times
    within it (holding the GIL, the op would let it run at most at its two ends)."""
    import threading
    import time
    n = 40000
    hits, shaded = town_inputs(n=n)
    shaded["lamps"] = torch.randn(400, 3)
    args = [*hits.values(), *shaded.values()]
    ops().town_shade(*args)   # warm
    span = []

    def shade():
        span.append(time.perf_counter())
        ops().town_shade(*args)
        span.append(time.perf_counter())

    worker = threading.Thread(target=shade)
    ticks = []
    worker.start()
    while worker.is_alive():
        ticks.append(time.perf_counter())
        time.sleep(0)
    worker.join()
    inside = sum(span[0] < t < span[1] for t in ticks)
    assert inside >= 10, (inside, span[1] - span[0])


# ------------------------------------------------------------------------------------------
# torch.compile
# ------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_compiled_layer_gives_the_eager_result():
    """``torch.compile(layer)`` without gradients: the ops are traced through their fake
    implementations into the compiled graphs, and the images are the eager ones."""
    from torch._dynamo.testing import CompileCounterWithBackend
    size = 24
    focal, centre = (size - 2) / math.radians(190), (size - 1) / 2
    camera = ot.Camera("equidistant", torch.tensor([focal, focal, centre, centre]), (size, size),
                       fov=math.radians(190))
    layer = ot.OmniProjection(camera, 8)
    cube = torch.rand(2, 6, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    rotation = make_rotation(2, f32)
    backend = CompileCounterWithBackend("inductor")
    torch._dynamo.reset()
    try:
        with torch.no_grad():
            expect = [layer(cube), layer(cube, rotation)]
            compiled = torch.compile(layer, backend=backend)
            got = [compiled(cube), compiled(cube), compiled(cube, rotation)]
    finally:
        torch._dynamo.reset()
    for (image, valid), (eager, eager_valid) in zip(got, [expect[0], *expect]):
        assert torch.equal(image, eager) and torch.equal(valid, eager_valid)
    traced = " ".join(str(g.graph) for g in backend.graphs)
    assert "omniscape_torch.sample_lut" in traced and "omniscape_torch.sample_rays" in traced


# ------------------------------------------------------------------------------------------
# The build
# ------------------------------------------------------------------------------------------
def test_name_holds_a_hash_of_the_cpu_flags_and_the_sources_not_their_path(monkeypatch,
                                                                           tmp_path):
    name = extension.name()
    assert name.startswith("omniscape_torch_kernels_") and name == extension.name()
    # the same sources in another checkout: the same name, the same library
    copies = []
    for source in extension.SOURCES:
        copies.append(tmp_path / "checkout" / source.name)
        copies[-1].parent.mkdir(exist_ok=True)
        copies[-1].write_bytes(source.read_bytes())
    monkeypatch.setattr(extension, "SOURCES", tuple(copies))
    assert extension.name() == name
    # another CPU, or a changed source (either of them): another name
    names = {name}
    for cpu in ("flags : fpu sse2 avx512f", "flags : fpu sse2"):
        with monkeypatch.context() as scope:
            scope.setattr(extension, "_cpu", lambda: cpu)
            names.add(extension.name())
    for copy in copies:
        data = copy.read_bytes()
        copy.write_bytes(data + b"\n")
        names.add(extension.name())
        copy.write_bytes(data)
    assert len(names) == 1 + 2 + len(copies) and extension.name() == name


def test_built_in_torchs_extension_cache_from_copies_of_the_sources():
    """The library lives where ``cpp_extension`` keeps extensions ($TORCH_EXTENSIONS_DIR,
    default ``~/.cache/torch_extensions``), with the speed and exactness flags, built from
    copies of the sources in its own folder (the same paths for every checkout)."""
    from torch.utils import cpp_extension
    ops()
    (path,) = extension._LOADED
    folder = Path(cpp_extension._get_build_directory(extension.name(), False))
    assert Path(path).parent == folder and Path(path).name.startswith(extension.name())
    build = (folder / "build.ninja").read_text()
    for flag in (*extension.CFLAGS, *extension.face_case_flags()):
        assert flag in build
    for source in extension.SOURCES:
        assert (folder / source.name).read_bytes() == source.read_bytes()
        # the .cpp files compiled from there (the header is included by them, beside them)
        assert (str(folder / source.name) in build) == (source.suffix == ".cpp")
    assert str(extension.SOURCES[0].parent) not in build


def test_every_file_of_the_sources_folder_is_a_source_and_every_include_one_of_them():
    """Every header and ``.cpp`` in ``csrc/`` is in SOURCES (the name's hash, the copies in the
    build folder, package_data's globs), and a quoted include names one of them: a header left
    out would be missing from the build folder, or changed without a rebuild."""
    folder = extension.SOURCES[0].parent
    on_disk = {p.name for p in folder.iterdir() if p.suffix in (".h", ".cpp")}
    names = [p.name for p in extension.SOURCES]
    assert sorted(names) == sorted(on_disk) and len(set(names)) == len(names)
    included = {m for path in extension.SOURCES
                for m in re.findall(r'^#include "([^"]+)"', path.read_text(), re.M)}
    built = extension._sources()   # the sources and the headers generated from Python
    assert set(built) - set(names) == {"os_layout.h"}
    assert included and included <= {n for n in built if n.endswith(".h")}
    for path in extension.SOURCES:   # each under the 1,200 lines of a C++ file
        assert path.read_text().count("\n") <= 1200, path.name
    package_data = (ROOT / "setup.cfg").read_text()
    assert "render/csrc/*.cpp, render/csrc/*.h" in package_data


def test_a_build_says_what_it_compiles_as_it_goes(monkeypatch, tmp_path):
    """A build names the sources it compiles (not one compiled before the build was
    interrupted), says as each is compiled, as ninja's log in the build folder records it, and
    between those, every heartbeat, the time so far and what is still compiling, then linking;
    the first line gives the measured range. cpp_extension.load stands in for ninja here (the
    slow tier's builds run the real one)."""
    from torch.utils import cpp_extension
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(extension, "_HEARTBEAT_S", 0.05)
    monkeypatch.setattr(extension, "_check_compiler", lambda: None)
    monkeypatch.setattr(extension, "_ninja_on_path", contextlib.nullcontext)
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    folder = Path(cpp_extension._get_build_directory(extension.name(), False))
    # an interrupted build: the town's object is there, newer than the sources
    extension._copy_sources(extension._sources(), folder)
    later = time.time() + 10
    (folder / "town_shade.o").write_bytes(b"")
    os.utime(folder / "town_shade.o", (later, later))
    log = folder / ".ninja_log"
    log.write_text("# ninja log v7\n0\t13000\t1\ttown_shade.o\t71fa9267aff165b0\n")

    def shown(text):
        deadline = time.monotonic() + 20
        while text not in err.getvalue():
            assert time.monotonic() < deadline, (text, err.getvalue())
            time.sleep(0.005)

    def ninja(name, sources, build_directory, **kwargs):
        assert sorted(Path(s).name for s in sources) == [
            "fastimage.cpp", "fastsample.cpp", "town_shade.cpp"]
        assert Path(build_directory) == folder
        shown(" s: still compiling fastsample.cpp, fastimage.cpp ...\n")
        with open(log, "a") as file:   # as ninja records a finished edge
            file.write("0\t32288\t2\tfastimage.o\tbadfe68571662616\n")
        shown("compiled fastimage.cpp in 32 s (1 of 2)\n")
        shown(" s: still compiling fastsample.cpp ...\n")
        with open(log, "a") as file:
            file.write("0\t34842\t3\tfastsample.o\t91c58560ecce2428\n0\t1")   # and a part
        shown("compiled fastsample.cpp in 35 s (2 of 2)\n")
        shown(" s: linking ...\n")
        (folder / f"{name}.so").write_bytes(b"")
        return str(folder / f"{name}.so")

    monkeypatch.setattr(cpp_extension, "load", ninja)
    assert extension._build() == str(folder / f"{extension.name()}.so")
    lines = err.getvalue().splitlines()
    assert lines[0].startswith(BUILDING) and "40-220 s on 2 cores" in lines[0], lines
    assert lines[1] == "omniscape_torch: compiling fastsample.cpp, fastimage.cpp", lines
    assert lines[-1].startswith(BUILT) and "town_shade" not in err.getvalue()
    assert all(re.fullmatch(r"omniscape_torch: (compiled \w+\.cpp in \d+ s \(\d of 2\)|"
                            r"\d+ s: (still compiling [\w., ]+|linking) \.\.\.)", line)
               for line in lines[2:-1]), lines
    assert [line for line in lines if "compiled" in line] == [
        "omniscape_torch: compiled fastimage.cpp in 32 s (1 of 2)",
        "omniscape_torch: compiled fastsample.cpp in 35 s (2 of 2)"]
    assert not any(t.name == "omniscape_torch build progress" for t in threading.enumerate())


def test_no_module_of_the_package_imports_ctypes():
    """The package's native code is the one torch extension: no ctypes (nor a second build)."""
    package = ROOT / "omniscape_torch"
    scanned = 0
    for path in package.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        scanned += 1
        if "ctypes" not in text:
            continue
        for node in ast.walk(ast.parse(text)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n == "ctypes" or n.startswith("ctypes.") for n in names), path
    assert scanned > 40


def test_ninja_beside_python_goes_first_on_the_path_and_comes_off(monkeypatch, tmp_path):
    """The ninja installed with this Python runs, for the build only: not on the PATH, or
    another on the PATH (ninja versions disagree on what is out of date)."""
    for name in ("venv", "system"):
        (tmp_path / name).mkdir()
        ninja = tmp_path / name / "ninja"
        ninja.write_text(f"#!/bin/sh\necho {name}\n")
        ninja.chmod(0o755)
    monkeypatch.setattr(extension, "_ninja_folders", lambda: [str(tmp_path / "venv")])

    def version():
        return subprocess.run(["ninja", "--version"], capture_output=True, text=True).stdout

    for path in (str(tmp_path / "empty"), str(tmp_path / "system")):
        monkeypatch.setenv("PATH", path)
        with extension._ninja_on_path():
            assert version() == "venv\n"
        assert os.environ["PATH"] == path
        with pytest.raises(KeyError):   # restored when the build fails too
            with extension._ninja_on_path():
                raise KeyError("build failed")
        assert os.environ["PATH"] == path
    monkeypatch.setenv("PATH", str(tmp_path / "venv"))   # already first: the PATH as it is
    with extension._ninja_on_path():
        assert os.environ["PATH"] == str(tmp_path / "venv")
    monkeypatch.delenv("PATH")
    with extension._ninja_on_path():
        assert os.environ["PATH"].startswith(str(tmp_path / "venv"))
    assert "PATH" not in os.environ
    monkeypatch.setattr(extension, "_ninja_folders", lambda: [])   # none with Python: PATH's
    monkeypatch.setenv("PATH", str(tmp_path / "system"))
    with extension._ninja_on_path():
        assert version() == "system\n" and os.environ["PATH"] == str(tmp_path / "system")
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    with pytest.raises(RuntimeError, match="ninja is not installed.*pip install ninja"):
        with extension._ninja_on_path():
            pass


#: A process that loads the ops and samples a cube; prints its checksum and whether its PATH
#: came back unchanged.
CHILD = textwrap.dedent("""
    import os, sys, warnings
    warnings.simplefilter("error")
    import torch
    from omniscape_torch.render.kernels import cube as fast
    from omniscape_torch.render.kernels import available
    path = os.environ.get("PATH")
    cube = torch.rand(2, 6, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    grid = torch.rand(1, 5, 7, 2, generator=torch.Generator().manual_seed(1)) * 2.2 - 1.1
    image = fast.sample_cube(cube, grid, pad=1)
    print(float(image.double().sum()), os.environ.get("PATH") == path, available())
    from omniscape_torch.render.kernels import build as extension
    print(extension._LOADED[0])
""")

#: What a build prints (stderr), as it starts and when it is done.
BUILDING = "omniscape_torch: building the C++ kernels"
BUILT = "omniscape_torch: the C++ kernels built in"


def _mirror_path_without_ninja(folder: Path) -> str:
    """A PATH of one folder linking every program on this PATH but ninja."""
    folder.mkdir()
    for entry in os.environ.get("PATH", "").split(os.pathsep):
        if not os.path.isdir(entry):
            continue
        for program in os.scandir(entry):
            target = folder / program.name
            if program.name != "ninja" and not target.exists():
                target.symlink_to(program.path)
    return str(folder)


@pytest.mark.slow
def test_loads_with_ninja_installed_beside_python_but_not_on_the_path(tmp_path):
    """``.venv/bin/python -m pytest`` without activating the virtualenv: ninja is in
    ``.venv/bin``, not on the PATH; the extension still builds or loads (a new process), and
    the PATH is the same afterwards."""
    if not any(os.access(os.path.join(f, "ninja"), os.X_OK) for f in extension._ninja_folders()):
        pytest.skip("ninja is not installed beside this Python (pip install ninja)")
    env = {**os.environ, "PATH": _mirror_path_without_ninja(tmp_path / "bin")}
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True,
                          text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    total, path_kept, available, _ = done.stdout.split()
    assert path_kept == "True" and available == "True"


@pytest.mark.slow
def test_concurrent_first_uses_build_once(tmp_path):
    """Two processes using the sampler for the first time on a machine at once (e.g. two
    training scripts, or DataLoader workers): one builds under cpp_extension's lock, the other
    waits and loads the same library; a third process later loads it without building."""
    env = {**os.environ, "TORCH_EXTENSIONS_DIR": str(tmp_path / "cache")}
    children = [subprocess.Popen([sys.executable, "-c", CHILD], env=env, cwd=ROOT, text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                for _ in range(2)]
    outputs = [child.communicate(timeout=600) for child in children]
    for child, (stdout, stderr) in zip(children, outputs):
        assert child.returncode == 0, stderr[-3000:]
        # a first use says so, once, as the build starts, and once more when it is done
        assert stderr.count(BUILDING) == stderr.count(BUILT) <= 1, stderr[-3000:]
    assert outputs[0][0] == outputs[1][0] and outputs[0][0].split()[1:3] == ["True", "True"]
    assert any(BUILT in stderr for _, stderr in outputs)
    # and what it compiles as it goes, from ninja's log: each source once as it is compiled
    # (the waiting process follows the same log)
    built = next(stderr for _, stderr in outputs if "omniscape_torch: compiling" in stderr)
    for source in ("fastsample.cpp", "fastimage.cpp", "town_shade.cpp"):
        assert len(re.findall(rf"omniscape_torch: compiled {source} in \d+ s", built)) == 1, built
    (folder,) = (tmp_path / "cache").iterdir()
    assert folder.name == extension.name() and not (folder / "lock").exists()
    (library,) = folder.glob("*.so")
    assert outputs[0][0].split()[3] == str(library)
    stamp = library.stat().st_mtime_ns
    again = subprocess.run([sys.executable, "-c", CHILD], env=env, cwd=ROOT, text=True,
                           capture_output=True, timeout=600)
    assert again.returncode == 0 and again.stdout == outputs[0][0]
    assert "omniscape_torch" not in again.stderr, again.stderr   # a load says nothing
    assert library.stat().st_mtime_ns == stamp and list(folder.glob("*.so")) == [library]
    # and the image is this process's
    cube = torch.rand(2, 6, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    grid = torch.rand(1, 5, 7, 2, generator=torch.Generator().manual_seed(1)) * 2.2 - 1.1
    assert float(outputs[0][0].split()[0]) == float(
        fastsample.sample_cube(cube, grid, pad=1).double().sum())


@pytest.mark.slow   # a process of its own: about 5 s
def test_a_checkout_elsewhere_loads_the_same_library_without_a_build(tmp_path):
    """Another checkout (or install) of the same sources finds the library that this one
    built and loads it: no build, nothing printed, the same file."""
    ops()
    (library,) = extension._LOADED
    stamp = os.stat(library).st_mtime_ns
    checkout = tmp_path / "checkout"
    shutil.copytree(ROOT / "omniscape_torch", checkout / "omniscape_torch",
                    ignore=shutil.ignore_patterns("__pycache__"))
    child = CHILD.replace("print(extension._LOADED[0])",
                          "print(extension._LOADED[0], extension.__file__)")
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True,
                          cwd=checkout, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    *_, loaded, module = done.stdout.split()
    assert Path(module).is_relative_to(checkout)   # the copy's package ran
    assert loaded == library and os.stat(library).st_mtime_ns == stamp
    assert "omniscape_torch" not in done.stderr, done.stderr


def test_without_a_compiler_one_warning_for_the_sampler_and_the_town(monkeypatch, tmp_path):
    """Nothing built and no compiler: the one build fails once, with one warning that says what
    falls back (the fast sampler to grid_sample, the town to its torch shading), and the town
    renders the same labels and depths (colours within float32 roundings)."""
    town = Town(0)
    pose = torch.tensor([0.0, -1.2, 0.0])
    fast = town.render_cubemap(pose, face_size=16)
    monkeypatch.setattr(extension, "_STATE", {})
    monkeypatch.setattr(extension, "_LOADED", [])   # as in a new process: nothing loaded yet
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "cache"))   # nothing built
    monkeypatch.setenv("CXX", "no-such-compiler-here")
    with pytest.warns(UserWarning, match="C\\+\\+ kernels could not be built") as caught:
        slow = town.render_cubemap(pose, face_size=16)
        assert not available()
        slow_again = town.render_cubemap(pose, face_size=16)
    messages = [str(w.message) for w in caught if "omniscape_torch" in str(w.message)]
    assert len(messages) == 1 and "no-such-compiler-here" in messages[0], messages
    assert "fast sampler is unavailable" in messages[0] and "town shades with torch" in messages[0]
    for key in ("labels", "depth", "range"):
        assert torch.equal(slow[key], fast[key]) and torch.equal(slow_again[key], fast[key])
    torch.testing.assert_close(slow["rgb"], fast["rgb"], rtol=0, atol=1e-6)
