"""The procedural town (``omniscape_torch.scenes``): determinism, geometry (the meshes against
the primitives they come from), labels, exactness of the cubemap path against direct ray
casting, the C++ shading ops against the torch reference, shadows, weather presets (CARLA's
parameters), layouts and their routes, motion."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from omniscape_torch.cubemap import FACES
from omniscape_torch.cubemap.faces import face_pixel_to_ray, face_rays
from omniscape_torch.render import kernels
from omniscape_torch.render.kernels import town as town_kernels
from omniscape_torch.scenes import CLASS_IDS, WEATHERS, Town, mesh, routes
from omniscape_torch.scenes.town import CARLA_WEATHERS, LAYOUTS, edge_texels
from omniscape_torch.scenes.weather import _get_weather, _kernel_weather

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
    carla = {"clear_noon", "cloudy_noon", "wet_noon", "wet_cloudy_noon", "mid_rainy_noon",
             "hard_rain_noon", "soft_rain_noon", "clear_sunset", "cloudy_sunset", "wet_sunset",
             "wet_cloudy_sunset", "mid_rain_sunset", "hard_rain_sunset", "soft_rain_sunset"}
    assert carla | {"overcast", "sunset", "night", "fog"} == set(outs)
    ref = outs["clear_noon"]
    for w, o in outs.items():
        assert torch.equal(o["labels"], ref["labels"]) and torch.equal(o["depth"], ref["depth"])
        assert o["rgb"].min() >= 0 and o["rgb"].max() <= 1
    names = list(outs)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert (outs[a]["rgb"] - outs[b]["rgb"]).abs().mean() > 0.01, (a, b)
    assert outs["night"]["rgb"].mean() < 0.5 * ref["rgb"].mean()
    # rain darkens; the sun reddens at sunset (red over blue)
    for rain in ("mid_rainy_noon", "hard_rain_noon"):
        assert outs[rain]["rgb"].mean() < 0.85 * ref["rgb"].mean(), rain

    def red_over_blue(o):
        return float(o["rgb"][0, :, 0].mean() / o["rgb"][0, :, 2].mean())
    assert red_over_blue(outs["clear_sunset"]) > 1.2 * red_over_blue(ref)
    # puddles on the wet road mirror the blue sky; the dry road is grey
    road = ref["labels"][0] == CLASS_IDS["Road"]

    def blue_road(o):
        rgb = o["rgb"][0].movedim(1, -1)[road]
        return float((rgb[:, 2] > rgb[:, 0] + 0.05).float().mean())
    assert blue_road(outs["wet_noon"]) > 0.02 and blue_road(ref) < 0.002
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


# -------------------------------------------------------------------- weather presets

def test_carla_presets_are_carlas():
    """The 14 presets' parameters are those of CARLA's own ``carla.WeatherParameters``, and
    they are all of CARLA's day presets (its ``*Night`` ones and ``DustStorm`` are not)."""
    carla = pytest.importorskip("carla")
    ours = set(CARLA_WEATHERS)
    theirs = {n for n in dir(carla.WeatherParameters) if n[0].isupper()
              and not n.endswith("Night") and n not in ("Default", "DustStorm")}
    assert ours == theirs and len(ours) == 14
    compared = 0
    for name, params in CARLA_WEATHERS.items():
        preset = getattr(carla.WeatherParameters, name)
        for key, value in params.items():
            assert getattr(preset, key) == pytest.approx(value), (name, key)
            compared += 1
    assert compared == 14 * 5


def test_shadows_where_a_ray_to_the_sun_meets_something(town):
    """Road points whose ray towards the sun (traced here, apart from the shading) meets
    something are darker than the others: the sun's share of their light is gone."""
    w = WEATHERS["clear_noon"]
    x, z = torch.meshgrid(torch.linspace(-5.0, 5.0, 21), torch.linspace(-60.0, 60.0, 241),
                          indexing="ij")
    origins = torch.stack([x, torch.full_like(x, -0.05), z], -1).reshape(-1, 3)
    down = town.render_rays(origins, torch.tensor([0.0, 1.0, 0.0]).expand_as(origins),
                            weather=w)
    road = down["labels"] == CLASS_IDS["Road"]
    ground = origins + down["range"].unsqueeze(-1) * torch.tensor([0.0, 1.0, 0.0])
    ground[:, 1] -= 1e-3
    to_sun = town.render_rays(ground, torch.tensor(w.sun_direction()).expand_as(ground))
    shadowed, lit = road & to_sun["hit"], road & ~to_sun["hit"]
    assert shadowed.sum() > 100 and lit.sum() > 100
    brightness = down["rgb"].mean(-1)
    assert brightness[shadowed].mean() < 0.7 * brightness[lit].mean()


