"""``generate --rig woodscape``: WoodScape's four cameras on a car, in WoodScape's layout, read
back the way WoodScape's tools and OmniDet's loader read it.

The readers here are written from their documented formats (WoodScape's README and scripts,
OmniDet's ``woodscape_loader.py``), not from the package: ``PIL.Image.open(...).convert``, the
calibration's intrinsic values by position, ``np.loadtxt(..., delimiter=",", usecols=(1, 2,
3, 4, 5))``, the displacement from two speeds and timestamps. Where a copy of WoodScape is on
the machine (the git mirror the project's tools fetch, or ``WOODSCAPE_REPO``), OmniDet's
loader itself reads the folder too (``test_omnidet_loader_reads_the_folder``; never imported
by the package). The geometry's oracle is WoodScape's documented projection
(``test_woodscape.DocumentedCamera``): road pixels, lifted by their distance through the
calibration file, lie on the ground.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import subprocess
import sys
import types
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.data import woodscape
from omniscape_torch.data.generate import CAMERAS, DatasetConfig, generate
from omniscape_torch.data.resume import folder_frames
from omniscape_torch.io import read_exr
from omniscape_torch.scenes import ride

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_woodscape import DocumentedCamera  # noqa: E402

Image = pytest.importorskip("PIL.Image")
cv2 = pytest.importorskip("cv2")

H, W = 48, 64
FRAMES = 2
NAMES = ("FV", "MVL", "MVR", "RV")
_MIRROR = Path("/work/.mirror/valeoai+WoodScape/repo")
_LOADER = "omnidet/data_loader/woodscape_loader.py"

#: WoodScape's README and OmniDet's loader: the per-image files (the loader's paths where the
#: two disagree), written out here from their text.
LAYOUT = ("rgb_images/{f}_{c}.png", "previous_images/{f}_{c}_prev.png",
          "semantic_annotations/gtLabels/{f}_{c}.png",
          "semantic_annotations/rgbLabels/{f}_{c}.png", "instance_annotations/{f}_{c}.json",
          "box_2d_annotations/{f}_{c}.txt", "calibration_data/calibration/{f}_{c}.json",
          "vehicle_data/rgb_images/{f}_{c}.json", "vehicle_data/previous_images/{f}_{c}.json",
          "distance_maps/{f}_{c}.exr")
#: scripts/configs/semantic_mapping_9_classes.json (ids 1..9, void 0) and the box classes of
#: box_2d_mapping_5_classes.json (ids 0..4), written out.
SEMANTIC_IDS = range(10)
BOX_CLASSES = {"vehicles": 0, "person": 1, "bicycle": 2, "traffic_light": 3,
               "traffic_sign": 4}
#: scripts/mappers/class_names.json for the tags the town has.
TAG_CLASS = {"car": "vehicles", "person": "person", "traffic_sign": "traffic_sign",
             "pole": "void"}


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("woodscape") / "ws"
    assert cli.main(["generate", "--rig", "woodscape", "--out", str(out), "--frames",
                     str(FRAMES), "--image-size", f"{H}x{W}", "--antialias", "1",
                     "--face-size", "48", "--no-progress"]) == 0
    return out


def _frames():
    return [f"{k:05d}" for k in range(FRAMES)]


def _image(path, mode):
    with Image.open(path) as im:
        return np.asarray(im.convert(mode))


# --------------------------------------------------------------------------------------------
# Paths and formats
# --------------------------------------------------------------------------------------------

def test_the_layout_is_woodscapes(folder):
    expected = {p.format(f=f, c=c) for p in LAYOUT for f in _frames() for c in NAMES}
    found = {p.relative_to(folder).as_posix() for p in folder.rglob("*")
             if p.is_file() and not p.name.startswith(".")
             and not p.relative_to(folder).as_posix().startswith(".")}
    run_files = {"dataset.json", "dynamics.json", "dynamics.csv", "dynamics_previous.json",
                 "contact_sheet.png"}
    assert found - run_files == expected
    assert run_files <= found
    # OmniDet's path files list rgb_images' names; its loader splits them so
    for name in os.listdir(folder / "rgb_images"):
        frame, cam = name.split(".")[0].split("_")
        assert frame in _frames() and cam in NAMES


def test_images_read_as_the_loader_reads_them(folder):
    for f in _frames():
        for c in NAMES:
            rgb = _image(folder / f"rgb_images/{f}_{c}.png", "RGB")
            prev = _image(folder / f"previous_images/{f}_{c}_prev.png", "RGB")
            gt = _image(folder / f"semantic_annotations/gtLabels/{f}_{c}.png", "L")
            colour = _image(folder / f"semantic_annotations/rgbLabels/{f}_{c}.png", "RGB")
            assert rgb.shape == prev.shape == (H, W, 3) and gt.shape == (H, W)
            assert set(np.unique(gt)) <= set(SEMANTIC_IDS)   # OmniDet zeroes ids above 9
            assert {1, 2} <= set(np.unique(gt))              # road and lane marks: seen
            # rgbLabels: the config's BGR colours, as cv2.imwrite writes them (RGB reversed)
            bgr = np.array([[0, 0, 0], [255, 0, 255], [255, 0, 0], [0, 255, 0], [0, 0, 255],
                            [255, 255, 255], [255, 255, 0], [0, 255, 255], [128, 128, 255],
                            [0, 128, 128]], np.uint8)
            assert np.array_equal(colour, bgr[gt][..., ::-1])
            distance = read_exr(folder / f"distance_maps/{f}_{c}.exr").numpy()
            assert distance.shape == (H, W) and (distance >= 0).all()
            # outside the 190-degree image circle: void, black and no distance
            assert (gt[distance == 0] == 0).all() and (rgb[distance == 0] == 0).all()


def test_calibration_read_by_position_as_omnidet_does(folder):
    for c in NAMES:
        data = json.loads((folder / f"calibration_data/calibration/00001_{c}.json").read_text())
        assert data["name"] == c
        values = list(data["intrinsic"].values())     # OmniDet: the values by position
        aspect, cx_offset, cy_offset = values[:3]
        k = values[4:8]
        camera, _ = woodscape.rig_camera(c, (H, W))
        cx, cy = camera.params[:2].tolist()
        assert abs(cx_offset + W / 2 - 0.5 - cx) < 1e-9
        assert abs(cy_offset + H / 2 - 0.5 - cy) < 1e-9
        assert values[3] == H and values[10] == W and values[8] == "radial_poly"
        assert k == camera.params[3:].tolist() and aspect == pytest.approx(float(camera.params[2]))


def test_boxes_read_as_the_loader_reads_them(folder):
    seen = 0
    for f in _frames():
        for c in NAMES:
            path = folder / f"box_2d_annotations/{f}_{c}.txt"
            if os.stat(path).st_size == 0:      # OmniDet: an empty file, no box
                continue
            boxes = np.loadtxt(path, delimiter=",", usecols=(1, 2, 3, 4, 5)).reshape(-1, 5)
            names = [row[0] for row in csv.reader(path.read_text().splitlines())]
            assert [BOX_CLASSES[n] for n in names] == boxes[:, 0].astype(int).tolist()
            x0, y0, x1, y1 = boxes[:, 1:].T
            assert (0 <= x0).all() and (x0 <= x1).all() and (x1 <= W - 1).all()
            assert (0 <= y0).all() and (y0 <= y1).all() and (y1 <= H - 1).all()
            # WoodScape's filters: 400 px at 1280 x 966 (scaled), no side under a tenth
            w, h = x1 - x0, y1 - y0
            assert (w * h >= 400 * H * W / (966 * 1280)).all()
            assert (w >= 0.1 * h).all() and (h >= 0.1 * w).all()
            seen += len(boxes)
    assert seen > 0


def test_instance_polygons_cover_their_objects_labels(folder):
    """WoodScape's semantic_map_generator, written out: fill each annotation's polygon (in
    z-order) with its class's id; the things' pixels of gtLabels are the polygons'."""
    semantic = {"vehicles": 6, "person": 4, "traffic_sign": 9}
    compared = 0
    for f in _frames():
        for c in NAMES:
            doc = json.loads((folder / f"instance_annotations/{f}_{c}.json").read_text())
            (key, entry), = doc.items()
            assert key == f"{f}_{c}.png"
            assert (entry["image_width"], entry["image_height"]) == (W, H)
            drawn = np.zeros((H, W), np.uint8)
            for a in sorted(entry["annotation"], key=lambda a: a["z_order"]):
                assert len(a["tags"]) == 1 and a["tags"][0] in TAG_CLASS
                pts = np.array(a["segmentation"])
                assert pts.shape[1] == 2 and len(pts) >= 3
                assert (pts >= 0).all() and (pts[:, 0] < W).all() and (pts[:, 1] < H).all()
                cls = TAG_CLASS[a["tags"][0]]
                if cls in semantic:
                    cv2.fillPoly(drawn, [pts.astype(np.int32)], semantic[cls])
            gt = _image(folder / f"semantic_annotations/gtLabels/{f}_{c}.png", "L")
            things = np.isin(gt, list(semantic.values()))
            assert (drawn[things] == gt[things]).all()      # every thing's pixel is covered
            if drawn.any():
                assert (drawn[drawn > 0] == gt[drawn > 0]).mean() > 0.8
                compared += int(things.sum())
    assert compared > 0


