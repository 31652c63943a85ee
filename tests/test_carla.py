"""CARLA decoders (depth, semantic tags, label sets) and the cubemap-capture converter."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.data import ocamcalib
from omniscape_torch.data.captures import (ConvertError, build_cameras, calib_file,
                                           convert_captures, find_captures, load_capture,
                                           render_capture)
from omniscape_torch.cubemap import FACES, face_rays
from omniscape_torch.io.atomic import LOCK_NAME
from omniscape_torch.io.carla import (EXT23_TO_13, NEW_CLASSES, NEW_TO_13, decode_depth,
                                      decode_labels, encode_depth, map_labels, to_13)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ocamcalib_checks import OCAMCALIB_PX, check_calib_results  # noqa: E402
from test_ocamcalib_reference import harness  # noqa: E402,F401 (the compiled C fixture)

STEP = 1000.0 / (256 ** 3 - 1)   # one depth code, metres
CAPTURE_SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "carla_capture.py"


def _encode(depth_m: np.ndarray) -> np.ndarray:
    """CARLA's depth encoding, written independently of the library: (H, W, 3) uint8 RGB."""
    code = np.rint(np.asarray(depth_m, np.float64) / 1000.0 * (256 ** 3 - 1)).astype(np.int64)
    r, g, b = code % 256, (code // 256) % 256, code // 65536
    return np.stack([r, g, b], -1).astype(np.uint8)


# ---------------------------------------------------------------------------- decoders

def test_decode_depth_round_trip_rgb_and_bgra():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0, 1000, size=(7, 9))
    depth[0, 0], depth[0, 1], depth[0, 2] = 0.0, 1000.0, 1.0
    rgb = _encode(depth)
    got = decode_depth(rgb, "RGB")
    assert got.dtype == torch.float32 and got.shape == (7, 9)
    # half a code step, plus float32 rounding at 1000 m
    np.testing.assert_allclose(got.numpy(), depth, atol=STEP / 2 + 1e-4)
    assert float(got[0, 0]) == 0.0 and float(got[0, 1]) == 1000.0
    bgra = np.concatenate([rgb[..., ::-1], np.full((7, 9, 1), 255, np.uint8)], -1)
    assert torch.equal(decode_depth(bgra, "BGRA"), got)
    assert torch.equal(decode_depth(torch.from_numpy(bgra), "BGRA"), got)
    # the library's encoder agrees with the test's
    assert np.array_equal(encode_depth(depth, "RGB"), rgb)


def test_decode_depth_known_codes():
    img = np.zeros((1, 3, 3), np.uint8)
    img[0, 0] = (1, 0, 0)        # R is the low byte
    img[0, 1] = (0, 1, 0)        # G: 256
    img[0, 2] = (0, 0, 1)        # B: 65536
    got = decode_depth(img, "RGB").double().numpy()[0]
    np.testing.assert_allclose(got, np.array([1, 256, 65536]) * STEP, rtol=1e-6)


def test_decode_errors():
    with pytest.raises(TypeError, match="uint8"):
        decode_depth(np.zeros((2, 2, 3), np.uint16), "RGB")
    with pytest.raises(ValueError, match="channel_order"):
        decode_depth(np.zeros((2, 2, 3), np.uint8), "GRB")
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        decode_labels(np.zeros((2, 2), np.uint8))


def test_decode_labels_red_channel():
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = np.arange(6).reshape(2, 3) + 20
    rgb[..., 1:] = 7   # ignored
    got = decode_labels(rgb, "RGB")
    assert got.dtype == torch.int64
    assert got.tolist() == [[20, 21, 22], [23, 24, 25]]
    bgra = np.concatenate([rgb[..., ::-1], np.full((2, 3, 1), 255, np.uint8)], -1)
    assert torch.equal(decode_labels(bgra, "BGRA"), got)