# -------------------------------------------------------------------- the C shading

def _needs_cpp():
    if not kernels.available():
        pytest.skip("no C++ compiler: the town shades with its torch twins")


@pytest.mark.parametrize("weather", ["clear_noon", "night", "wet_cloudy_sunset"])
def test_c_shading_matches_the_torch_twin(town, weather):
    """The C++ ops and their torch twins (``render.kernels.town``) give the same back faces,
    labels, ranges and hits, and colours and normals within a few float32 roundings (torch's
    sqrt is not correctly rounded on every CPU: one unit in the last place, here and there)."""
    _needs_cpp()
    rot = _rotation(0.1, 0.5, -0.05)
    pos = torch.tensor([[2.0, -1.6, -7.5]])
    d = town.cubemap_rays(40, rot).reshape(-1, 3).contiguous()
    scene = town.scene(3.0)
    w = _kernel_weather(_get_weather(weather), town.far)
    hits = [torch.from_numpy(h) for h in town._trace(scene, pos.numpy(), d.numpy(), "torch")]
    tri = hits[1].clone()
    tri[::7] = torch.randint(0, town._tri_attr.shape[1], tri[::7].shape,
                             generator=torch.Generator().manual_seed(0))   # some back faces
    back = [town_kernels.backfaces(d, tri, town._tri_attr, backend=b) for b in ("cpp", "torch")]
    assert torch.equal(*back) and back[0].any() and not back[0].all()
    fast, ref = (town_kernels.shade(pos, d, *hits, town._tables, w, scene.occluded, backend=b)
                 for b in ("cpp", "torch"))
    for key in ("labels", "range", "hit"):
        assert torch.equal(fast[key], ref[key]), key
    for key in ("rgb", "normal"):
        torch.testing.assert_close(fast[key], ref[key], rtol=0, atol=1e-6)
    assert fast["hit"].any() and (~fast["hit"]).any()


def test_the_town_kernels_check_their_arguments(town):
    """Bad arguments are refused the same on both routes, naming the argument; so is a
    backend that is not one."""
    d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    tri = torch.tensor([0, -1, 3, 2, 1])
    P = 8
    planes = (torch.zeros(3, P), torch.zeros(P), torch.zeros(P),
              torch.zeros(P, dtype=torch.int64))
    shaded = {"rgb": torch.rand(5, 3), "range": torch.rand(5),
              "labels": torch.zeros(5, dtype=torch.int64), "hit": tri >= 0}
    axis = torch.tensor([0.0, 0.0, 1.0])
    backends = ("torch", "cpp") if kernels.available() else ("torch",)
    for backend in backends:
        with pytest.raises(ValueError, match="tri: expected"):
            town_kernels.backfaces(d, tri.int(), town._tri_attr, backend=backend)
        with pytest.raises(ValueError, match="tri: expected triangle indices in \\[-1, "):
            town_kernels.backfaces(d, tri - 2, town._tri_attr, backend=backend)
        with pytest.raises(ValueError, match="index: expected texels in \\[0, 8\\)"):
            town_kernels.store(d, torch.arange(5) + 4, 0, shaded, axis, 1000.0, *planes,
                               backend=backend)
        with pytest.raises(ValueError, match="start: expected 0 <= start <= 3"):
            town_kernels.store(d, None, 4, shaded, axis, 1000.0, *planes, backend=backend)
        with pytest.raises(ValueError, match="axis: expected \\(3\\) torch.float32"):
            town_kernels.store(d, None, 0, shaded, axis.double(), 1000.0, *planes,
                               backend=backend)
    with pytest.raises(ValueError, match="backend: expected one of"):
        town_kernels.backfaces(d, tri, town._tri_attr, backend="gpu")
    for bad in ("gpu", None, "CPP"):
        with pytest.raises(ValueError, match="backend"):
            town.render_cubemap(POSE, face_size=4, backend=bad)
        with pytest.raises(ValueError, match="backend"):
            town.render_rays(POSE, torch.tensor([0.0, 0.0, 1.0]), backend=bad)


