"""The procedural town (``omniscape_torch.scenes``): determinism, geometry, labels, exactness of
the cubemap path against direct ray casting, weather presets, motion."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from omniscape_torch.cubemap import FACES
from omniscape_torch.cubemap.faces import face_rays
from omniscape_torch.scenes import CLASS_IDS, WEATHERS, Town

POSE = torch.tensor([0.0, -1.2, 0.0])  # on the centre line, eye height, looking north


@pytest.fixture(scope="module")
def town():
    return Town(0)


@pytest.fixture(scope="module")
def cube(town):
    return town.render_cubemap(POSE, face_size=48)


def _rotation(wx, wy, wz):
    w = torch.tensor([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])
    return torch.linalg.matrix_exp(w)


def test_shapes_and_label_range(cube):
    F = 48
    assert cube["rgb"].shape == (1, 6, 3, F, F) and cube["rgb"].dtype == torch.float32
    assert cube["depth"].shape == (1, 6, F, F)
    assert cube["labels"].shape == (1, 6, F, F) and cube["labels"].dtype == torch.int64
    assert cube["labels"].min() >= 0 and cube["labels"].max() <= 12
    assert cube["rgb"].min() >= 0 and cube["rgb"].max() <= 1
    assert torch.isfinite(cube["depth"]).all() and (cube["depth"] > 0).all()


def test_deterministic_by_seed(cube):
    again = Town(0).render_cubemap(POSE, face_size=48)
    for k in ("rgb", "depth", "labels"):
        assert torch.equal(again[k], cube[k])
    other = Town(1).render_cubemap(POSE, face_size=48)
    assert not torch.equal(other["labels"], cube["labels"])
    assert not torch.equal(other["rgb"], cube["rgb"])


def test_no_global_rng_used():
    torch.manual_seed(123)
    a = torch.rand(3)
    torch.manual_seed(123)
    Town(5)
    assert torch.equal(torch.rand(3), a)


def test_planar_depth_is_range_along_face_axis(town, cube):
    F = 48
    # texel (u, v) of every face: x = (u - c) / f, y = (v - c) / f, |ray| = sqrt(1 + x^2 + y^2)
    f, c = F / 2, (F - 1) / 2
    t = (torch.arange(F, dtype=torch.float32) - c) / f
    y, x = torch.meshgrid(t, t, indexing="ij")
    norm = torch.sqrt(1 + x * x + y * y).expand(6, F, F)
    torch.testing.assert_close(norm, face_rays(F).norm(dim=-1))
    rng, depth = cube["range"][0], cube["depth"][0]
    sky = cube["labels"][0] == CLASS_IDS["Unlabeled"]
    assert sky.any() and (~sky).any()
    torch.testing.assert_close(depth[~sky], (rng / norm)[~sky], rtol=1e-5, atol=1e-5)
    assert (depth[sky] == town.far).all() and (rng[sky] == town.far).all()
    # the down face sees the ground at planar depth = camera height exactly where it is road
    down = FACES.index("down")
    ground = (cube["labels"][0, down] == CLASS_IDS["Road"]) | \
        (cube["labels"][0, down] == CLASS_IDS["RoadLine"])
    torch.testing.assert_close(depth[down][ground], torch.full_like(depth[down][ground], 1.2))


def test_straight_down_hits_road_at_camera_height(town):
    for x, z in [(0.0, 0.0), (1.75, 10.0), (-2.0, -33.0)]:
        out = town.render_rays(torch.tensor([x, -1.2, z]), torch.tensor([0.0, 1.0, 0.0]))
        assert int(out["labels"]) in (CLASS_IDS["Road"], CLASS_IDS["RoadLine"])
        assert float(out["range"]) == pytest.approx(1.2, abs=1e-5)
        assert out["hit"]


def test_straight_up_is_sky(town):
    out = town.render_rays(POSE, torch.tensor([0.0, -1.0, 0.0]))
    assert int(out["labels"]) == CLASS_IDS["Unlabeled"]
    assert float(out["range"]) == town.far and not out["hit"]


def test_ground_zones_by_world_coordinates(town):
    # looking straight down from 20 m at chosen points of the cross-section
    cases = {(1.7, 9.0): "Road", (0.0, 1.0): "RoadLine", (3.5, 9.0): "RoadLine",
             (6.0, 0.5): "Sidewalk", (-6.0, 0.5): "Sidewalk"}
    for (x, z), name in cases.items():
        out = town.render_rays(torch.tensor([x, -0.5, z]), torch.tensor([0.0, 1.0, 0.0]))
        assert int(out["labels"]) == CLASS_IDS[name], (x, z, name)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_class_appears_from_the_default_pose(seed):
    town = Town(seed)
    assert town.classes_present == set(range(13))
    labels = town.render_cubemap(POSE, face_size=64)["labels"]
    assert set(labels.unique().tolist()) == set(range(13))


@pytest.mark.parametrize("rotated", [False, True])
def test_render_rays_of_texel_rays_equals_cubemap_exactly(town, rotated):
    F = 40  # not a multiple of the tile size: exercises the padded tiles
    rot = _rotation(0.2, -0.7, 0.15) if rotated else None
    pos = torch.tensor([2.0, -1.6, -7.5])
    cube = town.render_cubemap(pos, rot, face_size=F, t=3.0, weather="night")
    ref = town.render_rays(pos, town.cubemap_rays(F, rot), t=3.0, weather="night")
    assert torch.equal(ref["labels"], cube["labels"][0])
    assert torch.equal(ref["range"], cube["range"][0])
    assert torch.equal(ref["rgb"].permute(0, 3, 1, 2), cube["rgb"][0])


def test_render_rays_broadcasts_and_per_ray_origins_match(town):
    d = town.cubemap_rays(16)[0]  # (16, 16, 3)
    shared = town.render_rays(POSE, d)
    per_ray = town.render_rays(POSE.expand(16, 16, 3), d, chunk=37)
    assert shared["rgb"].shape == (16, 16, 3) and shared["labels"].shape == (16, 16)
    for k in ("rgb", "range", "labels"):
        assert torch.equal(shared[k], per_ray[k])


def test_face_subset(town, cube):
    mask = torch.tensor([True, False, False, True, False, True])
    part = town.render_cubemap(POSE, face_size=48, faces=mask)
    for k in ("rgb", "depth", "labels"):
        assert torch.equal(part[k][:, mask], cube[k][:, mask])
    assert (part["labels"][:, ~mask] == 255).all()


def test_weather_changes_colour_not_geometry(town):
    outs = {w: town.render_cubemap(POSE, face_size=32, weather=w) for w in WEATHERS}
    assert {"clear_noon", "overcast", "sunset", "night"} <= set(outs)
    ref = outs["clear_noon"]
    for w, o in outs.items():
        assert torch.equal(o["labels"], ref["labels"]) and torch.equal(o["depth"], ref["depth"])
        assert o["rgb"].min() >= 0 and o["rgb"].max() <= 1
    names = list(outs)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert (outs[a]["rgb"] - outs[b]["rgb"]).abs().mean() > 0.02, (a, b)
    assert outs["night"]["rgb"].mean() < 0.5 * ref["rgb"].mean()
    # fog changes colour only, and more with distance
    clear = dataclasses.replace(WEATHERS["clear_noon"], fog_density=0.0)
    thick = dataclasses.replace(WEATHERS["clear_noon"], fog_density=0.05)
    a = town.render_cubemap(POSE, face_size=32, weather=clear)
    b = town.render_cubemap(POSE, face_size=32, weather=thick)
    assert torch.equal(a["labels"], b["labels"]) and torch.equal(a["depth"], b["depth"])
    diff = (a["rgb"] - b["rgb"]).abs().sum(2)[0]
    hit = a["labels"][0] != 0
    near, far = hit & (a["range"][0] < 5), hit & (a["range"][0] > 40) & (a["range"][0] < 200)
    assert diff[far].mean() > 3 * diff[near].mean()
    with pytest.raises(ValueError):
        town.render_cubemap(POSE, face_size=8, weather="blizzard")


def test_textured_not_flat(cube):
    rgb, labels = cube["rgb"][0].permute(0, 2, 3, 1), cube["labels"][0]
    for name in ("Road", "Building", "Sidewalk"):
        px = rgb[labels == CLASS_IDS[name]]
        assert px.std(0).max() > 0.01, name


def test_moving_objects(town):
    m0, m1 = town.moving_objects(0.0), town.moving_objects(1.0)
    L = town.length
    step = torch.remainder(m1["z"] - m0["z"] + L / 2, L) - L / 2
    torch.testing.assert_close(step, m0["speed"])
    assert (m0["kind"] == 0).any() and (m0["kind"] == 1).any()
    assert (m1["z"].abs() <= L / 2).all()
    a = town.render_cubemap(POSE, face_size=32, t=0.0)
    b = town.render_cubemap(POSE, face_size=32, t=2.0)
    assert not torch.equal(a["labels"], b["labels"])
    # static scene parts do not move: the up face sees only buildings and sky
    up = FACES.index("up")
    assert torch.equal(a["labels"][0, up], b["labels"][0, up])


def test_sun_direction_unit_and_above_horizon():
    for w in WEATHERS.values():
        d = w.sun_direction()
        assert math.isclose(sum(x * x for x in d), 1.0, rel_tol=1e-9)
        assert d[1] < 0  # y down: the sun is up