def test_boxes_are_the_polygons_extent(folder):
    """box_2d_generator.py, written out: an object's box is its polygons' extent (the parts of
    one group_id merged); the box file holds the objects that pass the filters."""
    for f in _frames():
        for c in NAMES:
            doc = json.loads((folder / f"instance_annotations/{f}_{c}.json").read_text())
            objects = {}
            for a in next(iter(doc.values()))["annotation"]:
                cls = TAG_CLASS[a["tags"][0]]
                if cls == "void":
                    continue
                pts = np.array(a["segmentation"])
                box = [pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()]
                key = a["group_id"] or ("one", a["id"])
                if key in objects:
                    old = objects[key][1]
                    box = [min(old[0], box[0]), min(old[1], box[1]), max(old[2], box[2]),
                           max(old[3], box[3])]
                objects[key] = (cls, box)
            expected = sorted([cls, BOX_CLASSES[cls], *map(int, box)]
                              for cls, box in objects.values()
                              if (box[2] - box[0]) * (box[3] - box[1]) >= 400 * H * W / 966 / 1280
                              and box[2] - box[0] >= 0.1 * (box[3] - box[1])
                              and box[3] - box[1] >= 0.1 * (box[2] - box[0]))
            rows = [[r[0], *map(int, r[1:])] for r in csv.reader(
                (folder / f"box_2d_annotations/{f}_{c}.txt").read_text().splitlines())]
            assert sorted(rows) == expected