# -------------------------------------------------------------------- meshes and primitives

def test_meshes_wind_outward_and_lie_on_their_primitives():
    g = np.random.default_rng(0)
    lo = g.uniform(-5, 5, (4, 3)).astype(np.float32)
    lo[:, 1] -= 10   # above the ground (y down): their bottoms are kept
    hi = lo + g.uniform(0.5, 3, (4, 3)).astype(np.float32)
    cyl = np.array([[1.0, 2.0, 0.3, -4.0, 0.0], [-3.0, 5.0, 1.2, -1.0, -0.2]])
    sph = np.array([[0.0, -3.0, 1.0, 1.5], [4.0, -1.0, -2.0, 0.14]])
    cases = [(mesh.box_mesh(lo, hi, np.arange(4)), (lo + hi) / 2, 12),
             (mesh.cylinder_mesh(cyl, np.arange(2), 32),
              np.stack([cyl[:, 0], (cyl[:, 3] + cyl[:, 4]) / 2, cyl[:, 1]], -1), 3 * 32),
             (mesh.sphere_mesh(sph, np.arange(2), 3), sph[:, :3], 1280)]
    for m, centre, per_part in cases:
        assert m.num_triangles == per_part * len(centre)
        assert (np.bincount(m.part) == per_part).all()
        tri = m.vertices[m.triangles].astype(np.float64)         # (T, 3, 3)
        outward = ((tri.mean(1) - centre[m.part]) * m.face_normals).sum(-1)
        assert (outward > 0).all()
        np.testing.assert_allclose(np.linalg.norm(m.face_normals, axis=-1), 1, atol=1e-6)
    # the vertices lie on the primitives' surfaces
    s = cases[2][0]
    r = np.linalg.norm(s.vertices - sph[s.vertex_part, :3], axis=-1)
    np.testing.assert_allclose(r, sph[s.vertex_part, 3], atol=2e-6)   # float32 vertices
    c = cases[1][0]
    v, p = c.vertices, c.vertex_part
    side = np.abs(v[:, 1] - cyl[p, 3]) > 1e-6   # not on the cap's plane: on the side
    np.testing.assert_allclose(np.hypot(v[side, 0] - cyl[p[side], 0],
                                        v[side, 2] - cyl[p[side], 1]), cyl[p[side], 2],
                               atol=2e-6)
    # a box standing on the ground has no bottom face (it would lie in the ground's plane)
    assert mesh.box_mesh([[0, -2, 0]], [[1, 0, 1]], [0]).num_triangles == 10


def test_hits_match_the_primitives(town):
    """Rays straight down from 5 m above the buildings' roofs, the lamp poles' caps and the
    spheres' tops hit them at 5 m with their class (the spheres within the icosphere's depth
    below the sphere, ``r (1 - cos 4.7 deg)``)."""
    compared = 0
    down = torch.tensor([0.0, 1.0, 0.0])
    b = town.boxes_label == CLASS_IDS["Building"]
    top = torch.stack([(town.boxes_lo[b, 0] + town.boxes_hi[b, 0]) / 2, town.boxes_lo[b, 1] - 5,
                       (town.boxes_lo[b, 2] + town.boxes_hi[b, 2]) / 2], -1)
    out = town.render_rays(top, down.expand_as(top))
    assert (out["labels"] == CLASS_IDS["Building"]).all()
    torch.testing.assert_close(out["range"], torch.full_like(out["range"], 5.0), atol=2e-5,
                               rtol=0)
    compared += len(top)
    poles = (town.cyl_label == CLASS_IDS["Pole"]) & (town.cyl[:, 2] > 0.1)  # the lamps
    top = torch.stack([town.cyl[poles, 0], town.cyl[poles, 3] - 5, town.cyl[poles, 1]], -1)
    out = town.render_rays(top, down.expand_as(top))
    assert (out["labels"] == CLASS_IDS["Pole"]).all()
    torch.testing.assert_close(out["range"], torch.full_like(out["range"], 5.0), atol=2e-5,
                               rtol=0)
    compared += len(top)
    sph = town.sph[town.sph_label == CLASS_IDS["Vegetation"]]   # the crowns: nothing above
    top = torch.stack([sph[:, 0], sph[:, 1] - sph[:, 3] - 5, sph[:, 2]], -1)
    out = town.render_rays(top, down.expand_as(top))
    assert (out["labels"] == CLASS_IDS["Vegetation"]).all()
    depth = out["range"] - 5
    assert (depth >= -2e-5).all() and (depth <= sph[:, 3] * (1 - math.cos(math.radians(4.7)))).all()
    compared += len(top)
    assert compared > 50


