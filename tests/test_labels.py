"""Labels, palette and image I/O, checked against the real OmniScape CARLA frames.

The palette is CARLA 0.9.0-0.9.9's ``CITYSCAPES_PALETTE_MAP`` (LibCarla/source/carla/image/
CityScapesPalette.h), written out again below. The thresholds on the real frames were measured
on both frames (left / right) and set with a margin:

* within 10 colour units of a palette colour: 82.1 % / 83.8 % of the pixels; 89.5 % / 91.5 %
  once the ego motorcycle, drawn in (0, 0, 228) outside the palette (8.3 % / 8.4 %), is left out;
* lower half: Road 75.8 % / 72.0 %; top quarter: Unlabeled (CARLA 0.9's sky) 96.8 % / 95.0 %.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscape_torch.io import (CLASSES, IGNORE_INDEX, PALETTE, colorize, palette_to_labels,
                                read_image, to_float, write_image)

from conftest import SHARED_DATA

PANO = SHARED_DATA / "omniscape_equirect"
FRAMES = ["carla_left_semantic_palette_quantized.png", "carla_right_semantic_palette_quantized.png"]

# CityScapesPalette.h of CARLA 0.9.0-0.9.9, id: (name, RGB)
CARLA_13 = {
    0: ("Unlabeled", (0, 0, 0)), 1: ("Building", (70, 70, 70)), 2: ("Fence", (190, 153, 153)),
    3: ("Other", (250, 170, 160)), 4: ("Pedestrian", (220, 20, 60)),
    5: ("Pole", (153, 153, 153)), 6: ("RoadLine", (157, 234, 50)), 7: ("Road", (128, 64, 128)),
    8: ("Sidewalk", (244, 35, 232)), 9: ("Vegetation", (107, 142, 35)),
    10: ("Vehicle", (0, 0, 142)), 11: ("Wall", (102, 102, 156)),
    12: ("TrafficSign", (220, 220, 0)),
}
EGO_MOTORCYCLE = (0, 0, 228)


def test_classes_and_palette_are_carla_13():
    assert CLASSES == tuple(name for name, _ in CARLA_13.values())
    assert PALETTE.dtype == np.uint8 and PALETTE.shape == (13, 3)
    assert [tuple(map(int, c)) for c in PALETTE] == [rgb for _, rgb in CARLA_13.values()]
    assert len({tuple(c) for c in PALETTE}) == 13  # distinct colours: the mapping is invertible
    assert IGNORE_INDEX == 255
    with pytest.raises(ValueError):
        PALETTE[0, 0] = 1  # read-only: nobody recolours the package's palette by accident


def test_colorize_and_palette_to_labels_invert_each_other():
    ids = torch.arange(13).view(1, 13).repeat(3, 1)
    pictures = colorize(ids)
    assert pictures.dtype == np.uint8 and pictures.shape == (3, 13, 3)
    assert torch.equal(palette_to_labels(pictures), ids)
    assert torch.equal(palette_to_labels(torch.from_numpy(pictures)), ids)  # tensors too
    # ignore_index (and any id outside the palette) is drawn white, unlike Unlabeled (black)
    drawn = colorize(np.array([[IGNORE_INDEX, 0, 13, -1]]))
    assert [tuple(map(int, c)) for c in drawn[0]] == [(255,) * 3, (0,) * 3, (255,) * 3, (255,) * 3]
    with pytest.raises(TypeError, match="integer"):
        colorize(torch.zeros(2, 2))


def test_colorize_uint8_ids_as_int64_ones():
    """uint8 ids (a table of all 256) draw every id as the same ids in int64 do: the palette's
    colours for 0..12, white for the rest (IGNORE_INDEX included)."""
    ids = np.arange(256, dtype=np.uint8).reshape(16, 16)
    drawn = colorize(ids)
    assert drawn.dtype == np.uint8 and drawn.shape == (16, 16, 3)
    assert np.array_equal(drawn, colorize(ids.astype(np.int64)))
    assert np.array_equal(drawn.reshape(256, 3)[:13], PALETTE)
    assert bool((drawn.reshape(256, 3)[13:] == 255).all())


def test_palette_to_labels_is_the_nearest_colour():
    """Against a brute-force nearest-colour search over every pixel and every colour."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (37, 23, 3), dtype=np.uint8)
    rgb[::3] = PALETTE[rng.integers(0, 13, (13, 23))] + rng.integers(-4, 5, (13, 23, 3)).clip(0)
    d2 = ((rgb[..., None, :].astype(np.int64) - PALETTE.astype(np.int64)) ** 2).sum(-1)
    assert np.array_equal(palette_to_labels(rgb).numpy(), d2.argmin(-1))
    near = palette_to_labels(rgb, max_distance=20.0).numpy()
    assert np.array_equal(near, np.where(d2.min(-1) <= 400, d2.argmin(-1), IGNORE_INDEX))
    assert 0 < (near == IGNORE_INDEX).mean() < 1  # both outcomes exercised
    # any leading shape; a custom palette
    assert palette_to_labels(rgb[0]).shape == (23,)
    two = np.array([[0, 0, 0], [255, 255, 255]], dtype=np.uint8)
    assert palette_to_labels(np.array([[[10, 10, 10], [200, 200, 200]]], np.uint8),
                             palette=two).tolist() == [[0, 1]]
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        palette_to_labels(np.zeros((4, 4), np.uint8))
    with pytest.raises(TypeError, match="integer"):
        palette_to_labels(np.zeros((4, 4, 3), np.float32))