def test_polygons_trace_the_instance_map():
    """One object of two parts and a one-pixel object: the parts share a group id, each
    filled polygon is its part, and the extent is the tight box of the pixels."""
    ids = torch.zeros(20, 30, dtype=torch.int64)
    ids[2:8, 3:9] = 5
    ids[12:18, 20:27] = 5
    ids[10, 12] = 7
    labels = torch.where(ids > 0, 10, 7)   # Vehicle on Road
    doc = woodscape.instance_annotations(ids, labels, "x.png")
    parts = doc["x.png"]["annotation"]
    assert [a["group_id"] for a in parts] == [5, 5, None]
    assert [a["tags"] for a in parts] == [["car"]] * 3
    for a in parts[:2]:
        drawn = np.zeros((20, 30), np.uint8)
        cv2.fillPoly(drawn, [np.array(a["segmentation"], np.int32)], 1)
        assert drawn.sum() == 36 or drawn.sum() == 42
        assert (ids.numpy()[drawn > 0] == 5).all()
    assert woodscape.box_rows(doc) == [["vehicles", 0, 3, 2, 26, 17]]   # 7: too small


# --------------------------------------------------------------------------------------------
# The calibration files and the geometry
# --------------------------------------------------------------------------------------------

def test_calibration_files_project_as_the_cameras_rendered(folder):
    """Road pixels, lifted by their distance through the calibration file with WoodScape's
    documented projection, lie on the town's flat ground (the car's attitude from
    dynamics.json): the files, the images and the distances agree."""
    dynamics = json.loads((folder / "dynamics.json").read_text())
    to_rig = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # ISO -> OpenCV
    for k, f in enumerate(_frames()):
        r = dynamics[k]["rotation"]
        R = ride.camera_rotation(torch.tensor([r["roll"], r["pitch"], r["yaw"]],
                                              dtype=torch.float64)).numpy()
        for c in NAMES:
            path = folder / f"calibration_data/calibration/{f}_{c}.json"
            camera, T, name = ot.cameras.read_woodscape(path)
            assert name == c and camera.image_size == (H, W)
            gt = _image(folder / f"semantic_annotations/gtLabels/{f}_{c}.png", "L")
            distance = read_exr(folder / f"distance_maps/{f}_{c}.exr").numpy()
            v, u = np.nonzero((gt == 1) & (distance > 0) & (distance < 20))
            points = DocumentedCamera(json.loads(path.read_text())).project_2d_to_3d(
                np.stack((u, v), 1).astype(float), distance[v, u])
            height = -(points @ to_rig.T @ R.T)[:, 1]   # world y is down
            assert len(height) > 500
            # measured: |median| <= 0.1 mm, 90 % within 3-5 cm (the nearest texel's depth,
            # 48-texel faces); the file tilted 1 degree: a median of 3-8 mm in FV, MVR, RV
            # (MVL's tilt is the next test's)
            assert abs(np.median(height)) < 0.002, (c, np.median(height))
            assert np.percentile(np.abs(height), 90) < 0.07