def test_rays_from_inside_a_primitive_go_through_it(town):
    """A ray that starts inside a parked vehicle sees what a ray started just outside it sees,
    farther by the distance between the two starts (primitives are seen from outside)."""
    parked = (town.boxes_label == CLASS_IDS["Vehicle"]) & (town.boxes_mover < 0) & \
        (town.boxes_hi[:, 1] > -0.5)     # the bodies (their cabins sit on them)
    lo, hi = town.boxes_lo[parked], town.boxes_hi[parked]
    centre = (lo + hi) / 2
    side, back = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0])
    for d in (side, back):
        exit_t = hi[:, 0] - centre[:, 0] if d[0] > 0 else centre[:, 2] - lo[:, 2]
        outside = centre + (exit_t + 1e-3).unsqueeze(-1) * d
        a = town.render_rays(centre, d.expand_as(centre))
        b = town.render_rays(outside, d.expand_as(centre))
        assert torch.equal(a["labels"], b["labels"])
        hit = a["hit"]
        torch.testing.assert_close(a["range"][hit], b["range"][hit] + exit_t[hit] + 1e-3,
                                   atol=1e-3, rtol=0)
    assert len(centre) > 3


# -------------------------------------------------------------------- subsets, buffers, threads

def test_texel_subset_and_reused_buffers(town, cube):
    g = torch.Generator().manual_seed(0)
    mask = torch.rand(6, 48, 48, generator=g) < 0.3
    out = {"rgb": torch.empty(1, 6, 3, 48, 48), "labels": torch.empty(1, 6, 48, 48,
                                                                      dtype=torch.int64)}
    ptr = out["rgb"].data_ptr()
    part = town.render_cubemap(POSE, face_size=48, texels=mask, out=out)
    assert part["rgb"].data_ptr() == ptr
    for k in ("rgb", "depth", "labels", "range"):
        sel = part[k][0].movedim(1, -1)[mask] if k == "rgb" else part[k][0][mask]
        ref = cube[k][0].movedim(1, -1)[mask] if k == "rgb" else cube[k][0][mask]
        assert torch.equal(sel, ref), k
    assert (part["labels"][0][~mask] == 255).all() and (part["depth"][0][~mask] == 0).all()
    with pytest.raises(ValueError, match="out"):
        town.render_cubemap(POSE, face_size=48, out={"depth": torch.empty(1, 6, 47, 47)})
    with pytest.raises(ValueError, match="texels"):
        town.render_cubemap(POSE, face_size=48, texels=mask[:, :40])


def test_threads_and_pickling_do_not_change_the_images(town, cube):
    import pickle
    one = Town(0, threads=1).render_cubemap(POSE, face_size=48)
    again = pickle.loads(pickle.dumps(town)).render_cubemap(POSE, face_size=48)
    for k in ("rgb", "depth", "labels"):
        assert torch.equal(one[k], cube[k]) and torch.equal(again[k], cube[k])


def test_bad_arguments():
    for kw in ({"layout": 4}, {"layout": True}, {"length": 5}, {"far": -1}, {"threads": 0}):
        with pytest.raises(ValueError, match=next(iter(kw))):
            Town(0, **kw)
    with pytest.raises(ValueError, match="seed"):
        Town(-1)


# -------------------------------------------------------------------- layouts and routes

