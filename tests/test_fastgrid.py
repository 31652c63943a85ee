"""Tests of ``cubemap.grid``: the grid maths, eager and compiled, against the definitions.

The oracle is :func:`oracle`: ``einsum``, then ``cubemap.ray_to_face`` and ``face_uv_to_grid``
(the face table's gathers; themselves tested against DESIGN.md in ``test_cubemap.py``), not
the selection form under test.
The fused maths is checked first eagerly (cheap, every case), then compiled on tiny inputs, since
compilation dominates the run time (seconds per kernel; inductor caches them on disk).
"""

from __future__ import annotations

import itertools
import warnings

import pytest
import torch

from omniscape_torch.cubemap import face_uv_to_grid, ray_to_face
from omniscape_torch.cubemap import grid as fg

f32, f64 = torch.float32, torch.float64
FACE, PAD = 8, 1


def oracle(rays: torch.Tensor, rotation: torch.Tensor | None, face_size: int, pad: int, *,
           dtype: torch.dtype | None = None) -> torch.Tensor:
    """The definition of ``rotated_rays_to_grid``: the rotation by ``einsum`` in the rays'
    dtype, then ``ray_to_face`` and ``face_uv_to_grid`` in ``dtype``."""
    rays = rays.unsqueeze(0) if rays.dim() == 3 else rays
    if rotation is not None:
        rotation = rotation.unsqueeze(0) if rotation.dim() == 2 else rotation
        rays = torch.einsum("bij,bhwj->bhwi", rotation.to(rays.dtype), rays)
    face, uv = ray_to_face(rays.to(dtype or rays.dtype), face_size)
    return face_uv_to_grid(face, uv, face_size, pad)


def tie_rays(dtype) -> torch.Tensor:
    """``(345, 3)``: every ray with components in {-2, -1, -0.5, 0, 0.5, 1, 2} (face centres,
    edges and corners of the cube: exact ties of the dominant axis, and the zero ray), and two
    with negative zeros."""
    vals = (-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)
    ties = torch.tensor(list(itertools.product(vals, repeat=3)), dtype=dtype)  # [343, 3]
    signed_zeros = torch.tensor([[-0.0, 0.0, -0.0], [-0.0, -1.0, 1.0]], dtype=dtype)
    return torch.cat([ties, signed_zeros])