def test_mappings_are_total_into_13_classes():
    assert len(NEW_CLASSES) == 29
    assert sorted(NEW_TO_13) == list(range(29))
    assert sorted(EXT23_TO_13) == list(range(23))
    for mapping in (NEW_TO_13, EXT23_TO_13):
        assert all(0 <= v <= 12 for v in mapping.values())
        assert set(mapping.values()) == set(range(13))   # every class reachable
    ids = torch.arange(29)
    assert to_13(ids, "new").tolist() == [NEW_TO_13[i] for i in range(29)]
    # spot checks of the documented choices (ObjectLabel.h ids -> paper classes)
    c = {n: i for i, n in enumerate(ot.io.CLASSES)}
    assert NEW_TO_13[1] == c["Road"] and NEW_TO_13[24] == c["RoadLine"]
    assert NEW_TO_13[14] == NEW_TO_13[19] == c["Vehicle"]
    assert NEW_TO_13[12] == c["Pedestrian"] and NEW_TO_13[11] == c["Unlabeled"]
    assert to_13(torch.arange(13), "13").tolist() == list(range(13))


def test_map_labels_unknown():
    with pytest.raises(ValueError, match=r"\[29, 255\]"):
        map_labels(torch.tensor([1, 29, 255]), NEW_TO_13)
    got = map_labels(np.array([[1, 29], [-1, 3]]), NEW_TO_13, unknown=255)
    assert got.tolist() == [[7, 255], [255, 1]]
    with pytest.raises(ValueError, match="not in the mapping"):
        to_13(torch.tensor([13]), "13")
    with pytest.raises(TypeError):
        map_labels(torch.tensor([1.0]), NEW_TO_13)


# ---------------------------------------------------------------------------- captures

F = 16


def _scene():
    """Analytic faces from the direction of every texel: rgb, planar depth, new-set tags."""
    rays = face_rays(F, dtype=torch.float64).numpy()           # [6, F, F, 3], axis part 1
    norm = np.linalg.norm(rays, axis=-1)
    d = rays / norm[..., None]
    rgb = np.rint(255 * (d + 1) / 2).astype(np.uint8)           # [6, F, F, 3]
    rng = 5.0 + 2.0 * d[..., 0] + d[..., 1]                    # range, metres
    depth = rng / norm                                          # planar depth along the face axis
    v, u = np.meshgrid(np.arange(F), np.arange(F), indexing="ij")
    tags = (np.arange(6)[:, None, None] * 5 + (u + 2 * v)[None]) % 29
    return rgb, depth, tags.astype(np.int64)


def _write_capture(folder, rgb, depth, tags):
    for k, face in enumerate(FACES):
        ot.io.write_image(folder / f"{face}_rgb.png", rgb[k])
        ot.io.write_image(folder / f"{face}_depth.png", _encode(depth[k]))
        lab = np.zeros((F, F, 3), np.uint8)
        lab[..., 0] = tags[k]
        ot.io.write_image(folder / f"{face}_labels.png", lab)


@pytest.fixture
def capture_root(tmp_path):
    root = tmp_path / "cubemaps"
    rgb, depth, tags = _scene()
    _write_capture(root / "000042", rgb, depth, tags)
    return root, (rgb, depth, tags)


def test_load_capture_gives_expected_cubemaps(capture_root):
    root, (rgb, depth, tags) = capture_root
    assert find_captures(root) == [root / "000042"]
    cube = load_capture(root / "000042", label_set="new")
    assert cube["face_size"] == F
    assert cube["rgb"].shape == (1, 6, 3, F, F) and cube["rgb"].dtype == torch.float32
    expected_rgb = torch.from_numpy(rgb).permute(0, 3, 1, 2).float() / 255
    assert torch.equal(cube["rgb"][0], expected_rgb)
    assert cube["depth"].shape == (1, 6, F, F) and cube["depth"].dtype == torch.float32
    np.testing.assert_allclose(cube["depth"][0].double().numpy(), depth, atol=STEP / 2 + 1e-5)
    expected_labels = np.vectorize(NEW_TO_13.get)(tags)
    assert cube["labels"].shape == (1, 6, F, F) and cube["labels"].dtype == torch.int64
    assert np.array_equal(cube["labels"][0].numpy(), expected_labels)
    # a folder that is itself a capture is accepted
    assert find_captures(root / "000042") == [root / "000042"]


