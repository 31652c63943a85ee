"""The speed-vs-accuracy benchmark (benchmarks/harness.py, run by benchmarks/run.py): its
references, its Pareto front, its outputs, and its rows for missing peers."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import omniscape_torch as ot

# the harness is a module of benchmarks/, next to its helpers (common.py), as the scripts there
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import harness as bm  # noqa: E402

#: A tiny run: 24 x 24 pixels, the headline face 12, batch 2, two timed calls per row.
TINY = ["--size", "24", "--batch", "2", "--repeats", "2", "--warmup", "0", "--no-fused",
        "--town-pixels", "300", "--reference-samples", "3", "--no-progress"]


def _pinhole_face(face_size: int, dtype=torch.float64) -> ot.Camera:
    """The front face's own camera (DESIGN.md: f = F / 2, c = (F - 1) / 2)."""
    f, c = face_size / 2, (face_size - 1) / 2
    return ot.Camera("pinhole", torch.tensor([f, f, c, c], dtype=dtype), (face_size, face_size))


def _front_rays(u: torch.Tensor, v: torch.Tensor, face_size: int) -> torch.Tensor:
    """Unit rays of front-face pixels, written out from DESIGN.md (r = +x, b = +y, a = +z)."""
    f, c = face_size / 2, (face_size - 1) / 2
    rays = torch.stack(((u - c) / f, (v - c) / f, torch.ones_like(u)), -1)
    return rays / rays.norm(dim=-1, keepdim=True)


# --------------------------------------------------------------------------------------------
# References
# --------------------------------------------------------------------------------------------

def test_texture_reference_is_exact_for_the_face_camera():
    """A pinhole identical to the front face sees the cube's texel centres: its centre-ray
    reference equals the cube's front face, and OmniProjection's nearest rendering of the cube
    reproduces it (PSNR > 60 dB; float32 rounding only)."""
    size, ppr = 32, 16.0  # the finest wave: 1.5 pixels of this camera's axis
    camera = _pinhole_face(size)
    reference, valid = bm.texture_reference(camera, ppr, samples=1)
    cube = bm.texture_cubemap(size, ppr)
    assert bool(valid.all())
    torch.testing.assert_close(reference.float(), cube[0, 0], atol=1e-6, rtol=0)
    layer = ot.OmniProjection(_pinhole_face(size, torch.float32), size, interpolation="nearest")
    image, _ = layer(cube)
    assert bm._psnr(image[0], reference, valid) > 60


def test_texture_reference_averages_the_pixel_footprint():
    """samples = s: the mean of the texture over s x s sub-pixel rays, the rays written out
    independently of the camera model."""
    size, ppr, s = 8, 6.0, 3
    reference, _ = bm.texture_reference(_pinhole_face(size), ppr, samples=s)
    offsets = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5  # (0.5 + k) / s - 0.5
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64),
                          torch.arange(size, dtype=torch.float64), indexing="ij")
    total = sum(bm.sphere_texture(_front_rays(u + du, v + dv, size), ppr)
                for du in offsets for dv in offsets)
    torch.testing.assert_close(reference, (total / s**2).permute(2, 0, 1), atol=1e-12, rtol=0)
    # the footprint average differs from the centre rays (the finest wave is 1.5 pixels)
    centre, _ = bm.texture_reference(_pinhole_face(size), ppr, samples=1)
    assert float((centre - reference).abs().max()) > 0.01


def test_label_accuracy_known_case():
    labels = torch.tensor([[1, 2, 3], [4, 5, 6]])
    reference = torch.tensor([[1, 2, 0], [4, 0, 6]])
    assert bm.label_accuracy(labels, reference) == pytest.approx(4 / 6)
    with pytest.raises(ValueError, match="labels"):
        bm.label_accuracy(labels, reference[:1])


def test_pareto_front_hand_made():
    #          0     1     2     3     4         5     6     7
    cost = [1.0, 2.0, 3.0, 2.5, 0.5, math.nan, 4.0, 2.0]
    score = [10.0, 30.0, 20.0, 40.0, 5.0, 99.0, math.inf, 30.0]
    # 4 (fastest), 0, 1 (7 is its duplicate), 3; 2 is beaten by 3; NaN / inf never on it
    assert bm.pareto_front(cost, score) == [4, 0, 1, 3]
    assert bm.pareto_front([], []) == []
    with pytest.raises(ValueError, match="same length"):
        bm.pareto_front([1.0], [])


