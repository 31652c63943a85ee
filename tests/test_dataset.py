"""The dataset writer (``omniscape-torch generate``) and its statistics (``stats``)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.io.atomic import LOCK_NAME
from omniscape_torch import cli
from omniscape_torch.cameras import presets
from omniscape_torch.data import ocamcalib
from omniscape_torch.data.format import MODALITIES, OCAMCALIB
from omniscape_torch.data.generate import CAMERAS, DatasetConfig, generate
from omniscape_torch.data.readers import read_camera, read_camera_dict, read_ocamcalib
from omniscape_torch.data.stats import format_stats
from omniscape_torch.io import read_exr, read_image
from omniscape_torch.scenes.town import Town

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ocamcalib_checks import OCAMCALIB_PX, check_calib_results  # noqa: E402
from test_ocamcalib_reference import harness  # noqa: E402,F401 (the compiled C fixture)

SIZE = (48, 48)
FRAMES = 2


def _config(**kw):
    base = dict(frames=FRAMES, fps=2.0, image_size=SIZE, max_face_size=48, seed=0,
                weather=("clear_noon", "sunset"))
    base.update(kw)
    return DatasetConfig(**base)


def _files(root):
    """The dataset's files; not a lock (a run removes its ``.lock`` when it ends; a killed one
    leaves it, holding the id of its process, not data)."""
    return {p.relative_to(root).as_posix(): p for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != LOCK_NAME}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "data"
    result = generate(out, _config(), workers=1, progress=False)
    assert result["rendered"] == list(range(FRAMES)) and result["skipped"] == []
    return out


def test_layout(dataset):
    files = _files(dataset)
    for name in ("dataset.json", "dynamics.json", "dynamics.csv"):
        assert name in files
    for k in range(FRAMES):
        assert f".done/{k:06d}" in files
        for cam in CAMERAS:
            for modality, ext in MODALITIES.items():
                assert f"{cam}/{modality}/{k:06d}.{ext}" in files
    for cam in CAMERAS:
        assert f"{cam}/camera.json" in files and f"{cam}/extrinsics.json" in files
        assert f"{cam}/calib_results.txt" in files
    assert not [f for f in files if f.endswith(".tmp") or ".tmp." in f]
    manifest = json.loads(files["dataset.json"].read_text())
    assert manifest["config"] == _config().to_dict()
    assert set(manifest["cameras"]) == set(CAMERAS)
    assert "layout" in manifest and "torch" in manifest["versions"]
    recs = json.loads(files["dynamics.json"].read_text())
    assert [r["frame"] for r in recs] == list(range(FRAMES))
    assert set(recs[0]) >= {"timestamp", "location", "rotation", "velocity", "speed"}
    lines = files["dynamics.csv"].read_text().splitlines()
    assert len(lines) == FRAMES + 1 and lines[0].startswith("frame,timestamp,location_x")


def test_files_readable_and_consistent(dataset):
    for cam in CAMERAS:
        camera = ot.Camera.load_json(dataset / cam / "camera.json")
        assert camera.image_size == SIZE
        for k in range(FRAMES):
            n = f"{k:06d}"
            rgb = read_image(dataset / cam / "rgb" / f"{n}.png")
            labels = read_image(dataset / cam / "labels" / f"{n}.png")
            colour = read_image(dataset / cam / "labels_color" / f"{n}.png")
            valid = read_image(dataset / cam / "valid" / f"{n}.png")
            depth = read_exr(dataset / cam / "depth" / f"{n}.exr")
            assert rgb.shape == SIZE + (3,) and colour.shape == SIZE + (3,)
            assert labels.shape == SIZE and valid.shape == SIZE and depth.shape == SIZE
            assert set(valid.unique().tolist()) <= {0, 255}
            v = valid == 255
            assert v.any() and (~v).any()       # omni images have a rim
            assert ((labels == 255) == ~v).all()
            assert (labels[v] <= 12).all()
            assert depth.dtype == torch.float32 and torch.isfinite(depth).all()
            assert (depth[v] > 0).all() and (depth[~v] == 0).all()
            assert (colour[~v] == 255).all()


def test_depth_is_the_rendered_range(dataset):
    """Re-render one camera from the written intrinsics and extrinsics: the EXR holds exactly
    the layer's range; and that range is the town's ray-cast range (nearest texel)."""
    manifest = json.loads((dataset / "dataset.json").read_text())
    town = Town(0)
    recs = json.loads((dataset / "dynamics.json").read_text())
    for cam in ("fisheye_left", "catadioptric_right"):
        camera = ot.Camera.load_json(dataset / cam / "camera.json")
        extr = json.loads((dataset / cam / "extrinsics.json").read_text())
        k = 1
        pose = torch.tensor(extr["poses"][k]["T_world_camera"], dtype=torch.float64)
        rot, centre = pose[:3, :3].float(), pose[:3, 3].float()
        F = extr["face_size"]
        # the faces written: those rendered, a superset of those the layer reads
        faces = torch.tensor([f in extr["poses"][k]["faces"] for f in ot.cubemap.FACES])
        assert not (ot.visible_faces(camera, rot, face_size=F) & ~faces).any()
        cube = town.render_cubemap(centre, None, F, faces=faces, t=recs[k]["timestamp"],
                                   weather=manifest["weather_per_frame"][k])
        layer = ot.OmniProjection(camera, F, fused_grid=False)
        res = layer.render(depth=cube["depth"], labels=cube["labels"], rotation=rot)
        depth = read_exr(dataset / cam / "depth" / f"{k:06d}.exr")
        assert torch.equal(depth, res["depth"][0, 0])
        labels = read_image(dataset / cam / "labels" / f"{k:06d}.png")
        assert torch.equal(labels.long(), res["labels"][0])
        # the instance ids: the cube's, carried like the labels (nearest texel, 0 outside)
        ids = layer.render(labels=cube["instances"].long(), rotation=rot)["labels"][0]
        instances = read_image(dataset / cam / "instances" / f"{k:06d}.png").long()
        assert torch.equal(instances, torch.where(res["valid"][0, 0], ids, 0))
        # against the exact ray cast of the pixel rays (nearest-texel depth: a few pixels on
        # object edges differ, the bulk agrees closely)
        rays, valid = camera.ray_grid()
        truth = town.render_rays(centre, rays.float() @ rot.T, t=recs[k]["timestamp"])
        v = valid & (truth["range"] < 900)
        rel = ((depth[v] - truth["range"][v]).abs() / truth["range"][v])
        assert float(rel.median()) < 0.02
        # the pixels' instance ids are those of the pixel rays' own hits, but on edges
        seen = valid & ((truth["instances"] > 0) | (instances > 0))
        assert float((truth["instances"][seen] == instances[seen]).float().mean()) > 0.7


def test_rerun_is_noop_and_resume_completes(dataset, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    before = {f: p.stat().st_mtime_ns for f, p in _files(out).items()}
    result = generate(out, _config(), workers=1, progress=False)
    assert result["rendered"] == [] and result["skipped"] == list(range(FRAMES))
    assert {f: p.stat().st_mtime_ns for f, p in _files(out).items()} == before
    # interrupt frame 1: its marker and one of its files are gone
    (out / ".done" / "000001").unlink()
    (out / "catadioptric_left" / "depth" / "000001.exr").unlink()
    result = generate(out, _config(), workers=1, progress=False)
    assert result["rendered"] == [1] and result["skipped"] == [0]
    after = _files(out)
    assert set(after) == set(before)
    for f in before:       # frame 0 untouched; frame 1 rewritten with identical bytes
        if "000000" in f:
            assert after[f].stat().st_mtime_ns == before[f]
        assert after[f].read_bytes() == (dataset / f).read_bytes(), f
    # a marker without its files is not a finished frame either
    (out / "fisheye_right" / "rgb" / "000000.png").unlink()
    assert generate(out, _config(), workers=1, progress=False)["rendered"] == [0]


def test_min_object_pixels_leaves_the_small_objects_out_of_the_lists(dataset, tmp_path):
    """``min_object_pixels=N``: each objects file is the default one less its objects of
    fewer than N pixels; the instance maps and the other files stay as they were."""
    camera = CAMERAS[2]
    out = tmp_path / "min"
    generate(out, _config(frames=1, cameras=(camera,), min_object_pixels=10), progress=False)
    every = json.loads((dataset / camera / "objects" / "000000.json").read_text())
    kept = json.loads((out / camera / "objects" / "000000.json").read_text())
    assert kept == [o for o in every if o["pixels"] >= 10]
    assert 0 < len(kept) < len(every)
    for m in ("instances", "labels", "rgb"):
        f = f"{camera}/{m}/000000.png"
        assert (out / f).read_bytes() == (dataset / f).read_bytes()
    assert json.loads((out / "dataset.json").read_text())["config"]["min_object_pixels"] == 10
    with pytest.raises(ValueError, match="min_object_pixels: expected an integer of at least 1"):
        _config(min_object_pixels=0)
    with pytest.raises(ValueError, match="min_pixels: expected a positive integer"):
        ot.data.objects.instance_objects(torch.zeros(2, 2, dtype=torch.int64),
                                         torch.zeros(2, 2, dtype=torch.int64), min_pixels=0)


def test_a_dataset_from_before_min_object_pixels_lists_every_object(dataset, tmp_path):
    out = tmp_path / "old"
    shutil.copytree(dataset, out)
    manifest = json.loads((out / "dataset.json").read_text())
    del manifest["config"]["min_object_pixels"]
    (out / "dataset.json").write_text(json.dumps(manifest))
    assert generate(out, _config(), progress=False)["rendered"] == []
    with pytest.raises(ValueError, match="--min-object-pixels: the folder has 1, this run 4"):
        generate(out, _config(min_object_pixels=4), progress=False)


def test_a_run_leaves_no_lock_in_its_folder(dataset, tmp_path):
    """The folder lock's file goes when the run ends: finished, refused, or a share's run."""
    assert not (dataset / LOCK_NAME).exists()
    with pytest.raises(ValueError, match="another configuration"):
        generate(dataset, _config(seed=1), progress=False)
    assert not (dataset / LOCK_NAME).exists()
    out = tmp_path / "shared"
    generate(out, _config(frames=1, cameras=(CAMERAS[0],)), shard=(0, 2), progress=False)
    assert not list(out.glob(".shard-*")) and not (out / LOCK_NAME).exists()


def test_the_progress_bar_moves_per_frame(tmp_path, monkeypatch):
    """One step of the bar per frame finished (not per chunk of frames), in this process; the
    worker processes report each frame the same way (tests/test_processes.py)."""
    import tqdm

    steps = []

    class Bar(tqdm.tqdm):
        def __init__(self, *args, **kwargs):
            self.counted = kwargs.get("desc") == "generate"   # not the camera fits' bars
            super().__init__(*args, **kwargs)

        def update(self, n=1):
            if self.counted:
                steps.append(n)
            return super().update(n)

    monkeypatch.setattr(tqdm, "tqdm", Bar)
    config = _config(frames=3, image_size=(16, 16), max_face_size=16, cameras=(CAMERAS[0],))
    assert generate(tmp_path / "bar", config, progress=False)["rendered"] == [0, 1, 2]
    assert steps == [1, 1, 1]


def test_instances_and_objects(dataset):
    """Each camera's instance ids (16-bit PNG, read back with Pillow) are the town's objects:
    an id on exactly the pixels of an instance class, of its object's class, 0 outside the
    valid area; the same object keeps its id from frame to frame. Each objects file lists
    every id of the image once, with its class and the tight box of its pixels (XYXY corners,
    computed here with numpy) and their count."""
    from PIL import Image

    town = Town(0)
    things = [ot.io.CLASSES.index(c) for c in ("Pedestrian", "Pole", "Vehicle", "TrafficSign")]
    seen = {}
    for cam in CAMERAS:
        for k in range(FRAMES):
            n = f"{k:06d}"
            with Image.open(dataset / cam / "instances" / f"{n}.png") as im:
                assert im.mode.startswith("I;16") or im.mode == "I"
                ids = np.asarray(im).astype(np.int64)
            labels = read_image(dataset / cam / "labels" / f"{n}.png").numpy()
            valid = read_image(dataset / cam / "valid" / f"{n}.png").numpy() > 0
            assert ids.shape == SIZE and (ids[~valid] == 0).all()
            assert np.array_equal(ids > 0, np.isin(labels, things))
            assert np.array_equal(town.instance_label.numpy()[ids[ids > 0]], labels[ids > 0])
            objects = json.loads((dataset / cam / "objects" / f"{n}.json").read_text())
            assert [o["instance_id"] for o in objects] == sorted(set(ids[ids > 0].tolist()))
            for o in objects:
                rows, cols = np.nonzero(ids == o["instance_id"])
                assert o["box"] == [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]
                assert o["pixels"] == rows.size
                assert o["label"] == labels[rows[0], cols[0]]
                assert o["class"] == ot.io.CLASSES[o["label"]]
                seen.setdefault(o["instance_id"], set()).add(o["label"])
    assert len(seen) >= 3 and all(len(c) == 1 for c in seen.values())


def test_town_instances_are_objects():
    """Every vehicle, pedestrian, pole and traffic sign of the town is one instance; the
    cube's instance ids are those of ``render_rays`` of its texel rays."""
    town = Town(0)
    counts = torch.bincount(town.instance_label[1:], minlength=13)
    C = {c: ot.io.CLASSES.index(c) for c in ot.io.CLASSES}
    # 2 boxes a vehicle, a cylinder and a sphere a pedestrian, one primitive for the others
    assert counts[C["Vehicle"]] == int((town.boxes_label == C["Vehicle"]).sum()) // 2
    assert counts[C["Pedestrian"]] == int((town.sph_label == C["Pedestrian"]).sum())
    assert counts[C["Pole"]] == int((town.cyl_label == C["Pole"]).sum())
    assert counts[C["TrafficSign"]] == int((town.boxes_label == C["TrafficSign"]).sum())
    assert int(counts.sum()) == len(town.instance_label) - 1
    cube = town.render_cubemap((1.75, -1.2, 0.0), face_size=24)
    rays = town.render_rays(torch.tensor([1.75, -1.2, 0.0]), town.cubemap_rays(24))
    assert torch.equal(rays["instances"], cube["instances"][0].long())
    assert int(cube["instances"].max()) > 0