@pytest.mark.parametrize("name", FRAMES)
def test_real_semantic_frame(name):
    rgb = read_image(PANO / name)
    assert rgb.dtype == torch.uint8 and rgb.shape == (300, 600, 3)
    labels = palette_to_labels(rgb)
    assert labels.shape == (300, 600) and labels.dtype == torch.int64
    assert int(labels.min()) >= 0 and int(labels.max()) < 13

    near = palette_to_labels(rgb, max_distance=10.0) != IGNORE_INDEX
    ego = torch.from_numpy(np.linalg.norm(rgb.numpy().astype(float) - EGO_MOTORCYCLE, axis=-1)
                           <= 12)
    assert 0.05 < float(ego.float().mean()) < 0.12
    assert float(near.float().mean()) > 0.78
    assert float(near[~ego].float().mean()) > 0.86  # the rest: dithered edges only
    # the ego motorcycle is nearest to Vehicle, and beyond any small max_distance
    assert set(labels[ego].tolist()) == {CLASSES.index("Vehicle")}
    assert not bool(near[ego].any())

    # measured composition of a street-level panorama
    h = labels.shape[0]
    share = lambda part, cls: float((part == CLASSES.index(cls)).float().mean())  # noqa: E731
    assert share(labels[h // 2:], "Road") > 0.6
    assert int(torch.bincount(labels[h // 2:].flatten(), minlength=13).argmax()) == \
        CLASSES.index("Road")
    assert share(labels[: h // 4], "Unlabeled") > 0.9  # CARLA 0.9 has no sky class
    # the palette matches the frame: the common classes each have many near-exact pixels
    for cls in ("Unlabeled", "Building", "Pedestrian", "Pole", "RoadLine", "Road", "Sidewalk",
                "Vehicle"):
        colour = PALETTE[CLASSES.index(cls)].astype(float)
        assert int((np.linalg.norm(rgb.numpy() - colour, axis=-1) <= 10).sum()) > 300, cls


def test_image_io_round_trip(tmp_path):
    image = (np.arange(4 * 5 * 3) % 256).astype(np.uint8).reshape(4, 5, 3)
    path = write_image(tmp_path / "a.png", image)
    assert np.array_equal(read_image(path).numpy(), image)  # RGB order kept
    write_image(tmp_path / "a.png", torch.from_numpy(image[::-1].copy()))  # overwrite, tensor
    assert np.array_equal(read_image(path).numpy(), image[::-1])
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary left behind
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert np.array_equal(read_image(write_image(tmp_path / "g.png", grey)).numpy(), grey)
    with pytest.raises(TypeError, match="uint8"):
        write_image(tmp_path / "b.png", image.astype(np.float32))
    with pytest.raises(FileNotFoundError):
        read_image(tmp_path / "missing.png")


def test_to_float():
    image = torch.tensor([[[0, 255, 51]]], dtype=torch.uint8)  # (1, 1, 3)
    out = to_float(image)
    assert out.shape == (3, 1, 1) and out.dtype == torch.float32
    assert out.flatten().tolist() == pytest.approx([0.0, 1.0, 0.2])
    assert to_float(image, dtype=torch.float64).dtype == torch.float64
    assert to_float(np.full((2, 3), 65535, np.uint16)).flatten().tolist() == [1.0] * 6
    real = to_float(read_image(PANO / "carla_left_rgb.png"))
    assert real.shape == (3, 300, 600) and 0 <= float(real.min()) < float(real.max()) <= 1
    with pytest.raises(TypeError):
        to_float(torch.zeros(2, 2, 3))