# --------------------------------------------------------------------------------------------
# The runner
# --------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_runner_outputs(tmp_path):
    required = ot.required_face_size(ot.presets.fisheye((24, 24)))
    fine = f"bilinear F{2 * required}"  # a cube much finer than the image
    only = ["bilinear F12", fine, "cv2.remap float maps float32", "py360convert"]
    assert bm.main([*TINY, "--out-dir", str(tmp_path), "--only", *only]) == 0
    result = json.loads((tmp_path / "bench.json").read_text())
    for key in ("machine", "threads", "commit", "dirty", "versions", "devices", "setup",
                "rows", "pareto", "loadavg_start", "loadavg_end"):
        assert key in result
    assert result["threads"] == 2 and result["devices"] == ["cpu"]
    assert {"torch", "numpy", "cv2", "py360convert"} <= set(result["versions"])
    assert result["setup"]["required_face_size"] == required
    rows = {r["name"]: r for r in result["rows"]}
    assert "cv2.remap float maps float32" in rows and "py360convert c2e + cv2.remap" in rows
    for r in rows.values():
        assert len(r["timing"]["times_s"]) == 2
        assert r["ms_per_frame"] == pytest.approx(1e3 * r["timing"]["median_s"]
                                                  / r["settings"]["batch"])
        assert math.isfinite(r["accuracy"]["psnr_db"])
    assert rows["cv2.remap float maps float32"]["ratio_to_remap"] == 1.0
    assert result["pareto"]["cpu"] and all(result["rows"][i].get("pareto")
                                           for i in result["pareto"]["cpu"])

    # what the table must show: failing seams, aliasing, wrong labels
    head = rows["bilinear F12"]["accuracy"]
    assert rows["bilinear F12 border none"]["accuracy"]["seam_max_err"] > 3 * head["seam_max_err"]
    assert any("seams visible" in n for n in rows["bilinear F12 border none"]["notes"])
    assert rows[f"{fine} ss2"]["accuracy"]["psnr_db"] > rows[fine]["accuracy"]["psnr_db"] + 3
    assert any(n.startswith("aliased") for n in rows[fine]["notes"])
    assert 0.5 < head["label_accuracy"] <= 1 and head["town_psnr_db"] > 10
    assert rows[fine]["accuracy"]["town_psnr_db"] is None  # beyond F_req: no town cube

    table = (tmp_path / "bench.md").read_text()
    assert "| row | device |" in table
    assert all(f"| {name}" in table for name in rows)
    assert (tmp_path / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_missing_peers_are_skipped(tmp_path, monkeypatch):
    real = bm._optional
    missing = ("cv2", "py360convert", "pytorch360convert")
    monkeypatch.setattr(bm, "_optional", lambda name: None if name in missing else real(name))
    only = ["bilinear F12 b2", "cv2.remap", "py360convert", "pytorch360convert"]
    assert bm.main([*TINY, "--out-dir", str(tmp_path), "--only", *only]) == 0
    rows = json.loads((tmp_path / "bench.json").read_text())["rows"]
    skipped = [r for r in rows if r["skipped"]]
    assert {r["family"] for r in skipped} == {"cv2.remap", "py360convert", "pytorch360convert"}
    assert all("not installed" in r["notes"][0] and r["accuracy"] is None and "timing" not in r
               for r in skipped)
    ours = [r for r in rows if not r["skipped"]]
    assert [r["name"] for r in ours] == ["bilinear F12 b2"] and ours[0]["ratio_to_remap"] is None
    assert "not installed" in (tmp_path / "bench.md").read_text()


def test_bad_arguments(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="--device cuda"):
        bm._devices(["cuda"])
    assert bm._devices(["auto", "cpu"]) == [torch.device("cpu")]
    with pytest.raises(SystemExit) as exit_:
        bm.main(["--town-samples", "2"])
    assert exit_.value.code == 2
    assert "--town-samples: expected an odd number" in capsys.readouterr().err
    with pytest.raises(ValueError, match="pixels_per_radian"):
        bm.sphere_texture(torch.zeros(3, 3), -1.0)
    with pytest.raises(ValueError, match="directions"):
        bm.sphere_texture(torch.zeros(3, 2), 1.0)


# --------------------------------------------------------------------------------------------
# bench_projection.py and bench_augment.py: their quick modes, smaller still
# --------------------------------------------------------------------------------------------

def test_projection_benchmark_rows_ratios_and_floors(tmp_path):
    """Issue 16's rows, ratios and memory-traffic floors, and the uint8 agreement."""
    pytest.importorskip("cv2")
    import bench_projection as bp

    out = tmp_path / "projection.json"
    face = 16
    assert bp.main(["--quick", "--face", str(face), "--batches", "1", "2", "--repeats", "1",
                    "--warmup", "0", "--no-fused", "--copy-mb", "1", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = {(r["batch"], r["name"]): r for r in result["rows"]}
    new = ("u8_cached", "u8_cached_planes", "u8_rebuilt", "u8_cached_out", "f16_cached",
           "bf16_cached", "remap_u8_fixed", "copy")
    assert all((b, name) in rows for b in (1, 2) for name in new)
    bandwidth = result["copy"]["bandwidth_bytes_per_s"]
    assert set(bandwidth) == {"batch_1", "batch_2"} and min(bandwidth.values()) > 0
    # the traffic model, written out for one row: cube + table shared by the batch + image
    pixels = (2 * face) ** 2
    moved = rows[(2, "u8_cached")]["traffic"]
    assert moved["bytes_per_frame"]["total"] == 6 * face**2 * 3 + 12 * pixels / 2 + 3 * pixels
    assert moved["floor_s_per_frame"] == pytest.approx(moved["bytes_per_frame"]["total"]
                                                       / bandwidth["batch_2"])
    assert rows[(1, "u8_cached_out")]["traffic"]["bytes_per_frame"]["valid"] == pixels
    assert all(r["traffic"]["floor_ratio"] > 0 for r in result["rows"]
               if r["name"] in bp.TRAFFIC)
    assert all("traffic" not in r for r in result["rows"] if r["kind"] in ("part", "bandwidth"))
    ratios = {(q["batch"], q["ours"], q["peer"]): q for q in result["ratios"]}
    for (ours, peer), target in bp.TARGETS.items():
        q = ratios[(2, ours, peer)]
        assert q["target"] == target and q["meets_target"] == (q["ratio"] <= target)
        assert q["min_ratio"] > 0
    assert ratios[(1, "u8_cached", "remap_u8_fixed")]["aim"] == 0.8
    agreement = result["agreement"]
    assert agreement["batch_2_u8_vs_rounded_float_max_abs_diff"] <= 1
    # cv2's fixed-point maps put the taps on a 1/32-pixel grid: a few levels on a random cube
    assert agreement["batch_2_u8_vs_remap_u8_fixed_max_abs_diff"] <= 10
    assert agreement["batch_2_f16_vs_float32_max_abs_diff"] < 1e-2
    table = bp.markdown(result)
    assert "| x floor |" in table and "copy bandwidth" in table and "(aim 0.8)" in table


def test_augment_benchmark_uint8_rows(tmp_path):
    """Issue 16: RandomOmniCamera on uint8 cubes against float32 ones, same draws."""
    import bench_augment as ba

    out = tmp_path / "augment.json"
    assert ba.main(["--quick", "--batch", "2", "--face", "16", "--size", "32", "--repeats",
                    "1", "--warmup", "0", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = {r["name"]: r for r in result["rows"]}
    assert {"ours", "ours_u8", "rgb_f32", "rgb_u8", "rgb_u8_hwc", "rgb_f32_per_sample",
            "rgb_u8_per_sample", "call_16px"} <= set(rows)
    assert rows["call_16px"]["batch"] == 1 and rows["rgb_u8_per_sample"]["batch"] == 2
    if sys.platform.startswith("linux"):   # getrusage counts them
        assert all(r["page_faults"] >= 0 for r in rows.values())
    pairs = {(q["uint8"], q["float32"]): q for q in result["u8_headline"]}
    assert set(pairs) == {("rgb_u8", "rgb_f32"), ("rgb_u8_hwc", "rgb_f32"),
                          ("ours_u8", "ours"), ("rgb_u8_per_sample", "rgb_f32_per_sample")}
    for q in pairs.values():
        assert q["target"] == ba.U8_TARGET and q["throughput_ratio"] > 0
        assert q["meets_target"] == (q["throughput_ratio"] >= ba.U8_TARGET)
    assert result["u8_agreement"]["u8_vs_rounded_float_max_abs_diff"] <= 1
    assert "throughput rgb_u8 / rgb_f32" in ba.markdown(result)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
@pytest.mark.parametrize("heap", ["warm", "fresh"])
def test_set_heap_decides_whether_large_allocations_fault(heap):
    """common.set_heap, in a process of its own (it changes the heap for good): a 4 MiB tensor
    made per call faults in its 1024 pages every call with fresh mappings, none once the heap
    keeps its memory."""
    code = ("import sys, torch; sys.path.insert(0, 'benchmarks'); "
            "from common import measure, set_heap; "
            f"set_heap({heap!r}); "
            "print(measure([lambda: torch.ones(1 << 20)], repeats=5, warmup=2)[0]['page_faults'])")
    done = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    faults = float(done.stdout.split()[-1])
    assert faults >= 1024 if heap == "fresh" else faults < 16


def test_set_heap_refuses_unknown_modes():
    from common import set_heap

    with pytest.raises(ValueError, match="heap: expected one of"):
        set_heap("cold")


def test_reproject_benchmark_rows(tmp_path, monkeypatch):
    """Issue 17: RandomReproject per image and per batch against albumentations (where it is
    installed; else its row is skipped and said so) and kornia, with its agreement with the
    exact chain on the same draws."""
    import bench_reproject as br

    out = tmp_path / "reproject.json"
    assert br.main(["--quick", "--repeats", "1", "--warmup", "0", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = {r["name"]: r for r in result["rows"]}
    assert {"ours_batch", "ours_sample", "ours_sample_hwc", "exact", "ours_batch_detection",
            "ours_batch_instances"} <= set(rows)
    overhead = result["detection_overhead"]   # issue 35: the ratio to ours_batch, its target
    assert overhead["ours_batch_detection"] > 0 and overhead["target"] == br.DETECTION_TARGET
    assert all(r["images_per_s"] > 0 for r in rows.values())
    agreement = result["agreement"]
    assert agreement["valid_mismatch_fraction"] < 0.01
    assert agreement["rgb_max_abs_diff_levels"] <= 1 and agreement["label_agreement"] > 0.99
    if br.albumentations is None:
        assert "albumentations" in result["skipped"] and not result["headline"]
    else:
        assert {h["ours"] for h in result["headline"]} == {"ours_sample", "ours_sample_hwc",
                                                             "ours_batch"}
    monkeypatch.setattr(br, "albumentations", None)   # the peer missing: said, not failed
    assert br.main(["--quick", "--repeats", "1", "--warmup", "0", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert "albumentations" in result["skipped"] and "skipped albumentations" in br.markdown(
        result)


@pytest.mark.slow
def test_workers_benchmark_rows_and_its_peer(tmp_path):
    """Issue 17: RandomOmniCamera in DataLoader workers against the numpy + cv2.remap peer,
    every fisheye model and the mix, float32 and uint8; the peer's Newton inverse of
    Kannala-Brandt inverts its polynomial, its closed-form unprojections invert its radii,
    and its equidistant maps are bench_augment's."""
    pytest.importorskip("cv2")
    import numpy as np
    import bench_augment as ba
    import bench_workers as bw

    k = np.array([0.02, -0.01, 0.005, -0.002], dtype=np.float32)
    r = np.linspace(0, 1.4, 50, dtype=np.float32)   # short of every domain end and fold
    for model in ("equidistant", "equisolid", "stereographic", "kannala_brandt"):
        theta = bw.theta_of(model, r, k)
        assert np.allclose(bw.radius_of(model, theta, k), r, atol=1e-5)
    # the peer's closed-form unprojections of the other lenses: each ray's angle projects
    # back to its radius through the model's forward radius_of
    x = np.linspace(0, 0.9, 40, dtype=np.float64)[None, :]
    for model, lens in (("unified", [0.8]), ("eucm", [0.6, 1.1]),
                        ("double_sphere", [-0.2, 0.6])):
        lens = np.array(lens + [0.0] * (4 - len(lens)))
        rays = bw.rays_of(model, x, np.zeros_like(x), lens)
        theta = np.arctan2(rays[..., 0], rays[..., 2])
        assert np.allclose(bw.radius_of(model, theta, lens), x, atol=1e-9)
    # same draws: the rng's first calls are peer_draw's in both
    ours = bw.peer_maps("equidistant", np.random.default_rng(3), 24, 8)
    theirs = ba.peer_maps(*ba.peer_draw(np.random.default_rng(3)), 24, 8)
    assert all(np.allclose(a, b, atol=1e-4) for a, b in zip(ours, theirs))

    out = tmp_path / "workers.json"
    assert bw.main(["--quick", "--face", "8", "--size", "16", "--batch", "2", "--batches", "2",
                    "--rounds", "1", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    rows = {(r["model"], r["dtype"], r["row"]) for r in result["rows"]}
    models = (*ot.augment.FISHEYE_MODELS, "mix")
    assert rows == {(m, d, row) for m in models for d in ("float32", "uint8")
                    for row in ("ours_collate", "ours_sample", "peer")}
    assert all(r["images_per_s"] > 0 and r["first_batch_s"] > 0 for r in result["rows"])
    for q in result["ratios"]:
        assert q["meets_target"] == (q["ratio"] >= q["target"] if q["peer"] == "peer"
                                     else q["ratio"] <= q["target"])
    assert "| mix | uint8 | ours_collate / peer |" in bw.markdown(result)


# --------------------------------------------------------------------------------------------
# bench_training.py: issue 36's "proof that it helps", in its quick mode
# --------------------------------------------------------------------------------------------

#: A temporary of omniscape_torch.io.atomic: ``.<name>.<pid>.<8 characters>[suffix]``.
_TEMPORARY = re.compile(r"^\..+\.\d+\.[a-z0-9_]{8}(\..+)?$")


@pytest.mark.slow
def test_training_benchmark_quick(tmp_path, monkeypatch):
    """Every condition (albumentations skipped only with a reason) and camera kind in the JSON,
    mIoUs finite in [0, 1], per-class IoU, every run stopped by the rule, the kornia search
    over the whole grid; every output and cached file written by rename from a temporary
    beside it; and --estimate's projection."""
    import bench_training as bt

    replaced = []
    real_replace = os.replace

    def spy(src, dst, *args, **kwargs):
        replaced.append((Path(src), Path(dst)))
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", spy)
    out = tmp_path / "results" / "training.json"
    cache = tmp_path / "cache"
    assert bt.main(["--quick", "--cache", str(cache), "--out", str(out), "--no-progress"]) == 0
    result = json.loads(out.read_text())
    assert {"commit", "dirty", "machine", "versions", "threads", "setup", "runs", "summary",
            "augment_timing", "kornia_search", "skipped", "loadavg_start",
            "loadavg_end"} <= set(result)
    assert set(result["skipped"]) <= {"albumentations"}
    names = [n for n in bt.CONDITIONS if n not in result["skipped"]]
    assert list(result["conditions"]) == names and set(result["summary"]) == set(names)
    table = out.with_suffix(".md").read_text()
    stopping = result["setup"]["stopping"]
    for name in names:
        assert set(result["summary"][name]) == set(bt.CAMERA_KINDS)
        runs = [r for r in result["runs"] if r["condition"] == name]
        assert [r["seed"] for r in runs] == result["seeds"] == [0]
        for r in runs:
            assert stopping["min_steps"] <= r["steps"] <= stopping["max_steps"]
            assert len(r["losses"]) == r["steps"] and r["stopped"] in ("flat", "cap")
            assert (r["stopped"] == "flat") == (r["quarter_change"] <= stopping["flat_tol"])
            assert r["loss_end"] < r["loss_start"]
            for kind in bt.CAMERA_KINDS:
                miou = r["eval"][kind]["miou"]
                assert math.isfinite(miou) and 0 <= miou <= 1
                assert r["eval"][kind]["classes_present"]
        for kind in bt.CAMERA_KINDS:
            assert set(result["summary"][name][kind]["iou_mean"]) == set(bt.CLASSES)
        assert result["augment_timing"][name]["images_per_s"] > 0
        assert f"| {bt.LABELS[name]} |" in table
    assert "**Pole**" in table and "**Pedestrian**" in table and "**TrafficSign**" in table
    search = result["kornia_search"]
    assert len(search["grid"]) == len(bt.KORNIA_GRID)
    assert search["best"] in [{"center": r["center"], "gamma": r["gamma"]}
                              for r in search["grid"]]
    assert result["conditions"]["kornia_fisheye"]["gamma"] == search["best"]["gamma"]
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    cubes = sorted((cache / "train_town0_face32").glob("cube_*.pt"))
    traced = [cache / name for name in ("test_town1_size32.pt", "val_town0_size32.pt",
                                          "upper_town0_size32.pt")]
    assert len(cubes) == 4
    renamed = {dst for src, dst in replaced
               if src.parent == dst.parent and src.name.startswith(f".{dst.name}.")}
    for path in [out, out.with_suffix(".md"), out.with_suffix(".png"), *cubes, *traced]:
        assert path in renamed, path
    assert not [p for p in tmp_path.rglob(".*") if _TEMPORARY.match(p.name)]

    # a second read takes the cubes from the cache
    lines = []
    again = bt.training_cubes(cache, 0, 4, 32, log=lines.append)
    assert "0 rendered" in lines[0] and again["rgb"].shape == (4, 6, 3, 32, 32)

    estimate = tmp_path / "estimate.json"
    assert bt.main(["--quick", "--estimate", "--estimate-steps", "1", "--cache", str(cache),
                    "--out", str(estimate)]) == 0
    est = json.loads(estimate.read_text())
    assert set(est["step_s"]) == set(names) and all(v > 0 for v in est["step_s"].values())
    assert 0 < est["total_at_min_steps_s"] <= est["total_at_cap_s"]


def test_training_benchmark_parts(monkeypatch):
    """kornia's RandomFisheye with labels: the image's field, nearest, 255 where the image
    is zero padding; conditions reproducible from their seed, the global RNG untouched;
    RandomReproject given the faces' own intrinsics; traced labels those of the analytic
    equidistant rays; the stopping rule, the network's size, IoU on a known case; bad flags
    named."""
    import bench_training as bt

    g = torch.Generator().manual_seed(0)
    faces = {"rgb": torch.rand(4, 3, 16, 16, generator=g),
             "labels": torch.randint(0, 13, (4, 16, 16), generator=g)}
    cubes = {"rgb": torch.rand(1, 6, 3, 16, 16, generator=g),
             "labels": torch.randint(0, 13, (1, 6, 16, 16), generator=g)}
    ones = {"rgb": torch.ones(4, 3, 16, 16), "labels": torch.zeros(4, 16, 16, dtype=torch.long)}
    rgb, labels = bt.make_condition("kornia_fisheye", ones, cubes, 0).batch(torch.arange(4))
    inside, outside = rgb[:, 0] == 1, rgb[:, 0] == 0
    assert inside.any() and outside.any()
    assert bool((labels[inside] == 0).all()) and bool((labels[outside] == 255).all())

    idx = torch.tensor([0, 2, 3])
    names = ["kornia_fisheye", "reproject", "omni_camera", "fisheye_upper"]
    if not isinstance(bt.albumentations_or_reason(), str):
        names.append("albumentations")
    for name in names:
        state = torch.get_rng_state()
        pick = idx if name != "omni_camera" else torch.zeros(3, dtype=torch.long)
        a = bt.make_condition(name, faces, cubes, 5, traced=faces).batch(pick)
        assert torch.equal(torch.get_rng_state(), state)
        b = bt.make_condition(name, faces, cubes, 5, traced=faces).batch(pick)
        assert all(torch.equal(x, y) for x, y in zip(a, b))
        assert a[1].dtype == torch.int64 and a[0].shape == (3, 3, 16, 16)
    with pytest.raises(ValueError, match="name"):
        bt.make_condition("cutmix", faces, cubes, 0)
    with pytest.raises(ValueError, match="traced"):
        bt.make_condition("fisheye_upper", faces, cubes, 0)

    condition = bt.make_condition("reproject", faces, cubes, 3)
    calls = []
    render = ot.augment.RandomReproject._render   # (forward's render of its own draws)
    monkeypatch.setattr(ot.augment.RandomReproject, "_render",
                        lambda self, *a, **k: calls.append(k["intrinsics"]) or render(self, *a,
                                                                                      **k))
    condition.batch(idx)
    assert torch.equal(calls[0], torch.tensor([[8.0, 8.0, 7.5, 7.5]]).expand(3, 4))

    # traced: the labels of the equidistant rays (theta = r / f, f theta(95 deg) = 7.5 px)
    town, size = ot.scenes.Town(1, layout=2), 16
    camera, attitude = bt.test_camera("fisheye", size)
    rotation = bt.yaw_matrix(0.7) @ attitude
    position = [1.0, -1.0, 5.0]
    rgb, labels = bt.trace_image(town, camera, rotation, position, 0.0, "clear_sunset", 2)
    f, c = (size / 2 - 0.5) / math.radians(95), (size - 1) / 2
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64),
                          torch.arange(size, dtype=torch.float64), indexing="ij")
    x, y = (u - c) / f, (v - c) / f
    theta = torch.hypot(x, y)
    scale = torch.where(theta > 0, torch.sin(theta) / theta, torch.ones_like(theta))
    rays = torch.stack((x * scale, y * scale, torch.cos(theta)), -1)
    truth = town.render_rays(torch.tensor(position), rays.float() @ rotation.T, t=0.0,
                             weather="clear_sunset")["labels"]
    clear = (theta - math.radians(95)).abs() > 1e-4
    inside = clear & (theta < math.radians(95))
    assert rgb.dtype == labels.dtype == torch.uint8 and rgb.shape == (3, size, size)
    assert torch.equal(labels[inside].long(), truth[inside])
    assert bool((labels[clear & ~inside] == 255).all()) and bool((rgb[:, clear & ~inside] == 0)
                                                                 .all())

    assert sum(p.numel() for p in bt.UNet(13, 16, 4).parameters()) == 488_909
    assert sum(p.numel() for p in bt.UNet(13, 16, 3).parameters()) == 119_117
    assert bt.UNet(13, 4, 4)(torch.rand(1, 3, 24, 24)).shape == (1, 13, 24, 24)

    assert not bt.flat([4.0] * 4 + [3.0, 3.0, 2.0, 2.0], 0.02)["flat"]   # 3 -> 2: a third down
    rule = bt.flat([4.0] * 4 + [3.0, 3.0, 2.95, 2.95], 0.02)
    assert rule["flat"] and rule["quarter_change"] == pytest.approx(0.05 / 3)
    assert bt.flat([1.0] * 6 + [1.5] * 2, 0.0)["flat"]   # rising is flat

    truth = torch.tensor([[0, 0, 1, 255], [2, 2, 2, 255]])
    pred = torch.tensor([[0, 1, 1, 0], [2, 2, 0, 1]])
    scores = bt.iou_scores(bt.confusion(pred, truth, classes=4))
    # class 0: 1 / 3, class 1: 1 / 2, class 2: 2 / 3; class 3 absent from the truth
    assert scores["iou"][:3] == pytest.approx([1 / 3, 1 / 2, 2 / 3]) and scores["iou"][3] is None
    assert scores["miou"] == pytest.approx((1 / 3 + 1 / 2 + 2 / 3) / 3)
    assert scores["classes_present"] == [0, 1, 2] and scores["pixels"] == 6

    for argv, message in ((["--test-town", "0"], "--train-town and --test-town"),
                          (["--quick", "--size", "4"], "--size"),
                          (["--quick", "--size", "30"], "--size"),
                          (["--quick", "--seeds", "0", "0"], "--seeds"),
                          (["--quick", "--max-steps", "10"], "--max-steps"),
                          (["--quick", "--min-steps", "4", "--chunk", "2"], "--min-steps"),
                          (["--quick", "--flat-tol", "1.5"], "--flat-tol"),
                          (["--quick", "--test-weathers", "clear_noon"], "--test-weathers"),
                          (["--quick", "--lr", "-1"], "--lr")):
        with pytest.raises(SystemExit) as exit_:
            bt.main(argv)
        assert exit_.value.code == 2


def test_training_runs_resume_and_are_shared_between_processes(tmp_path):
    """A finished run is read back, not trained again; other settings train it again; a
    dead process's claim is taken over; a live one's is waited for until its record lands."""
    import threading

    import bench_training as bt

    calls = []

    def train(value):
        def f():
            calls.append(value)
            return {"value": value}
        return f

    meta = {"seed": 0, "kornia": {"center": (-0.1, 0.1)}}   # a tuple: JSON reads back a list
    assert bt.cached_run(tmp_path, "k", meta, train(1), log=calls.append) == {"value": 1}
    assert bt.cached_run(tmp_path, "k", meta, train(2), log=calls.append) == {"value": 1}
    assert calls == [1]
    assert bt.cached_run(tmp_path, "k", {**meta, "seed": 1}, train(3)) == {"value": 3}
    assert not list((tmp_path / "runs").glob("*.claim"))

    # a claim left by a process that has died: taken over
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / "runs" / "d.claim").write_text(str(dead.pid))
    assert bt.cached_run(tmp_path, "d", meta, train(4)) == {"value": 4}

    # a live process's claim (this process's parent): wait for the record it writes
    (tmp_path / "runs" / "w.claim").write_text(str(os.getppid()))
    logged = []

    def other():
        bt.write_json_atomic({"meta": json.loads(json.dumps(meta)), "run": {"value": 5}},
                             tmp_path / "runs" / "w.json")
        (tmp_path / "runs" / "w.claim").unlink()

    timer = threading.Timer(0.2, other)
    timer.start()
    assert bt.cached_run(tmp_path, "w", meta, train(6), wait=False) is None
    assert bt.cached_run(tmp_path, "w", meta, train(6), log=logged.append,
                         poll_s=0.05) == {"value": 5}
    timer.join()
    assert 6 not in calls and "waiting" in logged[0]

    # several jobs: the one another process trains is taken last, the others first, in order
    (tmp_path / "runs" / "b.claim").write_text(str(os.getppid()))
    calls.clear()
    timer = threading.Timer(0.2, lambda: (
        bt.write_json_atomic({"meta": {}, "run": {"value": "b"}}, tmp_path / "runs" / "b.json"),
        (tmp_path / "runs" / "b.claim").unlink()))
    timer.start()
    jobs = [(key, {}, train(key)) for key in "abc"]
    assert bt.cached_runs(tmp_path, jobs, logged.append, poll_s=0.05) == [
        {"value": "a"}, {"value": "b"}, {"value": "c"}]
    timer.join()
    assert calls == ["a", "c"]


# --------------------------------------------------------------------------------------------
# --quick never overwrites the committed full-run results (issue 32)
# --------------------------------------------------------------------------------------------

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_quick_results_go_to_a_git_ignored_folder():
    import common

    assert common.results_path("x.json") == common.RESULTS / "x.json"
    assert common.results_path("x.json", quick=True) == common.QUICK_RESULTS / "x.json"
    assert common.QUICK_RESULTS.parent == common.RESULTS
    ignored = subprocess.run(["git", "check-ignore", "-q",
                              str(common.QUICK_RESULTS / "bench.json")],
                             cwd=common.ROOT, capture_output=True)
    if ignored.returncode == 128:
        pytest.skip("not a git checkout")
    assert ignored.returncode == 0, "benchmarks/results/quick/ is not git-ignored"


def test_run_quick_writes_under_quick_and_a_full_run_under_results():
    import common

    parser = bm.argparse.ArgumentParser()
    bm.add_arguments(parser, common.RESULTS)
    assert bm._resolve(parser.parse_args(["--quick"])).out_dir == common.RESULTS / "quick"
    assert bm._resolve(parser.parse_args([])).out_dir == common.RESULTS
    assert bm._resolve(parser.parse_args(["--quick", "--out-dir", "elsewhere"])).out_dir == \
        Path("elsewhere")


@pytest.mark.parametrize("script", ["bench_antialias", "bench_augment", "bench_busy",
                                    "bench_cameras", "bench_fixed_cost", "bench_perspective",
                                    "bench_models_layer", "bench_png", "bench_projection",
                                    "bench_reproject", "bench_scaling", "bench_workers"])
def test_each_quick_mode_defaults_under_quick(script):
    import importlib

    import common

    module = importlib.import_module(script)
    full, quick = module.parse_args([]).out, module.parse_args(["--quick"]).out
    assert full.parent == common.RESULTS and quick == common.QUICK_RESULTS / full.name
    assert module.parse_args(["--quick", "--out", "x.json"]).out == Path("x.json")


def test_no_script_with_a_quick_mode_hard_codes_its_results_path():
    """Every benchmark with ``--quick`` takes its default output from common.results_path
    (the scripts without a parse_args function are checked here by their source)."""
    scripts = [p for p in sorted(BENCHMARKS.glob("*.py"))
               if '"--quick"' in p.read_text(encoding="utf-8")]
    assert len(scripts) >= 12, scripts
    for path in scripts:
        text = path.read_text(encoding="utf-8")
        assert not re.search(r'"results"\s*/\s*(f?"[\w{}.]+\.json"|\n)', text), path.name
        # harness.py: out_dir / "quick" (run.py passes it the folder)
        assert "results_path(" in text or '/ "quick"' in text or path.name == "run.py", \
            path.name


@pytest.mark.slow
def test_models_layer_benchmark_rows(tmp_path):
    """Issue 34: every model of CAMERAS has each row at each batch, its ratio to
    Kannala-Brandt's row in the same run, and a lens that sees (valid share > 0.3)."""
    import bench_models_layer as bml

    out = tmp_path / "m.json"
    assert bml.main(["--face", "16", "--batches", "1", "2", "--repeats", "1", "--warmup", "0",
                     "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    got = {(r["model"], r["row"], r["batch"]) for r in result["rows"]}
    want = {(m, row, b) for m in bml.CAMERAS for row, b in
            (("cached", 1), ("cached", 2), ("rebuilt", 1), ("rebuilt", 2), ("new_camera", 1))}
    assert got == want
    for r in result["rows"]:
        assert r["median_s"] > 0 and math.isfinite(r["ratio"])
        if r["model"] == bml.REFERENCE:
            assert r["ratio"] == 1.0
    assert all(share > 0.3 for share in result["valid_share"].values()), result["valid_share"]