@pytest.mark.numerics
def test_calib_results_agree_with_the_cameras_in_ocamcalib_c_code(dataset, harness):
    """Every camera folder holds OCamCalib's calib_results.txt: OCamCalib's C code reads it,
    and its cam2world and world2cam agree with the camera's own rays (camera.json) within
    0.05 px at every pixel the camera sees; camera.json records the fit and the valid area."""
    for cam in CAMERAS:
        camera = read_camera(dataset, cam)
        record = read_camera_dict(dataset, cam)["ocamcalib"]
        assert record["file"] == OCAMCALIB and record["model"] == "scaramuzza"
        assert record["degree"] in ocamcalib.DEGREES and record["within_tolerance"]
        assert 0 < record["rms_px"] <= record["max_px"] <= ocamcalib.TOLERANCE_PX
        assert record["invpol_max_px"] <= ocamcalib.INVPOL_PX
        errors = check_calib_results(harness, dataset / cam / OCAMCALIB, camera, record)
        print(f"{cam}: degree {record['degree']}, {errors}")
        assert errors["cam2world_px"] <= OCAMCALIB_PX and errors["world2cam_px"] <= OCAMCALIB_PX
        poly = read_ocamcalib(dataset, cam)
        assert poly.model.name == "scaramuzza" and poly.image_size == camera.image_size
        assert (poly.fov, poly.blind_fov) == (camera.fov, camera.blind_fov)