def test_the_town_along_the_files_rays_is_what_the_images_show(folder):
    """Each pixel's ray, from its calibration file (WoodScape's documented projection) and the
    car's pose (dynamics.json), traced through the town: the distance and the class the
    images hold (all six degrees of freedom of each camera, and its lens)."""
    from omniscape_torch.scenes.town import Town

    town = Town(0, layout=1)
    dynamics = json.loads((folder / "dynamics.json").read_text())
    to_rig = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # ISO -> OpenCV
    k, f = 1, _frames()[1]
    r, loc = dynamics[k]["rotation"], dynamics[k]["location"]
    R = ride.camera_rotation(torch.tensor([r["roll"], r["pitch"], r["yaw"]],
                                          dtype=torch.float64)).numpy() @ to_rig
    location = np.array([loc["y"], -loc["z"], loc["x"]])   # CARLA -> world (x east, y down)
    for c in NAMES:
        path = folder / f"calibration_data/calibration/{f}_{c}.json"
        oracle = DocumentedCamera(json.loads(path.read_text()))
        distance = read_exr(folder / f"distance_maps/{f}_{c}.exr").numpy()
        gt = _image(folder / f"semantic_annotations/gtLabels/{f}_{c}.png", "L")
        v, u = np.nonzero(distance > 0)
        ends = oracle.project_2d_to_3d(np.stack((u, v), 1).astype(float), np.ones(len(u)))
        origin = location + R @ oracle.translation
        directions = (ends - oracle.translation) @ R.T
        traced = town.render_rays(torch.from_numpy(origin).float(),
                                  torch.from_numpy(directions).float(),
                                  t=float(dynamics[k]["timestamp"]))
        near = traced["range"].numpy() < 100
        error = np.abs(distance[v, u][near] / traced["range"].numpy()[near] - 1)
        assert near.sum() > 300
        # measured: 0.57-0.86 % (the nearest texel's depth, 48-texel faces); the file turned
        # 3 degrees about the optical axis: 1.6-4.5 %; tilted 1 degree: 0.8-1.5 % (MVL, MVR
        # 1.3-1.5 %; FV and RV: off the ground, the test above)
        assert np.median(error) < 0.011, (c, np.median(error))
        same = woodscape.semantic_labels(traced["labels"]) == gt[v, u]
        assert same.mean() > 0.95, (c, same.mean())


