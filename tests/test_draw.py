"""The one draw of both augmentation modules (`render/kernels/draw.py`): one stream layout, one
Python draw, and its C++ twin (`frame_lens`) checked against it."""

from __future__ import annotations

import math

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.augment import RandomOmniCamera, RandomReproject
from omniscape_torch.render.kernels import draw, layout

DEG = math.pi / 180
KEYS = ("camera_params", "num_params", "fov", "blind_fov", "yaw", "pitch", "roll", "applied",
        "rotation")


@pytest.mark.parametrize("models", [("equidistant",), ("kannala_brandt", "eucm", "unified"),
                                    draw.FISHEYE_MODELS])
def test_both_modules_draw_the_same_fisheyes(models):
    """One draw: with the same seed, ranges and output size, `RandomOmniCamera`'s fisheyes and
    `RandomReproject`'s (unframed) are the same cameras and attitudes, bit for bit."""
    common = dict(fisheye_models=models, fov_range=(150 * DEG, 195 * DEG), center_jitter=2.0,
                  roll_range=(-0.3, 0.3), pitch_range=(-0.1, 0.1), yaw_range=(-0.2, 0.2),
                  p=0.6, seed=11, focal_scale_range=(0.9, 1.1))
    omni = RandomOmniCamera((40, 48), 16, **common).forward_parameters(9)
    persp = RandomReproject((40, 48), **common).forward_parameters(9)
    assert omni["model"] == persp["model"]
    for key in KEYS:
        assert torch.equal(omni[key], persp[key]), key
    assert len(set(omni["model"])) > 1 or len(models) == 1   # several models drawn


def test_each_family_reads_its_own_rows_of_the_stream():
    """Changing one family's rows of the uniforms changes what it draws and nothing else (the
    documented layout `STREAM`)."""
    spec = RandomOmniCamera((32, 32), 16, mode="mixed", fisheye_models=("kannala_brandt",),
                            seed=0)._spec()
    n = 5
    u = torch.rand(draw.STREAM_WIDTH * n, generator=torch.Generator().manual_seed(3),
                   dtype=torch.float64)
    base = draw.draw_cameras(spec, u, n)
    start, rows = draw.STREAM["attitude"]
    v = u.clone()
    v[start * n:(start + rows) * n] = 0.5
    turned = draw.draw_cameras(spec, v, n)
    assert torch.equal(turned["camera_params"], base["camera_params"])
    assert torch.equal(turned["fov"], base["fov"]) and turned["model"] == base["model"]
    on = base["applied"]
    assert bool(on.any()) and not torch.equal(turned["yaw"][on], base["yaw"][on])
    # every row is read by some family, none by two
    covered = sorted(r for first, count in draw.STREAM.values() for r in range(first, first + count))
    assert covered == list(range(draw.STREAM_WIDTH))


@pytest.mark.parametrize("jitter,same,p", [(0.0, False, 1.0), (2.0, False, 0.5),
                                           (0.0, True, 1.0)])
def test_the_cpp_twin_is_the_python_draw(jitter, same, p):
    """`frame_lens` (one lens with a table, framed to a pinhole source) against the Python draw
    on the same uniforms: every key equal but the rotations (within 1e-15) and the focals
    (1e-12, relative), which go through the C++ library's cosines."""
    if not ot.render.kernels.available():
        pytest.skip("no C++ kernels here")
    K = torch.tensor([30.0, 30.0, 23.5, 15.5], dtype=torch.float64)

    def params(backend):
        aug = RandomReproject((48, 56), coverage_range=(0.4, 0.9), center_jitter=jitter,
                              same_on_batch=same, p=p, seed=4, backend=backend)
        return aug.forward_parameters(7, intrinsics=K, source_size=(32, 48))

    cpp, ref = params("cpp"), params("torch")
    assert cpp.keys() == ref.keys() and cpp["model"] == ref["model"]
    for key in ("fov", "yaw", "pitch", "roll", "applied", "coverage", "num_params",
                "blind_fov"):
        assert torch.equal(cpp[key], ref[key]), key
    torch.testing.assert_close(cpp["rotation"], ref["rotation"], atol=1e-15, rtol=0)
    torch.testing.assert_close(cpp["camera_params"], ref["camera_params"], rtol=1e-12, atol=0)


def test_the_generated_header_holds_the_stream_and_the_rotation():
    """The C++ build reads the stream's rows and the rotation's entries from `layout_header`
    (generated from `STREAM` and `presets.rotation_rows`): evaluating the generated entries
    gives `yaw_pitch_roll_to_matrix`."""
    text = layout.layout_header().decode()
    for family, macro in (("fov", "FOV"), ("attitude", "ATTITUDE"), ("applied", "APPLIED"),
                          ("coverage", "COVERAGE"), ("jitter", "JITTER")):
        assert f"#define OS_DRAW_{macro} {draw.STREAM[family][0]}\n" in text
    entries = next(line for line in text.splitlines() if "OS_ROTATION_ENTRIES" in line
                   and line.startswith("#define")).split(" ", 2)[2]
    yaw, pitch, roll = 0.3, -0.2, 0.7
    values = dict(cy=math.cos(yaw), sy=math.sin(yaw), cp=math.cos(pitch), sp=math.sin(pitch),
                  cr=math.cos(roll), sr=math.sin(roll))
    got = torch.tensor(eval(entries.replace("{", "[").replace("}", "]"), {}, values),
                       dtype=torch.float64).reshape(3, 3)
    want = ot.presets.yaw_pitch_roll_to_matrix(*(torch.tensor(a, dtype=torch.float64)
                                                 for a in (yaw, pitch, roll)))
    torch.testing.assert_close(got, want, atol=1e-15, rtol=0)


def test_backend_is_checked():
    with pytest.raises(ValueError, match="backend"):
        RandomReproject((16, 16), source_fov=1.0, backend="gpu")
    with pytest.raises(ValueError, match="backend"):
        RandomOmniCamera((16, 16), 8, backend=None)