@pytest.mark.slow
@pytest.mark.numerics
def test_calib_results_at_the_default_image_size(tmp_path, harness):
    """The rig's two kinds of camera (module docstring of generate.py: presets.fisheye and
    presets.catadioptric looking down) at generate's default image size, without rendering:
    the polynomial of the smallest degree within the tolerance, OCamCalib's functions within
    0.05 px."""
    size = DatasetConfig().image_size
    for kind, camera in (("fisheye", presets.fisheye(size)),
                         ("catadioptric", presets.catadioptric(size, looking="down")[0])):
        fit = ocamcalib.fit_polynomial(camera)
        record = ocamcalib.write_calib_results(fit, tmp_path / f"{kind}.txt")
        assert record["within_tolerance"] and record["max_px"] <= ocamcalib.TOLERANCE_PX
        if record["degree"] > ocamcalib.DEGREES[0]:    # the smallest degree that reaches it
            lower = ocamcalib.fit_polynomial(camera, degrees=(record["degree"] - 1,))
            assert lower.max_px > ocamcalib.TOLERANCE_PX
        errors = check_calib_results(harness, tmp_path / f"{kind}.txt", camera, record)
        print(f"{kind} {size}: degree {record['degree']}, held-out max {record['max_px']:.4f} "
              f"px, {errors}")
        assert errors["cam2world_px"] <= OCAMCALIB_PX and errors["world2cam_px"] <= OCAMCALIB_PX