def test_the_cameras_are_woodscapes():
    """FV is front.json's camera; each camera at 1280 x 966 projects as its file says."""
    from test_woodscape import FRONT

    assert woodscape.calibration("FV") == FRONT
    for c in NAMES:
        camera, T = woodscape.rig_camera(c)
        oracle = DocumentedCamera(woodscape.calibration(c))
        gen = np.random.default_rng(1)
        world = np.stack((gen.uniform(-10, 15, 500), gen.uniform(-8, 8, 500),
                          gen.uniform(0, 3, 500)), -1)
        t = T.numpy()
        pixels, valid = camera.model.project(torch.from_numpy((world - t[:3, 3]) @ t[:3, :3]),
                                             camera.params)
        theirs = oracle.project_3d_to_2d(world)
        assert valid.sum() > 100
        assert np.abs(pixels.numpy()[valid.numpy()] - theirs[valid.numpy()]).max() < 1e-6


# --------------------------------------------------------------------------------------------
# The vehicle data and the car
# --------------------------------------------------------------------------------------------

def test_displacement_from_speed_is_the_distance_driven(folder):
    """OmniDet's get_displacements_from_speed, written out: microseconds and km/h."""
    now = json.loads((folder / "dynamics.json").read_text())
    before = json.loads((folder / "dynamics_previous.json").read_text())
    for k, f in enumerate(_frames()):
        for c in NAMES:
            prev = json.loads((folder / f"vehicle_data/previous_images/{f}_{c}.json").read_text())
            cur = json.loads((folder / f"vehicle_data/rgb_images/{f}_{c}.json").read_text())
            t = [float(prev["timestamp"]) / 1e6, float(cur["timestamp"]) / 1e6]
            v = [float(prev["ego_speed"]) / 3.6, float(cur["ego_speed"]) / 3.6]
            assert t[1] - t[0] == pytest.approx(1 / 30, abs=2e-6)
            displacement = 0.5 * (v[1] + v[0]) * (t[1] - t[0])
            a, b = now[k]["location"], before[k]["location"]
            driven = float(np.hypot(a["x"] - b["x"], a["y"] - b["y"]))
            assert displacement == pytest.approx(driven, abs=1e-4)
    assert json.loads((folder / "vehicle_data/previous_images/00000_FV.json").read_text())[
        "ego_speed"] == 0   # frame 0: the car at rest at its start


def test_a_car_rolls_out_of_the_turns_and_a_motorcycle_into_them():
    from omniscape_torch.data.generate import town_route

    route = town_route(0, 1)
    car = ride.simulate(route, 4.0, frames=120, **ride.CAR)
    bike = ride.simulate(route, 4.0, frames=120)
    for states, sign, top in ((car, -1, 2.0), (bike, 1, 30.0)):
        turning = states["lateral_acceleration"].abs() > 0.8
        roll = states["rotation"][turning, 0]
        assert turning.sum() > 10
        assert (torch.sign(roll) == sign * torch.sign(
            states["lateral_acceleration"][turning])).float().mean() > 0.9
        assert roll.abs().max() < top
    assert car["speed"].max() <= ride.CAR["max_speed"] + 1e-9
    assert car["lateral_acceleration"].abs().max() <= ride.CAR["max_lateral_acceleration"] + 0.05
    assert car["rotation"][:, 0].abs().max() < 1.5 < bike["rotation"][:, 0].abs().max()


# --------------------------------------------------------------------------------------------
# Resume, defaults, errors
# --------------------------------------------------------------------------------------------

