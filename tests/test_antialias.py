"""Antialiasing (``render.antialias``) and framing (``render.framing``) of perspective sources
seen through random fisheyes (``RandomReproject``, ``ot.reproject``).

Oracles: the area average of a 1-px line grid over each output pixel, by the independent
supersampler of ``benchmarks/bench_antialias.py`` (closed-form equidistant and pinhole
projections, 16 x 16 nearest samples a pixel); the valid share measured from ``valid``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.render.kernels import framing
from omniscape_torch.augment import RandomReproject

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_antialias as ba  # noqa: E402

DEG = math.pi / 180
#: Cityscapes' geometry at a quarter: 256 x 512, fx = fy = 2262 / 4.
SRC = (256, 512)
FOCAL = 2262 / 4
K = torch.tensor([FOCAL, FOCAL, (SRC[1] - 1) / 2, (SRC[0] - 1) / 2], dtype=torch.float64)


def test_prefilter_matches_the_area_average_of_a_line_grid():
    """At the defaults (framed to 50-90 % of the output) a 1-px grid of period 4 (Cityscapes
    at an eighth): point samples alias (< 23 dB against the area average), the prefilter
    reaches >= 25 dB and gains more than 8 dB on every draw; so does no cheaper order of the
    same work (the source reduced by an area filter first, then point samples, as
    albumentations resizes then distorts: < 23 dB at every factor); labels are the nearest
    texel either way (never blended)."""
    res = ba.compare((64, 64), (128, 256, FOCAL / 2), 4, 2, seed=5)
    area = [name for name in res if name.startswith("area")]
    assert all(v < 23 for name in ["off", *area] for v in res[name]), res
    assert len(area) == len(ba.AREA_FACTORS) or ba.cv2 is None
    assert all(v >= 25 for v in res["on"]), res
    assert min(b - a for a, b in zip(res["off"], res["on"])) > 8
    modules = res["modules"]
    labels = torch.randint(0, 19, (2, *SRC), generator=torch.Generator().manual_seed(1))
    params = modules["on"].forward_parameters(2, intrinsics=K, source_size=SRC)
    a, b = (modules[n]({"labels": labels, "intrinsics": K}, params=params) for n in ("off", "on"))
    assert torch.equal(a["labels"], b["labels"]) and torch.equal(a["valid"], b["valid"])


@pytest.mark.parametrize("fast", [True, False])
def test_magnifying_output_is_point_sampling_bit_for_bit(fast):
    """Where no output pixel covers more than one source pixel (a 24 x 32 source into a
    128 x 128 fisheye), antialiasing changes nothing: the same tensors, both paths."""
    image = torch.rand(2, 3, 24, 32, generator=torch.Generator().manual_seed(2))
    outs = []
    for antialias in (False, True):
        aug = RandomReproject((128, 128), source_fov=60 * DEG, seed=4, antialias=antialias)
        with torch.set_grad_enabled(not fast):
            outs.append(aug(image.clone().requires_grad_(not fast)))
    assert torch.equal(outs[0]["rgb"], outs[1]["rgb"]) and torch.equal(outs[0]["valid"],
                                                                       outs[1]["valid"])
    src = ot.Camera("pinhole", [20.0, 20.0, 15.5, 11.5], (24, 32))
    dst = ot.Camera("equidistant", [60.0, 60.0, 63.5, 63.5], (128, 128))
    a, b = (ot.reproject(image, src, dst, antialias=flag)[0] for flag in (False, True))
    assert torch.equal(a, b)


def test_reproject_prefilters_a_minifying_pinhole():
    """``ot.reproject`` of a 2-px checkerboard into a pinhole 4x coarser: point samples keep
    texels (aliasing: every sample lands on a dark one), the prefilter gives the mean, 0.5,
    within 0.02 (inside the one-pixel rim, where the source ends)."""
    yy, xx = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="ij")
    board = (((yy // 2) + (xx // 2)) % 2).double()[None, None]
    src = ot.Camera("pinhole", torch.tensor([100.0, 100.0, 63.0, 63.0], dtype=torch.float64),
                    (128, 128))
    dst = ot.Camera("pinhole", torch.tensor([25.0, 25.0, 15.5, 15.5], dtype=torch.float64),
                    (32, 32))
    point, _ = ot.reproject(board, src, dst, antialias=False)
    smooth, _ = ot.reproject(board, src, dst)
    assert float((point - 0.5).abs().max()) > 0.4
    assert float((smooth - 0.5)[..., 1:-1, 1:-1].abs().max()) < 0.02   # (edges: clamped)


@pytest.mark.parametrize("models", [("equidistant",), ot.augment.FISHEYE_MODELS])
def test_drawn_coverage_is_the_valid_share(models):
    """``coverage_range``: each sample's drawn share lies in the range and its ``valid`` share
    is that share (within 0.02: pixel rounding of the region's rim), across seeds, lenses and
    attitudes; the default frames a Cityscapes-shaped source to at least half the output."""
    image = torch.zeros(6, 3, *SRC, dtype=torch.uint8)
    for seed in (0, 1):
        aug = RandomReproject((96, 96), fisheye_models=models, coverage_range=(0.3, 0.95),
                              center_jitter=4.0, seed=seed, antialias=False)
        out = aug({"rgb": image, "intrinsics": K})
        drawn = out["params"]["coverage"]
        assert bool(((drawn >= 0.3) & (drawn <= 0.95)).all())
        measured = out["valid"].double().mean((1, 2, 3))
        torch.testing.assert_close(measured, drawn, atol=0.02, rtol=0)
    default = RandomReproject((96, 96), fisheye_models=models, seed=3, antialias=False)(
        {"rgb": image, "intrinsics": K})
    assert float(default["valid"].float().mean((1, 2, 3)).min()) >= 0.5 - 0.02


@pytest.mark.parametrize("jitter,same", [(0.0, False), (3.0, False), (0.0, True)])
def test_one_call_draw_is_the_framing_steps(jitter, same):
    """The draw of one lens with a table (``frame_lens``: rotations, reach, radius and focal in
    one C++ call) gives the rotations of ``presets.rotation_rows`` and the focals of
    ``framing.reach``, the lens's radius table and ``framing.focal_for_coverage`` in turn."""
    aug = RandomReproject((64, 80), coverage_range=(0.4, 0.9), center_jitter=jitter,
                          same_on_batch=same, seed=5)
    k = K.expand(5, 4)
    params = aug.forward_parameters(5, intrinsics=k, source_size=SRC)
    cos = torch.stack([params[a] for a in ("yaw", "pitch", "roll")]).cos().numpy()
    sin = torch.stack([params[a] for a in ("yaw", "pitch", "roll")]).sin().numpy()
    rows = ot.cameras.presets.rotation_rows(cos[0], sin[0], cos[1], sin[1], cos[2], sin[2])
    want = torch.tensor([[[float(e[b]) for e in row] for row in rows] for b in range(5)],
                        dtype=torch.float64)
    torch.testing.assert_close(params["rotation"], want, atol=1e-15, rtol=0)
    half = (params["fov"] / 2).numpy()
    theta = framing.reach(want.numpy(), k.numpy(), SRC, half)
    unit = aug._unit_lens("equidistant")
    centre = params["camera_params"][:, 2:4].numpy()
    focal = framing.focal_for_coverage(unit.radius_at(theta),
                                       framing.to_edge(centre, (64, 80)),
                                       params["coverage"].numpy(), (64, 80))
    torch.testing.assert_close(params["camera_params"][:, 0], torch.from_numpy(focal),
                               rtol=1e-12, atol=0)
    assert torch.equal(params["camera_params"][:, 0], params["camera_params"][:, 1])
    assert params["model"] == ("equidistant",) * 5


@pytest.mark.parametrize("jitter,same,p", [(0.0, False, 1.0), (3.0, False, 0.5),
                                           (0.0, True, 1.0)])
def test_one_call_draw_is_the_numpy_draw(jitter, same, p):
    """The same uniforms give the same draw through the C++ op as through the NumPy steps
    (which run where the extension cannot be built): every key, the attitudes and fields of
    view exactly, the rotations and focals within the rounding of their cosines."""
    def draw(backend):
        aug = RandomReproject((64, 80), coverage_range=(0.4, 0.9), center_jitter=jitter,
                              same_on_batch=same, p=p, seed=5, backend=backend)
        return aug.forward_parameters(6, intrinsics=K, source_size=SRC)

    fast_draw = draw("cpp")
    slow = draw("torch")
    assert fast_draw.keys() == slow.keys() and fast_draw["model"] == slow["model"]
    for key in ("fov", "yaw", "pitch", "roll", "applied", "coverage", "num_params",
                "blind_fov"):
        assert torch.equal(fast_draw[key], slow[key]), key
    assert bool((~slow["applied"]).any()) == (p < 1)
    torch.testing.assert_close(fast_draw["rotation"], slow["rotation"], atol=1e-15, rtol=0)
    torch.testing.assert_close(fast_draw["camera_params"], slow["camera_params"], rtol=1e-12,
                               atol=1e-12)


def test_framing_and_antialias_arguments():
    with pytest.raises(ValueError, match="coverage_range"):
        RandomReproject((32, 32), coverage_range=(0.5, 1.5))
    with pytest.raises(ValueError, match="coverage_range"):
        RandomReproject((32, 32), coverage_range=(0.5, 0.9), focal_scale_range=(1.0, 2.0))
    with pytest.raises(TypeError, match="antialias"):
        RandomReproject((32, 32), antialias="yes")
    with pytest.raises(TypeError, match="antialias"):
        ot.reproject(torch.rand(1, 1, 8, 8), ot.presets.fisheye((8, 8)),
                     ot.presets.fisheye((8, 8)), antialias=1)
    # no source known: the inscribed circle (focal_scale_range), no coverage drawn
    params = RandomReproject((32, 32), source_fov=60 * DEG).forward_parameters(2)
    assert "coverage" not in params