def test_calib_results_are_fitted_once_per_camera_and_kept_on_rerun(dataset, tmp_path,
                                                                      monkeypatch):
    """A rerun fits nothing; a missing file or record is fitted again (once for a stereo pair,
    whose intrinsics are the same), to the same bytes."""
    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    fitted = []
    real = ocamcalib.fit_polynomial

    def counting(camera, **kwargs):
        fitted.append(camera.model.name)
        return real(camera, **kwargs)

    monkeypatch.setattr(ocamcalib, "fit_polynomial", counting)
    assert generate(out, _config(), progress=False)["rendered"] == []
    assert fitted == []
    for cam in ("fisheye_left", "fisheye_right"):
        (out / cam / OCAMCALIB).unlink()
    # a dataset written before the files: camera.json without the record
    path = out / "catadioptric_right" / "camera.json"
    data = json.loads(path.read_text())
    del data["ocamcalib"]
    path.write_text(json.dumps(data))
    generate(out, _config(), progress=False)
    assert fitted == ["equidistant", "unified"]
    for cam in CAMERAS:
        for name in (OCAMCALIB, "camera.json"):
            assert (out / cam / name).read_bytes() == (dataset / cam / name).read_bytes()


def test_other_config_refused(dataset, tmp_path):
    """Refused before any work, naming each differing setting by its option with both values
    (not only "another configuration")."""
    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    with pytest.raises(ValueError, match="another configuration") as err:
        generate(out, _config(frames=3, image_size=(48, 32), save_panorama=True),
                 progress=False)
    message = str(err.value)
    assert f"--frames: the folder has {FRAMES}, this run 3" in message
    assert "--image-size: the folder has 48, this run 48x32" in message
    assert "--save-panorama: the folder has off, this run on" in message
    assert "--seed" not in message and "--weather" not in message    # the same


def test_config_changes_names_the_settings_as_the_command_line_writes_them():
    from omniscape_torch.data.generate import config_changes

    old = _config().to_dict()
    assert config_changes(old, old) == ""
    assert config_changes(None, old) == ""           # an unreadable manifest: no details
    new = _config(cameras=("fisheye_left", "fisheye_right"), face_size=32).to_dict()
    assert config_changes(old, new) == (
        f": --face-size: the folder has the default, this run 32; --cameras: the folder has "
        f"{','.join(CAMERAS)}, this run fisheye_left,fisheye_right")
    del old["town"]
    assert "--town: the folder has none, this run 1" in config_changes(old, new)


def test_cli_rerun_with_other_settings_is_one_line_naming_them(dataset, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    argv = ["generate", "--out", str(out), "--frames", str(FRAMES), "--image-size", "32",
            "--max-face-size", "48", "--weather", "clear_noon,sunset", "--no-progress"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--image-size: the folder has 48, this run 32" in err[0], err


def test_dataset_from_before_antialias_is_antialias_1(tmp_path):
    """A manifest written before ``antialias`` existed (no such key) is a dataset of
    ``antialias=1``: its rerun resumes, a rerun asking for 2 is refused. The default is 2 for
    images of at most 512 x 512 pixels, else 1, and the manifest records the number."""
    assert _config().antialias == 2 and _config(image_size=(1024, 1024)).antialias == 1
    out = tmp_path / "old"
    config = _config(frames=1, cameras=("fisheye_left",), antialias=1)
    generate(out, config, progress=False)
    manifest = out / "dataset.json"
    data = json.loads(manifest.read_text())
    assert data["config"]["antialias"] == 1
    del data["config"]["antialias"]
    manifest.write_text(json.dumps(data))
    assert generate(out, config, progress=False)["skipped"] == [0]
    data["config"].pop("antialias", None)
    manifest.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="another configuration"):
        generate(out, _config(frames=1, cameras=("fisheye_left",)), progress=False)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="antialias"):
            _config(antialias=bad)


def test_antialias_option(tmp_path):
    """``--antialias N`` reaches the manifest's configuration; 0 is refused by the parser."""
    out = tmp_path / "aa"
    assert cli.main(["generate", "--out", str(out), "--frames", "1", "--image-size", "16",
                     "--max-face-size", "16", "--cameras", "fisheye_left", "--antialias", "3",
                     "--no-progress"]) == 0
    assert json.loads((out / "dataset.json").read_text())["config"]["antialias"] == 3
    with pytest.raises(SystemExit):
        cli.main(["generate", "--out", str(tmp_path / "bad"), "--antialias", "0"])