def test_a_rerun_completes_an_interrupted_run(folder, tmp_path):
    out = tmp_path / "ws"
    import shutil

    shutil.copytree(folder, out)
    (out / ".done/000001").unlink()                          # killed before its marker
    (out / "box_2d_annotations/00001_MVR.txt").unlink()
    kept = (out / "rgb_images/00000_FV.png").stat().st_mtime_ns
    config = DatasetConfig(rig="woodscape", frames=FRAMES, image_size=(H, W), antialias=1,
                           face_size=48)   # the fixture's
    result = generate(out, config, progress=False)
    assert result["rendered"] == [1] and result["skipped"] == [0]
    assert (out / "rgb_images/00000_FV.png").stat().st_mtime_ns == kept
    for p in LAYOUT:
        a, b = folder / p.format(f="00001", c="MVR"), out / p.format(f="00001", c="MVR")
        assert a.read_bytes() == b.read_bytes(), p   # frame k depends on the settings and k
    assert generate(out, config, progress=False)["rendered"] == []


def test_the_default_rig_is_unchanged(tmp_path):
    config = DatasetConfig()
    assert (config.rig, config.image_size, config.cameras) == ("omniscape", (256, 256), CAMERAS)
    assert DatasetConfig(rig="woodscape").image_size == (966, 1280)
    assert DatasetConfig(rig="woodscape").cameras == NAMES
    # a folder written before the rig existed is the omniscape rig's
    old = DatasetConfig(frames=2).to_dict()
    del old["rig"]
    (tmp_path / "dataset.json").write_text(json.dumps({"config": old}))
    assert folder_frames(tmp_path, DatasetConfig(frames=2)) == 2
    with pytest.raises(ValueError, match="--rig: the folder has omniscape, this run woodscape"):
        folder_frames(tmp_path, DatasetConfig(frames=2, rig="woodscape", image_size=(256, 256),
                                              cameras=NAMES))


