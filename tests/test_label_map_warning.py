"""A uint8 label map given as the image to render (``ot.reproject``, ``OmniProjection``,
``RandomOmniCamera``, ``RandomReproject``) warns once, saying how to pass labels; a real RGB
image does not (issue 32). Real data: a CARLA frame of the OmniScape dataset and its semantic
segmentation (../shared/data/omniscape_equirect)."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.render.reference import LabelMapWarning

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "omniscape_equirect"
FACE, SIZE = 24, (32, 32)


@pytest.fixture(scope="module")
def images():
    """``(rgb (1, 3, H, W), labels (1, 1, H, W), labels as three equal channels)`` uint8, a
    real 600 x 300 panorama at half size."""
    if not (DATA / "carla_left_rgb.png").is_file():
        pytest.skip("../shared/data missing")
    rgb = ot.io.read_image(DATA / "carla_left_rgb.png")[::2, ::2].permute(2, 0, 1)[None]
    semantic = ot.io.read_image(DATA / "carla_left_semantic_palette_quantized.png")
    ids = ot.io.palette_to_labels(semantic)[::2, ::2].to(torch.uint8)[None, None]
    return rgb.contiguous(), ids.contiguous(), ids.expand(1, 3, *ids.shape[2:]).contiguous()


def _cube(image: torch.Tensor) -> torch.Tensor:
    """``(1, 6, C, F, F)`` uint8 faces of a panorama, nearest (labels stay ids)."""
    return ot.equirect_to_cubemap(image, FACE, interpolation="nearest", labels=False)


def _calls(image: torch.Tensor) -> dict:
    """The four entry points, each rendering ``image`` (a panorama) as its image."""
    src = ot.equirectangular_camera(image.shape[-1], image.shape[-2])
    dst = ot.presets.fisheye(SIZE, fov=math.radians(180))
    cube = _cube(image)
    return {
        "reproject": lambda: ot.reproject(image, src, dst),
        "OmniProjection": lambda: ot.OmniProjection(dst, FACE)(cube),
        "RandomOmniCamera": lambda: ot.augment.RandomOmniCamera(SIZE, FACE, seed=0)(
            {"rgb": cube}),
        "RandomReproject": lambda: ot.augment.RandomReproject(SIZE, source_fov=math.radians(90), seed=0)(
            {"rgb": image[..., :, 100:200]}),
    }


@pytest.mark.parametrize("entry", ["reproject", "OmniProjection", "RandomOmniCamera",
                                   "RandomReproject"])
def test_a_real_rgb_image_does_not_warn(images, entry):
    with warnings.catch_warnings():
        warnings.simplefilter("error", LabelMapWarning)
        _calls(images[0])[entry]()


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("entry", ["reproject", "OmniProjection", "RandomOmniCamera",
                                   "RandomReproject"])
def test_a_label_map_as_the_image_warns_how_to_pass_labels(images, entry, channels):
    label_map = images[1] if channels == 1 else images[2]
    with pytest.warns(LabelMapWarning, match="looks like a label map.*labels=") as caught:
        _calls(label_map)[entry]()
    ours = [w for w in caught if issubclass(w.category, LabelMapWarning)]
    assert len({(w.filename, w.lineno, str(w.message)) for w in ours}) == 1   # shown once
    assert "'labels' key" in str(ours[0].message)


def test_labels_passed_as_labels_do_not_warn(images):
    """The right way, and ``labels=False`` (an image that happens to look like ids)."""
    src = ot.equirectangular_camera(images[1].shape[-1], images[1].shape[-2])
    dst = ot.presets.fisheye(SIZE, fov=math.radians(180))
    with warnings.catch_warnings():
        warnings.simplefilter("error", LabelMapWarning)
        ot.reproject(images[1][:, 0], src, dst, labels=True)
        ot.reproject(images[1], src, dst, labels=False)
        ot.augment.RandomOmniCamera(SIZE, FACE, seed=0)(
            {"rgb": _cube(images[0]), "labels": _cube(images[1])[:, :, 0].long()})


def test_a_binary_mask_does_not_warn():
    """0 / 255 (a valid mask, a checkerboard): an image to blend, not class ids."""
    mask = torch.zeros(1, 1, 16, 16, dtype=torch.uint8)
    mask[..., ::2, :] = 255
    src = ot.equirectangular_camera(16, 16)
    dst = ot.presets.fisheye((8, 8), fov=math.radians(180))
    with warnings.catch_warnings():
        warnings.simplefilter("error", LabelMapWarning)
        ot.reproject(mask, src, dst)
        ot.reproject(mask.expand(1, 3, 16, 16), src, dst)


def test_the_warning_is_shown_once():
    """One message from one place: Python's default filter shows it once."""
    label_map = torch.zeros(1, 1, 16, 16, dtype=torch.uint8)
    label_map[..., 8:] = 7
    src = ot.equirectangular_camera(16, 16)
    dst = ot.presets.fisheye((8, 8), fov=math.radians(180))
    with warnings.catch_warnings(record=True) as caught:
        warnings.resetwarnings()
        warnings.simplefilter("default")
        for _ in range(3):
            ot.reproject(label_map, src, dst)
    assert len([w for w in caught if issubclass(w.category, LabelMapWarning)]) == 1