@pytest.mark.slow
def test_workers_give_identical_files(dataset, tmp_path):
    out = tmp_path / "par"
    result = generate(out, _config(), workers=2, progress=False)
    assert result["rendered"] == list(range(FRAMES))
    a, b = _files(dataset), _files(out)
    assert set(a) == set(b)
    for f in a:
        assert a[f].read_bytes() == b[f].read_bytes(), f


@pytest.mark.parametrize("antialias", [1, 2])
@pytest.mark.parametrize("image_size", [(40, 72)])
def test_the_texels_a_camera_reads_give_the_same_images(image_size, antialias):
    """Tracing only the texels a camera's layer reads (``FrameRenderer.texels``) leaves its
    images bit for bit as with whole faces, and traces fewer texels; anti-aliased too (the set
    grown by the texel whose colour step to a neighbour decides its supersampling)."""
    from omniscape_torch.data.generate import FrameRenderer
    renderer = FrameRenderer(_config(image_size=image_size, max_face_size=64, frames=3,
                                     antialias=antialias))
    plan, town = renderer.plan, renderer.town
    compared = 0
    for name in CAMERAS:
        c = plan.cameras[name]
        F = c["face_size"]
        layer = renderer._layer(name, c["camera"], F)
        for k in range(3):
            faces, texels = plan.faces(name, k), renderer.texels(name, k)
            assert not (texels & ~faces.view(6, 1, 1)).any()
            images = []
            for mask in (None, texels):
                cube = town.render_cubemap(plan.centre(name, k).float(), None, F, faces=faces,
                                           texels=mask, t=float(k), antialias=antialias)
                with torch.no_grad():
                    images.append(layer.render(rgb=cube["rgb"], depth=cube["depth"],
                                               labels=cube["labels"],
                                               rotation=plan.rotation(name, k).float()))
            for key in ("rgb", "depth", "labels", "valid"):
                assert torch.equal(images[0][key], images[1][key]), (name, k, key)
            compared += 1
    assert compared == 12
    if antialias > 1:
        return
    # at full size the read texels leave out a fifth to a third of their faces' texels (at these
    # small sizes the taps of the pixels cover most of the faces)
    big = FrameRenderer(_config(image_size=(512, 512), face_size=512, frames=1))
    for name in ("fisheye_left", "catadioptric_left"):
        faces, texels = big.plan.faces(name, 0), big.texels(name, 0)
        assert texels.sum() < 0.85 * faces.sum() * 512 * 512, name


def test_town_option(tmp_path, capsys):
    """``--town 2`` writes the crossroads: its manifest says so, and its ride turns right
    (yaw from north towards east) where town 1's goes on north."""
    out = tmp_path / "town2"
    assert cli.main(["generate", "--out", str(out), "--frames", "16", "--fps", "1",
                     "--image-size", "16", "--max-face-size", "16", "--cameras",
                     "fisheye_left", "--town", "2", "--no-progress"]) == 0
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["config"]["town"] == 2
    yaw = [r["rotation"]["yaw"] for r in json.loads((out / "dynamics.json").read_text())]
    assert abs(yaw[0]) < 5 and 80 < yaw[-1] < 100
    assert DatasetConfig().town == 1


def test_cubemaps_panorama_and_subset(tmp_path):
    out = tmp_path / "extra"
    config = _config(frames=1, cameras=("fisheye_right",), weather=("night",),
                     save_cubemaps=True, save_panorama=True, face_size=16)
    generate(out, config, progress=False)
    files = _files(out)
    assert not any(f.startswith("fisheye_left") or f.startswith("catadioptric") for f in files)
    faces = json.loads((out / "fisheye_right" / "extrinsics.json").read_text())
    faces = faces["poses"][0]["faces"]
    assert faces and "back" not in faces
    for face in faces:
        assert read_image(out / f"fisheye_right/cubemap/rgb/000000_{face}.png").shape == \
            (16, 16, 3)
        assert read_exr(out / f"fisheye_right/cubemap/depth/000000_{face}.exr").shape == (16, 16)
    assert read_image(out / "panorama/rgb/000000.png").shape == (48, 96, 3)
    pano_depth = read_exr(out / "panorama/depth/000000.exr")
    assert pano_depth.shape == (48, 96) and (pano_depth > 0).all()