def test_convert_writes_fisheye_and_catadioptric(capture_root, tmp_path):
    root, (rgb, depth, tags) = capture_root
    out = tmp_path / "out"
    results = convert_captures(root, out, label_set="new", image_size=(48, 48))
    assert set(results) == {"000042"}
    cap = out / "000042"
    for cam in ("fisheye", "catadioptric"):
        for suffix in ("rgb.png", "depth.exr", "labels.png", "labels_color.png", "valid.png"):
            assert (cap / f"{cam}_{suffix}").is_file(), f"{cam}_{suffix}"
    assert not list(cap.glob(".*"))   # no temporary files left
    meta = json.loads((out / "cameras.json").read_text())
    assert meta["fisheye"]["camera"]["model"] == "equidistant"
    for cam in ("fisheye", "catadioptric"):
        assert (out / calib_file(cam)).is_file()
        assert meta[cam]["ocamcalib"]["file"] == calib_file(cam)
    # the fisheye looks forward: range near the centre ~ 5 + 2 dx + dy with d ~ +z
    rng = ot.io.read_exr(cap / "fisheye_depth.exr")
    assert rng.shape == (48, 48)
    assert abs(float(rng[23:25, 23:25].mean()) - 5.0) < 0.3
    valid = ot.io.read_image(cap / "fisheye_valid.png") > 0
    assert bool((rng[valid] > 2.5).all()) and bool((rng[~valid] == 0).all())
    labels = ot.io.read_image(cap / "fisheye_labels.png")
    assert bool((labels[valid] <= 12).all()) and bool((labels[~valid] == 255).all())
    # the catadioptric (looking down) sees the down face around its centre, range ~ 5 + dy = 6
    cata = ot.io.read_exr(cap / "catadioptric_depth.exr")
    cvalid = ot.io.read_image(cap / "catadioptric_valid.png") > 0
    assert bool(cvalid.any()) and not bool(cvalid[23:25, 23:25].any())   # blind centre
    assert bool((cata[cvalid] > 2.5).all())


@pytest.mark.numerics
def test_convert_writes_ocamcalib_files_that_agree_with_the_cameras(capture_root, tmp_path,
                                                                    harness, monkeypatch):
    """OUT/<camera>_calib_results.txt: OCamCalib's C code reads it, and its cam2world and
    world2cam agree with the camera of cameras.json within 0.05 px at every pixel it sees; a
    rerun into the same folder fits nothing and keeps the files."""
    root, _ = capture_root
    out = tmp_path / "out"
    convert_captures(root, out, label_set="new", image_size=(48, 48))
    meta = json.loads((out / "cameras.json").read_text())
    for cam in ("fisheye", "catadioptric"):
        record = meta[cam]["ocamcalib"]
        assert record["within_tolerance"] and record["max_px"] <= ocamcalib.TOLERANCE_PX
        camera = ot.Camera.from_dict(meta[cam]["camera"])
        errors = check_calib_results(harness, out / calib_file(cam), camera, record)
        print(f"{cam}: degree {record['degree']}, {errors}")
        assert errors["cam2world_px"] <= OCAMCALIB_PX and errors["world2cam_px"] <= OCAMCALIB_PX
    files = {cam: (out / calib_file(cam)).read_bytes() for cam in ("fisheye", "catadioptric")}

    def refuse(*args, **kwargs):
        raise AssertionError("fitted again")

    monkeypatch.setattr(ocamcalib, "fit_polynomial", refuse)
    convert_captures(root, out, label_set="new", image_size=(48, 48))
    assert json.loads((out / "cameras.json").read_text()) == meta
    assert {cam: (out / calib_file(cam)).read_bytes() for cam in files} == files