def signed_permutations(dtype) -> torch.Tensor:
    """``(48, 3, 3)``: every signed permutation matrix (exact rotations and reflections: with
    them the rotated rays are exact, so the grid must be identical bit for bit)."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = torch.zeros(3, 3, dtype=dtype)
            for i, (j, s) in enumerate(zip(perm, signs)):
                m[i, j] = s
            mats.append(m)
    return torch.stack(mats)


def random_rotations(n: int, dtype, seed: int = 0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=f64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1)).unsqueeze(-2)
    return q.to(dtype)


def random_rays(shape, dtype, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, 3, generator=gen, dtype=dtype)


# ------------------------------------------------------------------------------------------
# The fused maths, eagerly: every case, no compilation
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [f32, f64])
@pytest.mark.parametrize("size,pad", [(8, 1), (5, 2), (1, 0), (512, 1)])
def test_fused_maths_without_rotation_is_the_reference_bit_for_bit(dtype, size, pad):
    rays = torch.cat([tie_rays(dtype), random_rays((200,), dtype)]).reshape(1, 1, -1, 3)
    expected = oracle(rays, None, size, pad)
    got = fg._fused_plain(rays, size, pad, dtype)
    assert got.dtype == dtype and got.shape == expected.shape
    assert torch.equal(got, expected)


@pytest.mark.parametrize("dtype", [f32, f64])
def test_fused_maths_with_exact_rotations_keeps_ties_bit_for_bit(dtype):
    rays = tie_rays(dtype).reshape(1, 15, 23, 3)
    rot = signed_permutations(dtype)  # [48, 3, 3]
    expected = oracle(rays, rot, FACE, PAD)
    got = fg._fused_rotated(rays, rot, FACE, PAD, dtype)
    assert got.shape == (48, 15, 23, 2)
    assert torch.equal(got, expected)


def test_fused_maths_with_random_rotations_matches_to_rounding():
    rays = random_rays((1, 16, 20), f32)
    rot = random_rotations(5, f32)
    expected = oracle(rays, rot, 512, 1)
    got = fg._fused_rotated(rays, rot, 512, 1, f32)
    # float32 rounding of the rotated rays (einsum may sum in another order); a different
    # face would differ by a face's height in the atlas (1/3 in gy)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------------
# Compiled: tiny inputs, few kernels
# ------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_compiled_without_rotation_is_the_reference_bit_for_bit():
    rays = torch.cat([tie_rays(f32), random_rays((105,), f32)]).reshape(1, 3, 150, 3)
    got = fg.rotated_rays_to_grid(rays, None, FACE, PAD)
    assert fg.compile_failures() == {}
    assert torch.equal(got, oracle(rays, None, FACE, PAD))
    # one kernel for every shape and face size (dynamic shapes): (H, W, 3) rays, another F
    rays3 = random_rays((5, 7), f32)
    got = fg.rotated_rays_to_grid(rays3, None, 16, 2)
    assert got.shape == (1, 5, 7, 2)
    assert torch.equal(got, oracle(rays3, None, 16, 2))


@pytest.mark.slow
def test_compiled_rotation_broadcasting_ties_and_rounding():
    rays = tie_rays(f32).reshape(15, 23, 3)  # (H, W, 3), shared by every rotation
    rot = signed_permutations(f32)
    got = fg.rotated_rays_to_grid(rays, rot, FACE, PAD)
    assert got.shape == (48, 15, 23, 2)
    assert torch.equal(got, oracle(rays, rot, FACE, PAD))
    # a batch of rays, one rotation per sample, random rotations: equal to rounding
    rays_b = random_rays((3, 6, 10), f32)
    rot_b = random_rotations(3, f32)
    torch.testing.assert_close(fg.rotated_rays_to_grid(rays_b, rot_b, 512, 1),
                               oracle(rays_b, rot_b, 512, 1),
                               rtol=0, atol=1e-6)
    assert fg.compile_failures() == {}


@pytest.mark.slow
def test_compiled_gradients_float64_match_the_eager_path():
    rays = torch.cat([tie_rays(f64), random_rays((15,), f64)]).reshape(2, 9, 20, 3)
    rot = random_rotations(2, f64, seed=5)
    gen = torch.Generator().manual_seed(7)
    weight = torch.randn(2, 9, 20, 2, generator=gen, dtype=f64)
    grads = []
    for compiled in (True, False):
        r = rays.clone().requires_grad_(True)
        q = rot.clone().requires_grad_(True)
        grid = fg.rotated_rays_to_grid(r, q, FACE, PAD, compiled=compiled)
        assert grid.requires_grad and grid.dtype == f64
        (grid * weight).sum().backward()
        grads.append((grid.detach(), r.grad, q.grad))
    assert fg.compile_failures() == {}
    (g_c, dr_c, dq_c), (g_e, dr_e, dq_e) = grads
    torch.testing.assert_close(g_c, g_e, rtol=0, atol=1e-12)
    assert torch.isfinite(dr_c).all() and torch.isfinite(dq_c).all()
    torch.testing.assert_close(dr_c, dr_e, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(dq_c, dq_e, rtol=1e-10, atol=1e-10)
    # no graph without grad mode, even for inputs that require grad
    with torch.no_grad():
        out = fg.rotated_rays_to_grid(rays.requires_grad_(True), rot, FACE, PAD)
    assert not out.requires_grad
    torch.testing.assert_close(out, g_c, rtol=0, atol=0)


# ------------------------------------------------------------------------------------------
# Fallback and checks
# ------------------------------------------------------------------------------------------

@pytest.fixture
def fresh_cache(monkeypatch):
    """An empty compile cache for the test, the real one restored afterwards."""
    monkeypatch.setattr(fg, "_COMPILED", {})
    monkeypatch.setattr(fg, "_FAILURES", {})


def test_compiled_false_is_the_reference():
    rays = tie_rays(f64).reshape(1, 15, 23, 3)
    rot = random_rotations(3, f64)
    assert torch.equal(fg.rotated_rays_to_grid(rays, rot, FACE, PAD, compiled=False),
                       oracle(rays, rot, FACE, PAD))


def test_compile_unavailable_falls_back_and_warns_once(fresh_cache, monkeypatch):
    def broken_compile(*args, **kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(fg.torch, "compile", broken_compile)
    rays = tie_rays(f32).reshape(1, 15, 23, 3)
    rot = random_rotations(2, f32)
    expected = oracle(rays, rot, FACE, PAD)
    with pytest.warns(UserWarning, match="torch.compile failed.*no compiler here") as rec:
        got = fg.rotated_rays_to_grid(rays, rot, FACE, PAD)
    assert rec[0].filename == __file__  # points at the caller
    assert torch.equal(got, expected)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # remembered: no second warning, no second attempt
        assert torch.equal(fg.rotated_rays_to_grid(rays, rot, FACE, PAD), expected)
    (key, why), = fg.compile_failures().items()
    assert key == ("grid", True, f32, f32, "cpu", True) and "no compiler here" in why


def test_compiled_kernel_failing_at_call_falls_back_and_warns_once(fresh_cache, monkeypatch):
    calls = []

    def failing_kernel(*args):
        calls.append(1)
        raise RuntimeError("inductor: C++ compile error")

    monkeypatch.setattr(fg.torch, "compile", lambda fn, **kw: failing_kernel)
    rays = tie_rays(f32).reshape(1, 15, 23, 3)
    expected = oracle(rays, None, FACE, PAD)
    with pytest.warns(UserWarning, match="C\\+\\+ compile error") as rec:
        assert torch.equal(fg.rotated_rays_to_grid(rays, None, FACE, PAD), expected)
    assert rec[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.equal(fg.rotated_rays_to_grid(rays, None, FACE, PAD), expected)
    assert len(calls) == 1


def uncompiled_grid_failing_vjp(fn, **kwargs):
    """A stand-in for ``torch.compile``: the forward maths runs eagerly (no compilation), the
    backward kernel fails when called."""
    if fn.__name__.startswith("_vjp"):
        def failing(*args):
            raise RuntimeError("backward kernel broken")
        return failing
    return fn


def test_backward_kernel_failure_falls_back_to_eager_gradients(fresh_cache, monkeypatch):
    monkeypatch.setattr(fg.torch, "compile", uncompiled_grid_failing_vjp)
    rays = random_rays((2, 3, 4), f64).requires_grad_(True)
    rot = random_rotations(1, f64).requires_grad_(True)  # broadcast over the rays' batch
    grid = fg.rotated_rays_to_grid(rays, rot, FACE, PAD)
    with pytest.warns(UserWarning, match="vjp.*backward kernel broken"):
        grid.sum().backward()
    r, q = rays.detach().requires_grad_(True), rot.detach().requires_grad_(True)
    oracle(r, q, FACE, PAD).sum().backward()
    assert torch.equal(rays.grad, r.grad) and torch.equal(rot.grad, q.grad)
    assert set(k[0] for k in fg.compile_failures()) == {"vjp"}


def test_autograd_function_gradcheck_and_double_backward(fresh_cache, monkeypatch):
    # The autograd plumbing, with the kernels run eagerly: gradcheck (retain_graph, many
    # backward calls), one input only requiring grad, and double backward (create_graph).
    monkeypatch.setattr(fg.torch, "compile", lambda fn, **kwargs: fn)
    rays = random_rays((2, 3), f64)
    rays = rays / rays.abs().amax(-1, keepdim=True)  # away from the zero ray
    rot = random_rotations(2, f64, seed=4)
    assert torch.autograd.gradcheck(
        lambda r, q: fg.rotated_rays_to_grid(r, q, FACE, PAD),
        (rays.clone().requires_grad_(True), rot.clone().requires_grad_(True)))
    q = rot.clone().requires_grad_(True)
    (dq,) = torch.autograd.grad(fg.rotated_rays_to_grid(rays, q, FACE, PAD).square().sum(), q,
                                create_graph=True)
    q2 = rot.clone().requires_grad_(True)
    (dq2,) = torch.autograd.grad(
        oracle(rays, q2, FACE, PAD).square().sum(), q2,
        create_graph=True)
    torch.testing.assert_close(dq, dq2)
    torch.testing.assert_close(torch.autograd.grad(dq.sum(), q)[0],
                               torch.autograd.grad(dq2.sum(), q2)[0])
    assert fg.compile_failures() == {}


def test_dtype_argument_rotates_in_the_rays_dtype():
    rays = random_rays((2, 3, 5), f64)
    rot = random_rotations(2, f64)
    got = fg.rotated_rays_to_grid(rays, rot, 512, 1, dtype=f32, compiled=False)
    expected = fg._fused_rotated(rays, rot, 512, 1, f32)  # the fused maths, eagerly
    assert got.dtype == f32 and torch.equal(got, expected)


@pytest.mark.parametrize("rays,rot,match", [
    (torch.zeros(4, 3), None, "shape"),
    (torch.zeros(2, 3, 4, 2), None, r"\(\.\.\., 3\)"),
    (torch.zeros(2, 3, 4, 3, dtype=torch.int64), None, "floating"),
    (torch.zeros(2, 3, 4, 3), torch.eye(3).expand(3, 3, 3), "broadcast"),
    (torch.zeros(3, 4, 3), torch.zeros(2, 3, 4), "rotation"),
])
def test_bad_inputs_raise(rays, rot, match):
    with pytest.raises((ValueError, TypeError), match=match):
        fg.rotated_rays_to_grid(rays, rot, FACE, PAD)