@pytest.mark.parametrize("argv, message", [
    (["--rig", "woodscape", "--cameras", "fisheye_left"], "unknown camera 'fisheye_left' of "
                                                          "the woodscape rig"),
    (["--cameras", "FV"], "unknown camera 'FV' of the omniscape rig"),
    (["--rig", "woodscape", "--format", "webdataset"], "WoodScape's layout is a folder"),
    (["--rig", "woodscape", "--save-panorama"], "not with rig='woodscape'"),
])
def test_woodscape_options_refused_in_one_line(tmp_path, capsys, argv, message):
    assert cli.main(["generate", "--out", str(tmp_path / "x"), "--frames", "1",
                     "--image-size", "16", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


# --------------------------------------------------------------------------------------------
# OmniDet's own loader, where a copy of WoodScape is here
# --------------------------------------------------------------------------------------------

def _loader_source(tmp: Path) -> Path | None:
    root = os.environ.get("WOODSCAPE_REPO")
    if root and (Path(root) / _LOADER).is_file():
        return Path(root) / _LOADER
    if _MIRROR.is_dir():
        done = subprocess.run(["git", f"--git-dir={_MIRROR}", "show", f"HEAD:{_LOADER}"],
                              capture_output=True)
        if done.returncode == 0:
            (tmp / "woodscape_loader.py").write_bytes(done.stdout)
            return tmp / "woodscape_loader.py"
    return None


def test_omnidet_loader_reads_the_folder(folder, tmp_path, monkeypatch):
    """OmniDet's WoodScapeRawDataset (never imported by the package) reads the images, the
    semantic labels, the boxes, the intrinsics and the displacement of every image; its
    torchvision transforms (used by its training pipeline, not its readers) are stubbed."""
    source = _loader_source(tmp_path)
    if source is None:
        pytest.skip("no copy of WoodScape here (set WOODSCAPE_REPO to a checkout)")
    tv = types.ModuleType("torchvision")
    tv.transforms = types.SimpleNamespace(
        ToTensor=lambda: None, Resize=lambda *a, **k: None, ColorJitter=lambda **k: None,
        InterpolationMode=types.SimpleNamespace(BICUBIC=3, NEAREST=0))
    utils = types.ModuleType("train_utils.detection_utils")
    utils.crop_annotation = None
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "train_utils", types.ModuleType("train_utils"))
    monkeypatch.setitem(sys.modules, "train_utils.detection_utils", utils)
    spec = importlib.util.spec_from_file_location("omnidet_woodscape_loader", source)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    paths = tmp_path / "val.txt"
    paths.write_text("".join(f"{f}_{c}.png\n" for f in _frames() for c in NAMES))
    config = types.SimpleNamespace(train="semantic_detection", batch_size=1, crop=False,
                                   semantic_num_classes=10, num_scales=4, frame_idxs=[0, -1],
                                   input_width=W, input_height=H)
    loader = module.WoodScapeRawDataset(data_path=str(folder), path_file=str(paths),
                                        is_train=False, config=config)
    loader.original_res = namedtuple("original_res", "width height")(W, H)   # not 1280 x 966
    boxes = 0
    for line in loader.image_paths:
        frame, cam = line.split(".")[0].split("_")
        for i in config.frame_idxs:
            assert loader.get_image(i, None, frame, cam).size == (W, H)
        label = np.array(loader.get_label("semantic_annotations", None, frame, cam))
        assert label.shape == (H, W) and label.max() <= 9
        K, D, intrinsics = loader.get_intrinsics(None, frame, cam)
        camera, _ = woodscape.rig_camera(cam, (H, W))
        assert intrinsics[4] == float(camera.params[3])           # k1: its LUTs' key
        assert np.allclose(D, camera.params[3:].numpy())          # input size = image size
        assert abs(K[2] - 0.5 - float(camera.params[0])) < 1e-3   # its pixel-corner origin
        targets = loader.get_detection_label(None, frame, cam)
        if targets[:, 2:].abs().sum() > 0:
            assert ((targets[:, 2:4] >= 0) & (targets[:, 2:4] <= 1)).all()   # centres
            assert ((targets[:, 4:] >= 0) & (targets[:, 4:] <= 1)).all()     # sizes
            assert ((targets[:, 1] >= 0) & (targets[:, 1] <= 4)).all()
            boxes += len(targets)
        assert float(loader.get_displacements_from_speed(frame, cam)) >= 0
    assert boxes > 0


def test_the_folder_reads_back_as_tensors(folder):
    from omniscape_torch.data.datasets import collate

    dataset = woodscape.WoodScapeDataset(folder)
    assert [(f, c) for f, c in dataset.items] == [(f, c) for f in _frames() for c in NAMES]
    for item in dataset:
        f, c = item["frame"], item["camera"]
        assert item["rgb"].shape == item["previous"].shape == (3, H, W)
        gt = _image(folder / f"semantic_annotations/gtLabels/{f}_{c}.png", "L")
        assert np.array_equal(item["labels"].numpy(), gt)
        assert torch.equal(item["valid"][0], item["depth"] > 0)
        rows = np.loadtxt(folder / f"box_2d_annotations/{f}_{c}.txt", delimiter=",",
                          usecols=(1, 2, 3, 4, 5), ndmin=2) if os.stat(
            folder / f"box_2d_annotations/{f}_{c}.txt").st_size else np.zeros((0, 5))
        assert np.array_equal(item["box_labels"].numpy(), rows[:, 0])
        assert np.array_equal(item["boxes"].numpy(), rows[:, 1:] + [0, 0, 1, 1])
        camera, T = woodscape.rig_camera(c, (H, W))
        assert torch.allclose(item["intrinsics"], camera.params)
        assert torch.allclose(item["T_vehicle_camera"], T)
        assert item["vehicle"]["timestamp"] > item["vehicle_previous"]["timestamp"]
    batch = collate([dataset[0], dataset[1]])
    assert batch["rgb"].shape == (2, 3, H, W) and isinstance(batch["boxes"], list)