def test_convert_samples_8bit_faces_as_they_are(tmp_path, monkeypatch):
    """``convert`` renders the PNG faces' uint8 levels (channels innermost, no float copy)
    into the 8-bit image it writes: within a level of the float path (faces / 255 rendered in
    floats, then rounded), with EXR depth faces, and the other files identical."""
    from omniscape_torch.data.captures import build_cameras, render_capture
    from omniscape_torch.render.kernels.cube import is_channels_last
    from omniscape_torch.render.layer import OmniProjection

    _, depth, tags = _scene()
    rgb = np.random.default_rng(5).integers(0, 256, (6, F, F, 3), dtype=np.uint8)  # sharp
    capture = tmp_path / "cubemaps" / "000007"
    _write_capture(capture, rgb, depth, tags)
    for k, face in enumerate(FACES):   # float faces keep working beside 8-bit ones
        (capture / f"{face}_depth.png").unlink()
        ot.io.write_exr(capture / f"{face}_depth.exr", depth[k].astype(np.float32))

    cube = load_capture(capture, label_set="new", rgb_uint8=True)
    assert cube["rgb"].dtype == torch.uint8 and cube["rgb"].shape == (1, 6, 3, F, F)
    assert is_channels_last(cube["rgb"])   # the files' layout, read without a copy
    assert torch.equal(cube["rgb"][0], torch.from_numpy(rgb).permute(0, 3, 1, 2))
    with pytest.raises(TypeError, match="rgb_uint8"):
        load_capture(capture, label_set="new", rgb_uint8=1)

    seen = []
    real = OmniProjection.render

    def spy(self, **kwargs):
        if kwargs.get("rgb") is not None:
            seen.append((kwargs["rgb"].dtype, kwargs.get("channels_last")))
        return real(self, **kwargs)

    monkeypatch.setattr(OmniProjection, "render", spy)
    size = (40, 40)
    convert_captures(tmp_path / "cubemaps", tmp_path / "u8", label_set="new", image_size=size)
    assert seen == [(torch.uint8, True)] * 2
    cameras = build_cameras(image_size=size)
    render_capture(load_capture(capture, label_set="new"), cameras, tmp_path / "float")
    assert seen[2:] == [(torch.float32, False)] * 2
    compared = 0
    for cam in ("fisheye", "catadioptric"):
        got = ot.io.read_image(tmp_path / "u8" / "000007" / f"{cam}_rgb.png").int()
        ref = ot.io.read_image(tmp_path / "float" / f"{cam}_rgb.png").int()
        valid = ot.io.read_image(tmp_path / "u8" / "000007" / f"{cam}_valid.png") > 0
        assert got.shape == (*size, 3)
        assert int((got - ref).abs().max()) <= 1
        assert bool((got[~valid] == 0).all()) and int(got[valid].float().std()) > 10
        compared += int(valid.sum())
        for suffix in ("valid.png", "labels.png"):
            assert torch.equal(ot.io.read_image(tmp_path / "u8" / "000007" / f"{cam}_{suffix}"),
                               ot.io.read_image(tmp_path / "float" / f"{cam}_{suffix}"))
        assert torch.equal(ot.io.read_exr(tmp_path / "u8" / "000007" / f"{cam}_depth.exr"),
                           ot.io.read_exr(tmp_path / "float" / f"{cam}_depth.exr"))
    assert compared > 0


def test_missing_face_names_the_file(capture_root):
    root, _ = capture_root
    (root / "000042" / "up_depth.png").unlink()
    with pytest.raises(ValueError, match="up_depth.png"):
        load_capture(root / "000042")


def test_mismatched_face_size(capture_root):
    root, _ = capture_root
    ot.io.write_image(root / "000042" / "left_rgb.png", np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="left_rgb.png"):
        load_capture(root / "000042", label_set="new")
    ot.io.write_image(root / "000042" / "left_rgb.png", np.zeros((16, 12, 3), np.uint8))
    with pytest.raises(ValueError, match="square"):
        load_capture(root / "000042", label_set="new")


def test_decode_instances_tag_in_red_id_in_green_and_blue():
    image = np.zeros((1, 2, 4), np.uint8)
    image[0, 0, :3] = (14, 44, 1)     # RGB: Car, id 44 + 256 * 1
    image[0, 1, :3] = (3, 255, 255)   # Buildings, id 65535
    from omniscape_torch.io.carla import decode_instances
    tags, ids = decode_instances(image, "RGBA")
    assert tags.tolist() == [[14, 3]] and ids.tolist() == [[300, 65535]]
    tags, ids = decode_instances(image[..., [2, 1, 0, 3]], "BGRA")
    assert tags.tolist() == [[14, 3]] and ids.tolist() == [[300, 65535]]