@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_layouts_and_their_routes(layout):
    """Every layout holds every class and its streets' roads; its ride stays on the road
    (straight down from the route, every 2 m: Road or RoadLine) and leaves each turn on a lane's
    centre line (1.75 m off a street's)."""
    town = Town(0, layout=layout)
    assert town.classes_present == set(range(13))
    route = routes.route(layout, 0)
    pts = torch.tensor(route.position[::40], dtype=torch.float32)   # ds = 5 cm
    pts[:, 1] = -0.05
    out = town.render_rays(pts, torch.tensor([0.0, 1.0, 0.0]).expand_as(pts))
    road = (out["labels"] == CLASS_IDS["Road"]) | (out["labels"] == CLASS_IDS["RoadLine"])
    assert road.all(), pts[~road]
    x, _, z = route.position[-1]
    lanes = [s.offset + k * routes.LANE for s in town.streets for k in (-1, 1)]
    end = x if abs(math.sin(route.heading[-1])) < 0.5 else z   # heading along z: x is lateral
    assert min(abs(end - lane) for lane in lanes) < 0.01
    # the cross streets' roads, straight down at their centre lines away from the crossings
    for s in town.streets:
        p = torch.tensor([[s.offset + 2.0, -0.5, 30.0]]) if s.axis == "z" else \
            torch.tensor([[30.0, -0.5, s.offset + 2.0]])
        if s.axis == "z" and any(abs(30.0 - c.offset) < 9 for c in town.streets if c.axis == "x"):
            continue
        assert int(town.render_rays(p, torch.tensor([0.0, 1.0, 0.0]))["labels"]) == \
            CLASS_IDS["Road"]


def test_the_town_renders_the_same_with_its_torch_twins(town, cube):
    """``backend="torch"`` (what the town does where the C++ ops cannot be built) traces and
    shades with the ops' torch twins: against ``backend="cpp"``, the same labels, depths,
    ranges and instances, colours within float32 roundings."""
    _needs_cpp()
    fast = town.render_cubemap(POSE, face_size=48, backend="cpp")
    slow = town.render_cubemap(POSE, face_size=48, backend="torch")
    for key in ("labels", "depth", "range", "instances"):
        assert torch.equal(slow[key], fast[key]), key
    torch.testing.assert_close(slow["rgb"], fast["rgb"], rtol=0, atol=1e-6)
    assert (slow["labels"] == CLASS_IDS["Road"]).any() and (slow["depth"] < town.far).any()


# -------------------------------------------------------------------- anti-aliasing

@pytest.mark.parametrize("k", [2, 3])
def test_antialias_keeps_labels_depth_range_and_flat_texels(town, cube, k):
    """``antialias=k`` changes only the RGB of the texels on an edge (``edge_texels`` of the
    centre rays' cube); labels, depth and range are the centre rays', as with ``k = 1``."""
    aa = town.render_cubemap(POSE, face_size=48, antialias=k)
    for key in ("labels", "depth", "range"):
        assert torch.equal(aa[key], cube[key]), key
    edge = torch.stack([edge_texels(cube["labels"][0, f], cube["range"][0, f],
                                    cube["rgb"][0, f]) for f in range(6)])
    changed = (aa["rgb"][0] != cube["rgb"][0]).any(1)
    assert not (changed & ~edge).any()
    assert changed.sum() > 0.5 * edge.sum()
    # straight up, far from the sun (45 deg up): a smooth sky, not supersampled
    up = FACES.index("up")
    assert not edge[up, 20:28, 20:28].any()
    assert torch.equal(aa["rgb"][0, up, :, 20:28, 20:28], cube["rgb"][0, up, :, 20:28, 20:28])


