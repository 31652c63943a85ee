"""RandomOmniCamera: reproducibility, valid ranges, validity masks, gradients, pickling,
composition with kornia, DataLoader workers."""

import math
import pickle

import pytest
import torch
from torch import nn

from omniscape_torch.augment import ApplyToKey, RandomOmniCamera
from omniscape_torch.cameras import Camera
from omniscape_torch.cameras.registry import get_model
from omniscape_torch.cubemap.faces import FACES, face_rotations

SIZE, FACE = (24, 24), 16
ALL_FISHEYE = ("equidistant", "equisolid", "stereographic", "kannala_brandt")


def _batch(b=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(b, 6, 3, FACE, FACE, generator=g)
    labels = torch.randint(0, 13, (b, 6, FACE, FACE), generator=g)
    depth = 1 + 10 * torch.rand(b, 6, FACE, FACE, generator=g)
    return rgb, labels, depth


def _mixed(**kw):
    return RandomOmniCamera(SIZE, FACE, mode="mixed", fisheye_models=ALL_FISHEYE,
                            kb_distortion=0.2, center_jitter=2.0,
                            focal_scale_range=(0.9, 1.1), **kw)


def _equal(a, b):
    for key in ("rgb", "labels", "depth", "valid"):
        if not torch.equal(a[key], b[key]):
            return False
    return torch.equal(a["params"]["camera_params"], b["params"]["camera_params"]) and \
        torch.equal(a["params"]["rotation"], b["params"]["rotation"])


def test_same_seed_same_batch_different_seed_different():
    rgb, labels, depth = _batch()
    a = _mixed(seed=7)(rgb, labels, depth)
    b = _mixed(seed=7)(rgb, labels, depth)
    c = _mixed(seed=8)(rgb, labels, depth)
    assert _equal(a, b)
    assert not torch.equal(a["params"]["rotation"], c["params"]["rotation"])
    assert not torch.equal(a["rgb"], c["rgb"])
    # a call's generator overrides the module's, and leaves the module's stream untouched
    aug = _mixed(seed=7)
    d = aug(rgb, labels, depth, generator=torch.Generator().manual_seed(8))
    assert _equal(c, d)
    assert _equal(a, aug(rgb, labels, depth))


def test_successive_calls_differ():
    rgb, _, _ = _batch()
    aug = RandomOmniCamera(SIZE, FACE, seed=0)
    assert not torch.equal(aug(rgb)["params"]["rotation"], aug(rgb)["params"]["rotation"])


def test_draws_within_valid_ranges_and_render_clean():
    rgb, labels, depth = _batch(b=2)
    aug = _mixed()
    seen = set()
    deg = math.pi / 180
    for seed in range(50):
        out = aug(rgb, labels, depth, generator=torch.Generator().manual_seed(seed))
        prm = out["params"]
        for b, name in enumerate(prm["model"]):
            seen.add(name)
            p = prm["camera_params"][b, :int(prm["num_params"][b])]
            model = get_model(name)
            model.validate_params(p)
            fov = float(prm["fov"][b])
            assert float(model.max_angle(p)) > fov / 2
            if name == "unified":
                assert 200 * deg <= fov <= 230 * deg
                assert 0.7 <= float(p[4]) <= 1.0
                assert torch.all(p[5:] == 0)
            else:
                assert 160 * deg <= fov <= 200 * deg
            centre = p[2:4] - torch.tensor([(SIZE[1] - 1) / 2, (SIZE[0] - 1) / 2],
                                           dtype=p.dtype)
            assert float(centre.abs().max()) <= 2.0
            yaw, pitch, roll = (float(prm[k][b]) for k in ("yaw", "pitch", "roll"))
            assert abs(roll) <= 25 * deg and abs(pitch) <= 10 * deg and abs(yaw) <= math.pi
        R = prm["rotation"]
        eye = torch.eye(3, dtype=R.dtype).expand_as(R)
        torch.testing.assert_close(R @ R.transpose(1, 2), eye)
        assert out["valid"].flatten(1).any(1).all()
        for key in ("rgb", "depth"):
            assert torch.isfinite(out[key]).all()
        assert (out["depth"][out["valid"]] > 0).all()
        # labels are never blended
        assert set(out["labels"].unique().tolist()) <= set(labels.unique().tolist()) | {255}
        assert (out["labels"][~out["valid"][:, 0]] == 255).all()
    assert seen == set(ALL_FISHEYE) | {"unified"}


def test_valid_mask_matches_each_cameras_ray_grid():
    rgb, _, _ = _batch(b=4)
    compared = 0
    for seed in range(6):
        aug = _mixed(seed=seed)
        out = aug(rgb)
        prm = out["params"]
        for b, name in enumerate(prm["model"]):
            p = prm["camera_params"][b, :int(prm["num_params"][b])].float()
            blind = float(prm["blind_fov"][b]) or None
            cam = Camera(name, p, SIZE, fov=float(prm["fov"][b]), blind_fov=blind)
            _, valid = cam.ray_grid()
            mismatch = (valid != out["valid"][b, 0]).sum().item()
            # the Kannala-Brandt inverse iterates until every lane of the batch converges, so
            # a lone camera may differ in the last bit at the rim; exact for the closed forms
            assert mismatch <= (2 if name == "kannala_brandt" else 0), (name, mismatch)
            compared += 1
    assert compared > 0


def test_catadioptric_mount_and_p_zero():
    rgb, _, _ = _batch(b=2)
    down = face_rotations(torch.float64)[FACES.index("down")]
    out = RandomOmniCamera(SIZE, FACE, mode="catadioptric", p=0.0, seed=0)(rgb)
    prm = out["params"]
    assert not prm["applied"].any()
    torch.testing.assert_close(prm["rotation"], down.expand(2, 3, 3))
    fish = RandomOmniCamera(SIZE, FACE, p=0.0, seed=0).forward_parameters(3)
    torch.testing.assert_close(fish["rotation"], torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    # the blind cone masks the centre of a catadioptric image
    assert not out["valid"][:, 0, SIZE[0] // 2, SIZE[1] // 2].any()


def test_same_on_batch_and_replay():
    rgb, labels, _ = _batch(b=3)
    aug = _mixed(seed=3, same_on_batch=True)
    out = aug(rgb, labels)
    prm = out["params"]
    assert len(set(prm["model"])) == 1
    for key in ("camera_params", "rotation", "fov"):
        assert (prm[key] == prm[key][:1]).all()
    # identical cubemaps, identical draws -> identical images
    same = aug(rgb[:1].expand(3, -1, -1, -1, -1))
    assert (same["rgb"] == same["rgb"][:1]).all()
    # kornia-style replay of the returned parameters
    again = aug(rgb, labels, params=out["params"])
    assert torch.equal(again["rgb"], out["rgb"]) and torch.equal(again["labels"], out["labels"])


@pytest.mark.slow
def test_gradients_reach_the_cubemap():
    rgb, _, _ = _batch(b=2)
    rgb.requires_grad_(True)
    out = _mixed(seed=0)(rgb)
    out["rgb"].sum().backward()
    assert rgb.grad is not None and torch.isfinite(rgb.grad).all() and rgb.grad.abs().sum() > 0


def test_float64_and_labels_only():
    rgb, labels, depth = _batch(b=2)
    out = _mixed(seed=0)(rgb.double(), depth=depth.double())
    assert out["rgb"].dtype == torch.float64 and out["depth"].dtype == torch.float64
    lab = _mixed(seed=0)(None, labels)
    assert lab["labels"].dtype == torch.int64 and "rgb" not in lab


def test_pickle_round_trip_keeps_the_stream():
    rgb, labels, _ = _batch()
    aug = _mixed(seed=5)
    aug(rgb)   # advance the stream
    clone = pickle.loads(pickle.dumps(aug))
    assert _equal(aug(rgb, labels, torch.ones_like(labels).float()),
                  clone(rgb, labels, torch.ones_like(labels).float()))


def test_a_module_pickled_by_an_older_version_loads_and_renders():
    """The state of a module pickled before ``channels_last``, ``out_dtype`` and the generator's
    context key existed (and with the torch.Generator itself inside) loads with their defaults
    and renders as the module it was."""
    rgb, labels, _ = _batch()
    aug = _mixed(seed=5)
    aug(rgb)
    old = dict(aug.__dict__)
    for key in ("channels_last", "out_dtype", "_generator_key"):
        del old[key]
    old["_generator"] = torch.Generator()   # a copy in the same state, as unpickled
    old["_generator"].set_state(aug._generator.get_state())
    clone = RandomOmniCamera.__new__(RandomOmniCamera)
    clone.__setstate__(old)
    assert clone.channels_last is False and clone.out_dtype is None
    depth = torch.ones_like(labels).float()
    assert _equal(aug(rgb, labels, depth), clone(rgb, labels, depth))


def test_composes_with_kornia_in_sequential():
    kornia = pytest.importorskip("kornia")
    rgb, labels, depth = _batch(b=2)
    torch.manual_seed(0)   # kornia draws from the global RNG
    pipeline = nn.Sequential(
        RandomOmniCamera(SIZE, FACE, seed=0),
        ApplyToKey(kornia.augmentation.ColorJitter(0.3, 0.3, 0.3, 0.05, p=1.0)),
    )
    out = pipeline({"rgb": rgb, "labels": labels, "depth": depth})
    assert out["rgb"].shape == (2, 3, *SIZE)
    plain = RandomOmniCamera(SIZE, FACE, seed=0)(rgb, labels, depth)
    assert torch.equal(out["labels"], plain["labels"])
    assert not torch.equal(out["rgb"], plain["rgb"])
    assert (out["rgb"][~out["valid"].expand_as(out["rgb"])] == 0).all()


class _Cubes(torch.utils.data.Dataset):
    def __init__(self, aug):
        self.aug = aug
        self.rgb = _batch(b=4)[0]

    def __len__(self):
        return 4

    def __getitem__(self, i):
        return self.aug(self.rgb[i:i + 1])["params"]["rotation"][0]


def test_dataloader_workers_draw_distinct_reproducible_streams():
    # workers' streams follow PyTorch's worker seeds: a run repeats with the loader's generator
    # (tests/test_augment_workers.py: epochs, forked and spawned workers)
    def run():
        loader = torch.utils.data.DataLoader(_Cubes(RandomOmniCamera(SIZE, FACE, seed=11)),
                                             batch_size=None, num_workers=2,
                                             generator=torch.Generator().manual_seed(0))
        return torch.stack(list(loader))
    a, b = run(), run()
    assert torch.equal(a, b)
    # items 0 and 1 are the first draws of workers 0 and 1: different streams
    assert not torch.equal(a[0], a[1])


def test_rejects_ranges_outside_the_models():
    with pytest.raises(ValueError, match="fov_range"):
        RandomOmniCamera(SIZE, FACE, fisheye_models=("stereographic",),
                         fov_range=(3.0, 2 * math.pi))
    with pytest.raises(ValueError, match="cata_fov_range"):
        RandomOmniCamera(SIZE, FACE, mode="catadioptric", xi_range=(0.1, 0.5))
    with pytest.raises(ValueError, match="mode"):
        RandomOmniCamera(SIZE, FACE, mode="pinhole")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_batch_matches_cpu():
    rgb, labels, depth = _batch(b=3)
    cpu = _mixed(seed=2)(rgb, labels, depth)
    gpu = _mixed(seed=2)(rgb.cuda(), labels.cuda(), depth.cuda())
    assert gpu["rgb"].is_cuda and gpu["valid"].is_cuda
    assert torch.equal(gpu["params"]["rotation"], cpu["params"]["rotation"])   # drawn on CPU
    torch.testing.assert_close(gpu["rgb"].cpu(), cpu["rgb"], atol=1e-4, rtol=0)
    # rims may flip by a rounding of the rays; nearly all pixels agree
    assert (gpu["valid"].cpu() != cpu["valid"]).float().mean() < 0.01


def test_chunked_render_equals_whole_batch(monkeypatch):
    """On the CPU a batch is rendered a few samples at a time (``CHUNK_PIXELS``); chunks that
    split a model's samples, in and out of batch order (mixed models), change nothing."""
    from omniscape_torch.render import layer as projection
    rgb, labels, depth = _batch(b=7, seed=3)
    aug = _mixed(seed=11)
    params = aug.forward_parameters(7)
    models = list(params["model"])
    assert max(models.count(m) for m in models) > 2 and models != sorted(models)
    whole = aug(rgb, labels, depth, params=params)
    monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * SIZE[0] * SIZE[1])  # 2 samples a chunk
    chunked = aug(rgb, labels, depth, params=params)
    assert _equal(whole, chunked)
    assert bool(whole["valid"].any()) and bool((whole["labels"] != 255).any())


# ------------------------------------------------------------------ uint8 and channels-last cubes

def _u8(b=5, seed=4):
    return torch.randint(0, 256, (b, 6, 3, FACE, FACE), dtype=torch.uint8,
                         generator=torch.Generator().manual_seed(seed))


def _params_equal(a, b):
    return a["model"] == b["model"] and all(
        torch.equal(a[key], b[key]) for key in a if key != "model")


@pytest.mark.parametrize("chunked", [False, True])
def test_uint8_cube_within_a_level_of_the_float_path(chunked, monkeypatch):
    """A uint8 cube renders into uint8, rounded to nearest (half up) from the float image of
    its levels (``c.float()``) with the same seed; mixed models and chunks (indexed and sliced
    rows of preallocated outputs) included. The drawn parameters do not depend on the dtype."""
    from omniscape_torch.render import layer as projection
    if chunked:
        monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * SIZE[0] * SIZE[1])
    cube = _u8()
    _, labels, depth = _batch(b=5, seed=4)
    u8 = _mixed(seed=9)(cube, labels, depth)
    ref = _mixed(seed=9)(cube.float(), labels, depth)
    assert len(set(u8["params"]["model"])) > 1
    assert _params_equal(u8["params"], ref["params"])
    assert u8["rgb"].dtype == torch.uint8 and u8["rgb"].shape == (5, 3, *SIZE)
    expected = torch.floor(ref["rgb"] + 0.5)
    assert float((u8["rgb"].float() - expected).abs().max()) <= 1
    assert float((u8["rgb"].float() != expected).float().mean()) < 0.01
    for key in ("labels", "depth", "valid"):
        assert torch.equal(u8[key], ref[key]), key
    assert bool((u8["rgb"][~u8["valid"].expand_as(u8["rgb"])] == 0).all())
    # out_dtype: scaled to [0, 1] in the same pass
    scaled = _mixed(seed=9, out_dtype=torch.float32)(cube, labels, depth)
    assert scaled["rgb"].dtype == torch.float32
    torch.testing.assert_close(scaled["rgb"], ref["rgb"] / 255, atol=1e-6, rtol=0)
    wide = _mixed(seed=9, out_dtype=torch.float64)(cube.float() / 255)
    assert wide["rgb"].dtype == torch.float64
    torch.testing.assert_close(wide["rgb"], (ref["rgb"] / 255).double(), atol=1e-6, rtol=0)


@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
def test_channels_last_equals_channels_first_permuted(dtype, chunked, monkeypatch):
    from omniscape_torch.render import layer as projection
    if chunked:
        monkeypatch.setattr(projection, "CHUNK_PIXELS", 2 * SIZE[0] * SIZE[1])
    cube = _u8() if dtype == torch.uint8 else _batch(b=5, seed=4)[0]
    _, labels, depth = _batch(b=5, seed=4)
    last = cube.permute(0, 1, 3, 4, 2).contiguous()   # (B, 6, F, F, C), as files give faces
    first = _mixed(seed=9)(cube, labels, depth)
    out = _mixed(seed=9, channels_last=True)(last, labels, depth)
    assert out["rgb"].shape == (5, *SIZE, 3) and out["rgb"].dtype == dtype
    assert torch.equal(out["rgb"], first["rgb"].permute(0, 2, 3, 1))
    for key in ("labels", "depth", "valid"):
        assert torch.equal(out[key], first[key]), key
    # the dict form, and a labels-only call of a channels-last module
    as_dict = _mixed(seed=9, channels_last=True)({"rgb": last, "labels": labels})
    assert torch.equal(as_dict["rgb"], out["rgb"]) and torch.equal(as_dict["labels"],
                                                                   out["labels"])
    only = _mixed(seed=9, channels_last=True)(None, labels)
    assert "rgb" not in only and torch.equal(only["labels"], out["labels"])


def test_bad_channels_last_and_out_dtype_name_the_argument():
    with pytest.raises(TypeError, match="channels_last"):
        RandomOmniCamera(SIZE, FACE, channels_last="yes")
    with pytest.raises(TypeError, match="out_dtype"):
        RandomOmniCamera(SIZE, FACE, out_dtype=torch.int32)
    with pytest.raises(TypeError, match="out_dtype"):
        RandomOmniCamera(SIZE, FACE, out_dtype="float32")
    with pytest.raises(TypeError, match="out_dtype"):   # uint8 out needs a uint8 cube
        RandomOmniCamera(SIZE, FACE, out_dtype=torch.uint8, seed=0)(_batch(b=2)[0])
    assert RandomOmniCamera(SIZE, FACE, out_dtype=torch.uint8, seed=0)(
        _u8(b=2))["rgb"].dtype == torch.uint8
    last = _u8(b=2).permute(0, 1, 3, 4, 2)
    with pytest.raises(ValueError, match="channels_last=True"):
        RandomOmniCamera(SIZE, FACE, seed=0)(last)
    with pytest.raises(ValueError, match="channels_last=False"):
        RandomOmniCamera(SIZE, FACE, channels_last=True, seed=0)(_u8(b=2))
    with pytest.raises(TypeError, match="cubemap"):
        RandomOmniCamera(SIZE, FACE, seed=0)(_u8(b=2).to(torch.int32))


class _Fill(nn.Module):
    """Every entry set to ``value`` (an image augmentation that touches the invalid pixels)."""

    def __init__(self, value):
        super().__init__()
        self.value = value

    def forward(self, x):
        return torch.full_like(x, self.value)


def test_apply_to_key_masks_channels_last_and_uint8():
    cube = _u8(b=2)
    first = nn.Sequential(RandomOmniCamera(SIZE, FACE, seed=1), ApplyToKey(_Fill(200)))(cube)
    last = nn.Sequential(RandomOmniCamera(SIZE, FACE, seed=1, channels_last=True),
                         ApplyToKey(_Fill(200)))(cube.permute(0, 1, 3, 4, 2))
    valid = first["valid"]
    assert bool(valid.any()) and bool((~valid).any())
    expected = torch.where(valid, 200, 0).to(torch.uint8).expand(2, 3, *SIZE)
    assert first["rgb"].dtype == torch.uint8 and torch.equal(first["rgb"], expected)
    assert torch.equal(last["rgb"], expected.permute(0, 2, 3, 1))
    # labels (B, H, W) broadcast per pixel, not against the batch
    lab = ApplyToKey(_Fill(7), key="labels")(
        RandomOmniCamera(SIZE, FACE, seed=1)(None, _batch(b=2)[1]))
    assert lab["labels"].shape == (2, *SIZE)
    assert torch.equal(lab["labels"], torch.where(valid[:, 0], 7, 0))
    # C = H = W cannot tell the layouts apart: the flag decides
    square = {"rgb": torch.ones(1, 4, 4, 4, dtype=torch.uint8),
              "valid": torch.zeros(1, 1, 4, 4, dtype=torch.bool)}
    square["valid"][0, 0, 0, 1] = True
    with pytest.raises(ValueError, match="channels_last"):
        ApplyToKey(nn.Identity())(square)
    got = ApplyToKey(nn.Identity(), channels_last=True)(square)["rgb"]
    assert torch.equal(got[0, 0, 1], torch.ones(4, dtype=torch.uint8)) and int(got.sum()) == 4
    got = ApplyToKey(nn.Identity(), channels_last=False)(square)["rgb"]
    assert torch.equal(got[0, :, 0, 1], torch.ones(4, dtype=torch.uint8)) and int(got.sum()) == 4


@pytest.mark.parametrize("build", [lambda K: K.RandomHorizontalFlip(p=1.0),
                                   lambda K: K.RandomAffine(10.0),
                                   lambda K: torch.nn.Sequential(K.ColorJitter(0.1),
                                                                 K.RandomCrop((8, 8)))])
def test_apply_to_key_refuses_augmentations_that_move_pixels(build):
    """A flip through ``ApplyToKey`` would flip the RGB and not the labels or the mask: refused
    with the module's name, nested ones included; colour augmentations are accepted."""
    import kornia.augmentation as K
    module = build(K)
    with pytest.raises(TypeError, match="moves pixels"):
        ApplyToKey(module)
    ApplyToKey(K.ColorJitter(0.1, 0.1))


def test_kornia_geometric_augmentations_go_after_on_every_key():
    """The README's composition: RandomOmniCamera, then kornia's AugmentationSequential on
    rgb, labels and valid at once (masks: nearest); a flip moves all three alike, labels stay
    labels (no blended values) and the pixels that an affine warp reveals are invalid, then
    labelled ignore_index again."""
    K = pytest.importorskip("kornia.augmentation")
    gen = torch.Generator().manual_seed(0)
    module = RandomOmniCamera((32, 32), 16, mode="fisheye", seed=1)
    cube = torch.rand(2, 6, 3, 16, 16, generator=gen)
    out = module(cube, labels=torch.randint(0, 5, (2, 6, 16, 16), generator=gen))
    flip = K.AugmentationSequential(K.RandomHorizontalFlip(p=1.0),
                                    data_keys=["input", "mask", "mask"])
    rgb, labels, valid = flip(out["rgb"], out["labels"][:, None], out["valid"])
    assert torch.equal(rgb, out["rgb"].flip(-1))
    assert torch.equal(labels[:, 0], out["labels"].flip(-1))
    assert torch.equal(valid, out["valid"].flip(-1))
    warp = K.AugmentationSequential(K.RandomAffine(degrees=0, translate=(0.3, 0.3), p=1.0),
                                    data_keys=["input", "mask", "mask"])
    rgb, labels, valid = warp(out["rgb"], out["labels"][:, None], out["valid"])
    assert labels.dtype == torch.int64 and valid.dtype == torch.bool
    assert set(labels.unique().tolist()) <= set(out["labels"].unique().tolist()) | {0}
    labels = labels[:, 0].masked_fill(~valid[:, 0], module.ignore_index)
    assert bool((labels[~valid[:, 0]] == module.ignore_index).all())
    assert int(valid.sum()) < int(out["valid"].sum())   # the shift revealed invalid pixels