def test_convert_writes_instances_and_objects_from_carla_instance_faces(tmp_path):
    """A capture of rgb, depth and CARLA instance faces (tag in R, id = G + 256 B; no label
    faces): the fisheye's instance ids (16-bit PNG, read with Pillow) are the face texels'
    ids that its pixel rays hit (nearest texel, computed here from the face table), kept for
    cars and pedestrians, not for a building; the labels come from the tags; each object's
    box is the tight box of its pixels."""
    from PIL import Image

    rgb, depth, _ = _scene()
    folder = tmp_path / "cubemaps" / "000001"
    folder.mkdir(parents=True)
    inst = np.zeros((6, F, F, 3), np.uint8)
    inst[..., 0] = 11                                      # Sky, id 0
    front, left = FACES.index("front"), FACES.index("left")
    inst[front, 5:11, 3:9] = (14, 44, 1)                   # a car, id 300
    inst[front, 0:3, :] = (3, 5, 0)                        # a building, id 5: not an instance
    inst[left, 6:12, 6:9] = (12, 7, 0)                     # a pedestrian, id 7
    for k, face in enumerate(FACES):
        ot.io.write_image(folder / f"{face}_rgb.png", rgb[k])
        ot.io.write_image(folder / f"{face}_depth.png", _encode(depth[k]))
        ot.io.write_image(folder / f"{face}_instances.png", inst[k])
    # what convert does with each capture (convert_chunk), without its OCamCalib fit
    cameras = build_cameras(("fisheye",), image_size=(40, 40))
    cap = tmp_path / "out" / "000001"
    render_capture(load_capture(folder, label_set="new", rgb_uint8=True), cameras, cap)
    with Image.open(cap / "fisheye_instances.png") as im:
        ids = np.asarray(im).astype(np.int64)
    labels = ot.io.read_image(cap / "fisheye_labels.png").numpy()
    assert set(np.unique(ids).tolist()) == {0, 7, 300}
    assert np.array_equal(ids == 300, labels == 10) and np.array_equal(ids == 7, labels == 4)
    # the front face's texel of each pixel ray, nearest (face table: a = +z, b = +y, r = +x)
    rays, valid = cameras["fisheye"][0].ray_grid()
    x, y, z = rays.double().unbind(-1)
    on_front = valid & (z > x.abs()) & (z > y.abs())
    u = torch.round(F / 2 * x / z + (F - 1) / 2)
    v = torch.round(F / 2 * y / z + (F - 1) / 2)
    car = on_front & (u >= 3) & (u <= 8) & (v >= 5) & (v <= 10)
    away = 0.02 * F   # rays within a texel's rounding of a texel edge may go either way
    clear = ((F / 2 * x / z + (F - 1) / 2 - u).abs() < 0.5 - away) & \
        ((F / 2 * y / z + (F - 1) / 2 - v).abs() < 0.5 - away)
    assert car.sum() > 20
    assert np.array_equal((ids == 300)[(on_front & clear).numpy()], car[on_front & clear].numpy())
    objects = json.loads((cap / "fisheye_objects.json").read_text())
    assert [(o["instance_id"], o["class"], o["label"]) for o in objects] == \
        [(7, "Pedestrian", 4), (300, "Vehicle", 10)]
    for o in objects:
        rows, cols = np.nonzero(ids == o["instance_id"])
        assert o["box"] == [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]
        assert o["pixels"] == rows.size
    # convert --min-object-pixels: the objects of fewer pixels left out, the map as it was
    small, big = sorted(o["pixels"] for o in objects)
    assert small < big
    fewer = tmp_path / "out" / "fewer"
    render_capture(load_capture(folder, label_set="new", rgb_uint8=True), cameras, fewer,
                   min_object_pixels=small + 1)
    assert json.loads((fewer / "fisheye_objects.json").read_text()) == \
        [o for o in objects if o["pixels"] == big]
    assert (fewer / "fisheye_instances.png").read_bytes() == \
        (cap / "fisheye_instances.png").read_bytes()


def test_unknown_tag_names_the_file(capture_root):
    root, _ = capture_root
    with pytest.raises(ValueError, match="labels.png"):   # tags up to 28 are not 13-class ids
        load_capture(root / "000042", label_set="13")


def test_no_capture(tmp_path):
    with pytest.raises(ValueError, match="no capture"):
        find_captures(tmp_path)
    with pytest.raises(FileNotFoundError):
        find_captures(tmp_path / "nope")


def test_cli_convert(capture_root, tmp_path, capsys):
    root, _ = capture_root
    out = tmp_path / "cli"
    assert cli.main(["convert", "--cubemaps", str(root), "--out", str(out), "--label-set", "new",
                     "--size", "32", "32", "--cameras", "fisheye"]) == 0
    assert (out / "000042" / "fisheye_rgb.png").is_file()
    assert not (out / "000042" / "catadioptric_rgb.png").exists()
    assert "000042" in capsys.readouterr().out