@pytest.mark.parametrize("rotated", [False, True])
@pytest.mark.parametrize("k", [2, 3])
def test_antialias_rgb_is_the_mean_of_the_sub_texel_rays(town, k, rotated):
    """A supersampled texel's RGB is the mean of its ``k x k`` stratified sub-texel rays
    (sub-texel ``(u, v)`` at ``(i + 0.5) / k - 0.5`` of a texel from the centre), traced here on
    their own (``render_rays``). The rays are built bit for bit as the cube builds them
    (``face_pixel_to_ray``, the rotation as element-wise sums; for odd ``k`` the middle one is
    the texel's own ray): the town's textures tell a ray's last bit apart (the ground's noise
    cells split at ``y = 0``, where its hit points' rounding falls)."""
    F, pos = 24, torch.tensor([1.0, -1.4, -3.0])
    rot = _rotation(0.3, -0.5, 0.1) if rotated else None
    one = town.render_cubemap(pos, rot, F, t=2.0)
    aa = town.render_cubemap(pos, rot, F, t=2.0, antialias=k)
    edge = torch.stack([edge_texels(one["labels"][0, f], one["range"][0, f], one["rgb"][0, f])
                        for f in range(6)])
    picked = torch.nonzero(edge)[torch.randperm(int(edge.sum()),
                                                generator=torch.Generator().manual_seed(0))[:40]]
    off = (torch.arange(k, dtype=torch.float32) + 0.5) / k - 0.5
    dv, du = (x.reshape(-1) for x in torch.meshgrid(off, off, indexing="ij"))
    centre = (du == 0) & (dv == 0)
    for f, i, j in picked.tolist():
        uv = torch.stack([j + du[~centre], i + dv[~centre]], -1)
        rays = face_pixel_to_ray(f, uv, F, normalize=True)
        if rot is not None:
            rays = rays[:, :1] * rot[:, 0] + rays[:, 1:2] * rot[:, 1] + rays[:, 2:] * rot[:, 2]
        if centre.any():
            rays = torch.cat([rays, town.cubemap_rays(F, rot)[f, i, j][None]])
        assert len(rays) == k * k
        mean = town.render_rays(pos, rays, t=2.0)["rgb"].mean(0)
        torch.testing.assert_close(aa["rgb"][0, f, :, i, j], mean, rtol=0, atol=1e-6)
    # most texels on an edge change colour
    assert (aa["rgb"][0].movedim(1, -1)[edge] != one["rgb"][0].movedim(1, -1)[edge]).any(-1) \
        .float().mean() > 0.5


def test_antialias_with_texel_masks_and_buffers(town):
    """Within ``texels``, a texel whose 8 neighbours are all rendered is anti-aliased as on a
    whole face; the others stay unrendered; ``out`` buffers are written in place."""
    F = 32
    whole = town.render_cubemap(POSE, face_size=F, antialias=2)
    mask = torch.zeros(6, F, F, dtype=torch.bool)
    mask[:, 4:20, 6:30] = True
    out = {"rgb": torch.full((1, 6, 3, F, F), 7.0)}
    part = town.render_cubemap(POSE, face_size=F, texels=mask, out=out, antialias=2)
    assert part["rgb"].data_ptr() == out["rgb"].data_ptr()
    assert torch.equal(part["rgb"][0, :, :, 5:19, 7:29], whole["rgb"][0, :, :, 5:19, 7:29])
    assert (part["rgb"][0].movedim(1, -1)[~mask] == 0).all()
    assert (part["labels"][0][~mask] == 255).all()
    faces = torch.tensor([True, False, False, False, True, False])
    sub = town.render_cubemap(POSE, face_size=F, faces=faces, antialias=2)
    assert torch.equal(sub["rgb"][0, faces], whole["rgb"][0, faces])
    assert (sub["rgb"][0, ~faces] == 0).all()


def test_bad_antialias(town):
    for bad in (0, -2, 1.5, True, "2", None):
        with pytest.raises(ValueError, match="antialias"):
            town.render_cubemap(POSE, face_size=8, antialias=bad)


def test_texel_subset_with_the_torch_twins(town, cube):
    """The torch twins write a texel subset's colours too (and anti-alias them)."""
    mask = torch.zeros(6, 48, 48, dtype=torch.bool)
    mask[:, 10:30, 5:25] = True
    part = town.render_cubemap(POSE, face_size=48, texels=mask, backend="torch")
    torch.testing.assert_close(part["rgb"][0].movedim(1, -1)[mask],
                               cube["rgb"][0].movedim(1, -1)[mask], rtol=0, atol=1e-6)
    aa = town.render_cubemap(POSE, face_size=48, texels=mask, antialias=2, backend="torch")
    assert torch.equal(aa["labels"], part["labels"])