def test_stats(dataset, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(dataset, out)
    assert cli.main(["stats", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Table I" in text and "Road" in text and "catadioptric" in text
    for angle in ("yaw", "pitch", "roll"):
        assert angle in text
    png = (out / "stats.png").read_bytes()
    assert png.startswith(b"\x89PNG")
    result = json.loads((out / "stats.json").read_text())
    recs = json.loads((out / "dynamics.json").read_text())
    rolls = np.array([r["rotation"]["roll"] for r in recs])
    assert result["table_one"]["roll"]["mean"] == pytest.approx(rolls.mean())
    assert result["table_one"]["roll"]["max"] == pytest.approx(rolls.max())
    for kind in ("fisheye", "catadioptric"):
        assert sum(result["class_share"][kind].values()) == pytest.approx(1.0)
        assert result["class_share"][kind]["Road"] > 0
    assert format_stats(result).splitlines()[0].startswith("Table I")
    assert "Unlabeled (class 0) is the sky" in text   # said where the shares are
    # the shares count valid pixels only
    n_valid = sum(int((read_image(p) == 255).sum()) for cam in ("fisheye_left", "fisheye_right")
                  for p in (out / cam / "valid").glob("*.png"))
    assert result["pixels"]["fisheye"] == n_valid
    # the objects of the objects files, per kind of camera; a dataset without them has none
    listed = [o["class"] for cam in ("catadioptric_left", "catadioptric_right")
              for p in (out / cam / "objects").glob("*.json") for o in json.loads(p.read_text())]
    cata = result["objects"]["catadioptric"]
    assert cata["images"] == 2 * FRAMES and cata["per_image"] == len(listed) / (2 * FRAMES)
    assert cata["classes"] == {c: listed.count(c) for c in set(listed)}
    assert "objects (instances) per image" in text
    for cam in CAMERAS:
        shutil.rmtree(out / cam / "objects")
    assert "objects" not in ot.data.stats.stats(out, plot=False)


@pytest.mark.parametrize("argv, message", [
    (["--cameras", "fisheye_center"], "unknown camera 'fisheye_center'"),
    (["--image-size", "0"], "expected N or HxW"),
    (["--image-size", "abc"], "expected N or HxW"),
    (["--weather", "rainy"], "unknown weather 'rainy'"),
    (["--frames", "0"], "positive integer"),
    (["--town", "4"], "invalid choice"),
])
def test_cli_errors(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as err:
        cli.main(["generate", "--out", str(tmp_path / "x"), *argv])
    assert err.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_cli_generate_and_stats_missing(tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["generate", "--out", str(out), "--frames", "1", "--image-size", "32x40",
            "--face-size", "16", "--cameras", "fisheye_left", "catadioptric_left",
            "--no-progress"]
    assert cli.main(argv) == 0
    printed = capsys.readouterr()
    last = printed.out.strip().splitlines()[-1]   # what to open first
    assert last.startswith("wrote 1 frame(s)") and f"open {out / 'contact_sheet.png'} first" in last
    # the camera fits said in plain words, once per camera, after what they are
    lines = printed.err.splitlines()
    fits = [i for i, line in enumerate(lines) if " a polynomial of degree " in line]
    assert len(fits) == 2 and lines[fits[0] - 1].startswith("calib_results.txt: each camera")
    assert read_image(out / "catadioptric_left/rgb/000000.png").shape == (32, 40, 3)
    assert not (out / "fisheye_right").exists()
    assert cli.main(["stats", str(tmp_path / "nothing")]) == 2
    assert "no dataset.json" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Reliability: incomplete datasets, one writer per folder, temporaries, frame independence,
# sizes and memory checked before any work
# --------------------------------------------------------------------------------------------

def test_stats_of_an_interrupted_run_counts_finished_frames_only(dataset, tmp_path, capsys):
    out = tmp_path / "partial"
    shutil.copytree(dataset, out)
    (out / ".done" / "000001").unlink()        # frame 1 not finished (its marker comes last)
    for name in CAMERAS:
        (out / name / "labels" / "000001.png").unlink(missing_ok=True)
    assert cli.main(["stats", str(out), "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert f"the 1 finished of {FRAMES} frames" in text
    # the frame left out is named, with the file it lacks: here its marker (not finished)
    assert (f"skipped frame 000001: not finished (no .done/000001; missing "
            f"{CAMERAS[0]}/labels/000001.png and {len(CAMERAS) - 1} more file(s))") in text
    result = json.loads((out / "stats.json").read_text())
    assert result["frames"] == 1 and result["frames_planned"] == FRAMES
    recs = json.loads((out / "dynamics.json").read_text())
    assert result["table_one"]["roll"]["mean"] == pytest.approx(recs[0]["rotation"]["roll"])
    n_valid = sum(int((read_image(out / cam / "valid" / "000000.png") == 255).sum())
                  for cam in ("fisheye_left", "fisheye_right"))
    assert result["pixels"]["fisheye"] == n_valid
    assert json.loads((out / "stats.json").read_text())["skipped"]["000001"][0] == \
        ".done/000001"
    (out / ".done" / "000000").unlink()
    assert cli.main(["stats", str(out)]) == 2
    assert "none of its 2 frames is finished" in capsys.readouterr().err


def test_stats_names_a_file_lost_from_a_finished_frame(dataset, tmp_path, capsys):
    out = tmp_path / "lost"
    shutil.copytree(dataset, out)
    (out / CAMERAS[1] / "valid" / "000000.png").unlink()    # the marker stays
    assert cli.main(["stats", str(out), "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert (f"skipped frame 000000: missing {CAMERAS[1]}/valid/000000.png (its marker is "
            "there: the file was lost; run generate again to render the frame anew)") in text
    assert f"the 1 finished of {FRAMES} frames" in text


def test_a_second_run_into_the_same_folder_stops_with_a_message(tmp_path, capsys):
    from omniscape_torch.io.atomic import FolderBusyError, folder_lock

    out = tmp_path / "busy"
    with folder_lock(out):
        with pytest.raises(FolderBusyError, match=f"process {__import__('os').getpid()}"):
            generate(out, _config(frames=1), progress=False)
        assert cli.main(["generate", "--out", str(out), "--frames", "1", "--image-size", "16",
                         "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "another run" in err
        assert not (out / "dataset.json").exists()
    generate(out, _config(frames=1), progress=False)     # the lock is free again


def test_a_run_removes_the_temporaries_of_ended_processes_only(tmp_path):
    """Temporaries carry their writer's process id: those of a process that has ended are
    removed when a run starts, those of a live process (another run writing) are left."""
    import subprocess
    import sys

    from omniscape_torch.io.atomic import remove_stale_temporaries

    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True)
    dead = int(ended.stdout)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        folder = tmp_path / "ds" / "fisheye_left" / "rgb"
        folder.mkdir(parents=True)
        stale = folder / f".000000.png.{dead}.abcd1234.tmp"
        stale_dir = tmp_path / "ds" / f".000003.{dead}.k_9x2abc.partial"
        other = folder / f".000001.png.{live.pid}.abcd1234.tmp"
        plain = folder / ".notes.txt"
        for path in (stale, other, plain):
            path.write_bytes(b"x")
        stale_dir.mkdir()
        (stale_dir / "fisheye_rgb.png").write_bytes(b"x")
        removed = remove_stale_temporaries(tmp_path / "ds")
        assert set(removed) == {stale, stale_dir}
        assert other.exists() and plain.exists() and not stale.exists()
        generate(tmp_path / "ds", _config(frames=1), progress=False)
        assert other.exists()
    finally:
        live.kill()
        live.wait()


@pytest.fixture(scope="module")
def longer(tmp_path_factory):
    """The dataset of the module's settings with one more frame, written from scratch."""
    out = tmp_path_factory.mktemp("longer") / "data"
    generate(out, _config(frames=FRAMES + 1), progress=False)
    return out


def test_frame_k_depends_on_the_seed_and_k_only(dataset, longer):
    """A longer run extends a shorter one: frames 0 and 1 of a 3-frame run are those of the
    2-frame run byte for byte (ride noise, face sizes and weather do not depend on the frame
    count), and so are the cameras."""
    short, long_ = _files(dataset), _files(longer)
    per_frame = [f for f in short if f.startswith(".done/") or f.split("/")[-1][:6].isdigit()]
    assert len(per_frame) > 10
    differ = [f for f in per_frame if short[f].read_bytes() != long_[f].read_bytes()]
    assert not differ, differ
    for name in CAMERAS:
        assert (dataset / name / "camera.json").read_bytes() == \
            (longer / name / "camera.json").read_bytes()


def test_a_larger_frames_extends_a_finished_dataset(dataset, longer, tmp_path):
    """``--frames 3`` into a finished 2-frame folder of the same settings renders frame 2
    only, keeps frames 0 and 1 untouched, and leaves the folder a 3-frame run writes, byte for
    byte; fewer frames than the folder's are refused, naming the setting."""
    out = tmp_path / "grown"
    shutil.copytree(dataset, out)
    before = {f: p.stat().st_mtime_ns for f, p in _files(out).items() if "00000" in f}
    logged = []
    result = generate(out, _config(frames=FRAMES + 1), progress=False, log=logged.append)
    assert result["rendered"] == [FRAMES] and result["skipped"] == list(range(FRAMES))
    assert any(f"from {FRAMES} to {FRAMES + 1} frames" in line for line in logged)
    grown, fresh = _files(out), _files(longer)
    assert set(grown) == set(fresh)
    differ = [f for f in fresh if grown[f].read_bytes() != fresh[f].read_bytes()]
    assert not differ, differ
    assert {f: grown[f].stat().st_mtime_ns for f in before} == before
    with pytest.raises(ValueError, match="--frames: the folder has 3, this run 2.*a larger "
                                         "--frames extends it"):
        generate(out, _config(), progress=False)


def test_extending_repacks_the_short_last_shard(dataset, tmp_path):
    from omniscape_torch.data.shards import pack

    out = tmp_path / "grown"
    shutil.copytree(dataset, out)
    assert pack(out, frames_per_shard=4)["written"] == ["shard-000000.tar"]
    generate(out, _config(frames=FRAMES + 1), format="webdataset", progress=False)
    index = json.loads((out / "shards" / "index.json").read_text())
    assert index["frames"] == FRAMES + 1 and index["shards"][0]["frames"] == [0, FRAMES]
    import tarfile
    with tarfile.open(out / "shards" / "shard-000000.tar") as tar:
        frames = {int(n.split("_")[0]) for n in tar.getnames()}
    assert frames == set(range(FRAMES + 1))


def _cut(path, keep=0.5):
    """Cut the file at ``path`` short (a copy stopped halfway)."""
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep)])


def test_the_integrity_check_finds_every_cut_and_no_whole_file(dataset, tmp_path):
    from omniscape_torch.data.integrity import file_damage

    files = [p for p in _files(dataset).values() if p.suffix in (".png", ".exr", ".json")]
    assert {p.suffix for p in files} == {".png", ".exr", ".json"}
    assert [p for p in files if file_damage(p) is not None] == []
    for p in files:
        if not p.name.startswith("000000"):
            continue
        data = p.read_bytes()
        for cut in (1, 8, 40, len(data) // 2, len(data) - 13, len(data) - 2):
            copy = tmp_path / p.name
            copy.write_bytes(data[:cut])
            assert file_damage(copy) is not None, (p, cut)
    assert file_damage(tmp_path / "none.png") == "missing"


def test_a_damaged_file_is_named_by_stats_and_rendered_again_by_generate(dataset, tmp_path,
                                                                        capsys):
    out = tmp_path / "damaged"
    shutil.copytree(dataset, out)
    rgb = f"{CAMERAS[2]}/rgb/000001.png"
    _cut(out / rgb)
    _cut(out / f"{CAMERAS[0]}/depth/000001.exr")
    assert cli.main(["stats", str(out), "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert f"skipped frame 000001: {CAMERAS[0]}/depth/000001.exr is damaged: cut short" in text
    assert "(and 1 more file(s)); run generate again to render the frame anew" in text
    assert f"the 1 finished of {FRAMES} frames" in text
    recorded = json.loads((out / "stats.json").read_text())["damaged"]["000001"]
    assert set(recorded) == {rgb, f"{CAMERAS[0]}/depth/000001.exr"}
    logged = []
    result = generate(out, _config(), progress=False, log=logged.append)
    assert result["rendered"] == [1] and result["skipped"] == [0]
    assert any(line.startswith("frame 000001: ") and "is damaged" in line for line in logged)
    assert (out / rgb).read_bytes() == (dataset / rgb).read_bytes()


def test_a_file_that_does_not_decode_is_named_by_stats(dataset, tmp_path, capsys):
    """Damage past the structure the check reads (a flipped byte in the compressed pixels):
    the decoding finds it, and stats names the file."""
    out = tmp_path / "flipped"
    shutil.copytree(dataset, out)
    labels = out / CAMERAS[1] / "labels" / "000000.png"
    data = bytearray(labels.read_bytes())
    at = data.index(b"IDAT") + 20
    data[at:at + 8] = bytes(8)
    labels.write_bytes(bytes(data))
    assert cli.main(["stats", str(out), "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert (f"skipped frame 000000: {CAMERAS[1]}/labels/000000.png is damaged: cannot be "
            "decoded") in text


@pytest.mark.parametrize("kwargs, match", [
    (dict(face_size=1), "face_size: expected an integer of at least 8"),
    (dict(face_size=7), "face_size: expected an integer of at least 8"),
    (dict(max_face_size=4), "max_face_size: expected an integer of at least 8"),
    (dict(image_size=(4, 64)), "image_size: expected .* at least 8"),
])
def test_sizes_below_a_useful_minimum_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        _config(**kwargs)


def test_a_run_that_cannot_fit_in_memory_is_refused_before_any_work(tmp_path, capsys,
                                                                    monkeypatch):
    import omniscape_torch.data.generate as writer
    from omniscape_torch.data.generate import check_memory, estimate_memory

    def never(*args, **kwargs):
        raise AssertionError("a refused run renders nothing")

    monkeypatch.setattr(writer.FrameRenderer, "render", never)
    out = tmp_path / "huge"
    assert cli.main(["generate", "--out", str(out), "--image-size", "100000",
                     "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "GB of memory" in err
    assert "the largest image size that fits is" in err
    assert not out.exists()
    # the size suggested fits in the memory the check was given, and the next one up does not
    # (a fixed budget: the machine's free memory moves while the test runs)
    budget = 8e9
    with pytest.raises(MemoryError) as refused:
        check_memory(_config(image_size=(20000, 20000), max_face_size=1024), available=budget)
    size = int(str(refused.value).split("the largest image size that fits is ")[1].split("x")[0])
    check_memory(_config(image_size=(size, size), max_face_size=1024), available=budget)
    with pytest.raises(MemoryError):
        check_memory(_config(image_size=(size + 1, size + 1), max_face_size=1024),
                     available=budget)
    with pytest.raises(MemoryError, match="fewer workers"):
        check_memory(_config(image_size=(size, size), max_face_size=1024), workers=64,
                     available=budget)
    # more workers need more memory; so do larger images
    config = _config(image_size=(size, size), max_face_size=1024)
    assert estimate_memory(config, 2) > estimate_memory(config, 1)
    assert estimate_memory(_config(image_size=(512, 512))) > estimate_memory(_config())


@pytest.mark.slow
def test_the_memory_estimate_bounds_a_measured_run(tmp_path):
    """The estimate is an upper bound of the peak resident memory of a process that renders a
    frame (measured in a fresh process), and not a loose one (within 2.5x; the frame peaks at
    0.6-0.8 GB). The peak is the child's VmHWM (its own address space): Linux carries the
    high-water mark of the process that forked it into the child's ``ru_maxrss`` across exec,
    so that measured the test process itself (1.23-1.64 GB late in a CI run)."""
    import subprocess
    import sys

    from omniscape_torch.data.generate import estimate_memory

    config = DatasetConfig(frames=1, image_size=(160, 160), face_size=320,
                           cameras=("fisheye_left",))
    code = (
        "import resource, sys\n"
        "from omniscape_torch.data.generate import DatasetConfig, render_frame\n"
        "c = DatasetConfig(frames=1, image_size=(160, 160), face_size=320, "
        "cameras=('fisheye_left',))\n"
        f"render_frame(c, {str(tmp_path / 'out')!r}, 0)\n"
        "try:\n"
        "    with open('/proc/self/status') as f:\n"
        "        kb = next(int(l.split()[1]) for l in f if l.startswith('VmHWM:'))\n"
        "except OSError:  # no procfs: ru_maxrss (it may include the parent's peak)\n"
        "    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "print(kb * 1024)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, check=True)
    peak = int(done.stdout.split()[-1])
    estimate = estimate_memory(config)
    assert peak <= estimate <= 2.5 * peak, (peak, estimate)