# ---------------------------------------------------------------------------- capture script

def test_capture_script_compiles_and_rig_matches_faces():
    """The script imports without CARLA, and its rig rotations are the cube faces'."""
    import importlib.util
    import math
    import py_compile

    from omniscape_torch.cubemap import face_rotations
    from omniscape_torch.cameras.presets import yaw_pitch_roll_to_matrix

    path = CAPTURE_SCRIPT
    py_compile.compile(str(path), doraise=True)
    spec = importlib.util.spec_from_file_location("carla_capture", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.FACES == FACES
    from omniscape_torch.data.captures import MODALITIES
    assert tuple(module.SENSORS) == MODALITIES   # it records what convert reads
    rotations = face_rotations(torch.float64)
    for k, face in enumerate(FACES):
        pitch, yaw, roll = module.RIG[face]
        yaw, pitch, roll = (torch.tensor(math.radians(a), dtype=torch.float64)
                            for a in (yaw, pitch, roll))
        r = yaw_pitch_roll_to_matrix(yaw, pitch, roll)
        torch.testing.assert_close(r, rotations[k], atol=1e-12, rtol=0)


def _load_capture_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("carla_capture", CAPTURE_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_rig_face_vectors_in_carla():
    """With the CARLA client library: each rig camera's forward, right and up vectors (CARLA's
    left-handed x forward, y right, z up), taken to our OpenCV frame by (x, y, z)_ours =
    (y, -z, x)_carla, are the face's a (looks along), r (image right) and -b (image up)."""
    carla = pytest.importorskip("carla", reason="the CARLA client library (pip install carla)")
    from omniscape_torch.cubemap import face_axes

    module = _load_capture_script()
    axes = face_axes(torch.float64)

    def ours(v):
        return torch.tensor([v.y, -v.z, v.x], dtype=torch.float64)

    for k, face in enumerate(FACES):
        pitch, yaw, roll = module.RIG[face]
        t = carla.Transform(carla.Location(), carla.Rotation(pitch=pitch, yaw=yaw, roll=roll))
        a, b, r = axes[k]
        torch.testing.assert_close(ours(t.get_forward_vector()), a, atol=1e-6, rtol=0,
                                   msg=lambda m: f"{face} forward: {m}")
        torch.testing.assert_close(ours(t.get_right_vector()), r, atol=1e-6, rtol=0,
                                   msg=lambda m: f"{face} right: {m}")
        torch.testing.assert_close(ours(t.get_up_vector()), -b, atol=1e-6, rtol=0,
                                   msg=lambda m: f"{face} up: {m}")


# ---------------------------------------------------------------------------- bad captures

def _three_captures(root):
    """Captures 000001 (good), 000002 (to be broken by the test), 000003 (good)."""
    rgb, depth, tags = _scene()
    for name in ("000001", "000002", "000003"):
        _write_capture(root / name, rgb, depth, tags)
    return root / "000002"


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


def _garbage(path):
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"not really a png" * 10)


def _out_of_range(path):
    lab = np.zeros((F, F, 3), np.uint8)
    lab[..., 0] = 200   # no tag 200 in any label set
    ot.io.write_image(path, lab)


def _smaller(path):
    ot.io.write_image(path, np.zeros((F // 2, F // 2, 3), np.uint8))


BREAKAGES = {
    "missing face": ("up_depth.png", lambda p: p.unlink()),
    "different size": ("left_rgb.png", _smaller),
    "truncated png": ("back_rgb.png", _truncate),
    "garbage png": ("right_depth.png", _garbage),
    "labels out of range": ("down_labels.png", _out_of_range),
}


@pytest.mark.parametrize("breakage", sorted(BREAKAGES))
def test_convert_skips_a_bad_capture_and_reports_it(tmp_path, breakage):
    filename, breaker = BREAKAGES[breakage]
    bad = _three_captures(tmp_path / "cubemaps")
    breaker(bad / filename)
    out = tmp_path / "out"
    with pytest.raises(ConvertError) as info:
        convert_captures(tmp_path / "cubemaps", out, label_set="new", image_size=(24, 24))
    err = info.value
    assert set(err.failures) == {"000002"} and set(err.results) == {"000001", "000003"}
    assert filename in err.failures["000002"]            # the message names the file
    assert "000002" in str(err) and filename in str(err)
    # the good captures are complete, the bad one has nothing, and no staging folder is left
    for name in ("000001", "000003"):
        assert len(list((out / name).iterdir())) == 10
        assert sorted(p.name for p in err.results[name]) == sorted(
            p.name for p in (out / name).iterdir())
    assert not (out / "000002").exists()
    assert sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME) == [
        "000001", "000003", "cameras.json", "catadioptric_calib_results.txt",
        "fisheye_calib_results.txt"]


def test_corrupt_exr_depth_face_names_the_file(tmp_path):
    """Depth faces may be float EXR (metres); a corrupt one fails that capture only."""
    bad = _three_captures(tmp_path / "cubemaps")
    _, depth, _ = _scene()
    for k, face in enumerate(FACES):
        (bad / f"{face}_depth.png").unlink()
        ot.io.write_exr(bad / f"{face}_depth.exr", depth[k].astype(np.float32))
    cube = load_capture(bad, label_set="new")             # good EXR faces load
    np.testing.assert_allclose(cube["depth"][0].numpy(), depth, rtol=1e-6)
    _truncate(bad / "front_depth.exr")
    with pytest.raises(ValueError, match="front_depth.exr"):
        load_capture(bad, label_set="new")
    with pytest.raises(ConvertError) as info:
        convert_captures(tmp_path / "cubemaps", tmp_path / "out", label_set="new",
                         image_size=(16, 16), cameras=("fisheye",))
    assert "front_depth.exr" in info.value.failures["000002"]
    assert set(info.value.results) == {"000001", "000003"}


def test_render_failure_leaves_nothing_half_written(tmp_path, monkeypatch):
    """An error while writing (here the third file) leaves no file of that capture."""
    import omniscape_torch.data.captures as convert

    _three_captures(tmp_path / "cubemaps")
    real = convert.write_exr
    calls = {"n": 0}

    def flaky(path, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:     # the second capture's fisheye depth
            raise OSError(f"{path}: disk full (simulated)")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(convert, "write_exr", flaky)
    out = tmp_path / "out"
    with pytest.raises(ConvertError) as info:
        convert_captures(tmp_path / "cubemaps", out, label_set="new", image_size=(16, 16),
                         cameras=("fisheye",))
    assert set(info.value.failures) == {"000002"}
    assert "disk full" in info.value.failures["000002"]
    assert sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME) == [
        "000001", "000003", "cameras.json", "fisheye_calib_results.txt"]


def test_cli_convert_reports_failures_and_exits_non_zero(tmp_path, capsys):
    bad = _three_captures(tmp_path / "cubemaps")
    _garbage(bad / "front_labels.png")
    out = tmp_path / "cli"
    assert cli.main(["convert", "--cubemaps", str(tmp_path / "cubemaps"), "--out", str(out),
                     "--label-set", "new", "--size", "16", "16", "--cameras", "fisheye"]) == 1
    captured = capsys.readouterr()
    assert "000001" in captured.out and "000003" in captured.out
    assert "1 of 3 captures failed" in captured.err
    assert "000002" in captured.err and "front_labels.png" in captured.err
    assert (out / "000001" / "fisheye_rgb.png").is_file() and not (out / "000002").exists()


def test_convert_with_no_good_capture_writes_nothing(tmp_path, capsys):
    """Every capture bad: no cameras.json, no output folder (it did not exist before), the
    failures listed by file, exit 1."""
    root = tmp_path / "cubemaps"
    _three_captures(root)
    for name in ("000001", "000002", "000003"):
        _garbage(root / name / "left_rgb.png")
    out = tmp_path / "out"
    assert cli.main(["convert", "--cubemaps", str(root), "--out", str(out), "--label-set",
                     "new", "--size", "16", "16", "--cameras", "fisheye"]) == 1
    err = capsys.readouterr().err
    assert "3 of 3 captures failed" in err and err.count("left_rgb.png") == 3
    assert not out.exists()
    # into an existing folder: nothing added to it either
    out.mkdir()
    with pytest.raises(ConvertError):
        convert_captures(root, out, label_set="new", image_size=(16, 16), cameras=("fisheye",))
    assert [p.name for p in out.iterdir() if p.name != LOCK_NAME] == []
