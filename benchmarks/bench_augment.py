"""Random omni-camera augmentation: ``RandomOmniCamera`` against per-sample ``cv2.remap``.

Issue 5's throughput benchmark: images per second, on the CPU with ``--threads`` (default 2)
threads, for batches of ``B`` cubemaps ``6 x F x F`` (RGB float32 + uint8 labels) rendered to
``S x S`` equidistant fisheyes (default B = 16, F = 256, S = 512), with a new random camera
(fov uniform in 160-200 deg, image circle inscribed) and attitude (roll +-25 deg, pitch +-10 deg,
any yaw) per sample and call. Timed round-robin in one run:

* ``ours``: ``RandomOmniCamera((S, S), F, mode="fisheye")(cube, labels=labels)`` (drawing,
  cameras, rays, fov cones, grid, RGB bilinear sampling, label gather, masking);
* ``peer``: what a user would write without this package, per sample: draw the same kind of
  camera and attitude with numpy, compute every pixel's ray (numpy, float32), rotate it, pick the
  cube face (argmax of the six face axes of DESIGN.md's table) and its face (u, v), build
  ``map_x``/``map_y`` into an atlas of the 6 faces stacked vertically, each face padded by one
  texel by edge replication (``np.pad(mode="edge")``, rebuilt per sample, timed), then
  ``cv2.remap`` the RGB atlas (HWC float32, ``INTER_LINEAR``) and the label atlas (uint8,
  ``INTER_NEAREST``), invalid pixels mapped outside (``BORDER_CONSTANT`` 0 / 255). Its inputs
  are numpy HWC arrays converted once, untimed (as a numpy user would hold them);
* our parts apart (``part`` rows): ``params`` (``forward_parameters``), ``rays``
  (``kernels.camera_grid(..., lazy=True)``: every camera's table, then every pixel's ray and
  validity, its cones included, in one C++ pass), ``sample`` (the layer's rendering of RGB and
  labels through those rays and the attitudes, on the fast path: each pixel's taps computed in
  the sampling pass), both in chunks of samples as ``render`` chunks a batch on the CPU
  (``projection.CHUNK_PIXELS``); and the peer's
  ``peer_maps`` (numpy maps only) and ``peer_remap`` (atlas padding + the two remaps, maps
  prebuilt).

* ``uint8`` cubes (issue 16): the same module settings and seed on the same cube as ``uint8``
  (``round(255 cube)``), so that the k-th call of every row below draws the same cameras and
  attitudes as the k-th call of ``ours``: ``ours_u8`` (``uint8`` RGB + labels, against
  ``ours``), and RGB alone, ``rgb_f32`` against ``rgb_u8`` (a ``uint8`` image, rounded half up)
  and ``rgb_u8_hwc`` (``channels_last=True``: a ``(B, 6, F, F, 3)`` cube and a ``(B, H, W, 3)``
  image, as image files hold them).
* one sample per call, as a ``Dataset``'s ``__getitem__`` applies the module: ``rgb_f32_per_sample``
  and ``rgb_u8_per_sample`` (the batch's B samples, one call each, timed together), and
  ``call_16px``: a call on one 16 x 16 image from 8-texel faces, the fixed cost of a call
  (drawing, the camera's table, checks, Python).

Headlines: ``ours`` images/s over ``peer`` images/s (target >= 2); ``uint8`` images/s over
float32 images/s (target >= 1.5, ``U8_TARGET``), for RGB alone (``rgb_u8`` / ``rgb_f32``: the
cube's dtype is all that differs; ``rgb_u8_hwc`` / ``rgb_f32``: the layout too) and with the
labels (``ours_u8`` / ``ours``: the labels' gather and their int64 image cost the same in both,
so the ratio is smaller) and one sample per call (``rgb_u8_per_sample`` /
``rgb_f32_per_sample``), all from the medians of the same interleaved run. A check renders
the peer with our drawn parameters and reports how far the two outputs agree (label agreement
on pixels both call valid, RGB mean / max abs difference; ours pads faces from their
neighbours, the peer by edge replication, so texels next to a seam differ slightly), and the
``uint8`` image against the float path on the same values rounded half up (at most 1 level).

Timing: ``common.measure``: ``--warmup`` untimed calls of each, then ``--repeats`` timed calls
round-robin, median and IQR. Randomness: seeded (``torch.Generator`` for the inputs and our
module, ``numpy.random.default_rng`` for the peer).

Usage::

    python benchmarks/bench_augment.py            # B = 16, 6 x 256 -> 512 x 512, 2 threads
    python benchmarks/bench_augment.py --quick    # B = 4, 6 x 64 -> 128 x 128, seconds

Results: a markdown table on stdout and JSON (``--out``, default
``benchmarks/results/augment.json``, written atomically).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
# Benchmark the checkout this script lives in, not whatever copy is installed.
sys.path.insert(0, str(ROOT))

from common import (HEAP_MODES, begin_run, loadavg, measure, results_path, run_main,  # noqa: E402
                    run_record, set_heap)
from omniscape_torch.augment import RandomOmniCamera  # noqa: E402
from omniscape_torch.cameras import Camera  # noqa: E402
from omniscape_torch.cubemap import face_axes  # noqa: E402
from omniscape_torch.render.layer import CHUNK_PIXELS, OmniProjection  # noqa: E402
from omniscape_torch.render.kernels.camera import camera_grid  # noqa: E402

try:
    import cv2
except ImportError:  # the OpenCV peer is skipped, our rows still run
    cv2 = None

SEED = 20240611
TARGET = 2.0  # ours / peer throughput
U8_TARGET = 1.5  # uint8 / float32 cube throughput (issue 16)
_DEG = math.pi / 180
FOV_RANGE = (160 * _DEG, 200 * _DEG)
ROLL_RANGE = (-25 * _DEG, 25 * _DEG)
PITCH_RANGE = (-10 * _DEG, 10 * _DEG)
YAW_RANGE = (-math.pi, math.pi)

# --------------------------------------------------------------------------------------------
# The peer: numpy maps + cv2.remap, per sample
# --------------------------------------------------------------------------------------------

# DESIGN.md's face table (the package's, cubemap/faces.py: the only copy), in FACES order:
# a (looks along), b (image down), r (image right); face pixel (u, v) is the ray
# r (u - c) / f + b (v - c) / f + a with f = F / 2, c = (F - 1) / 2.
FACE_A, FACE_B, FACE_R = face_axes(torch.float32).numpy().transpose(1, 0, 2)


def np_yaw_pitch_roll(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``R_yaw R_pitch R_roll`` (camera -> cube frame), the rig convention of DESIGN.md."""
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch),
                              math.cos(roll), math.sin(roll))
    r_yaw = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_pitch = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    r_roll = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return r_yaw @ r_pitch @ r_roll


def peer_draw(rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """A random fisheye fov and attitude, as a numpy user would draw them."""
    fov = rng.uniform(*FOV_RANGE)
    yaw, pitch, roll = rng.uniform(*YAW_RANGE), rng.uniform(*PITCH_RANGE), rng.uniform(*ROLL_RANGE)
    return fov, np_yaw_pitch_roll(yaw, pitch, roll)


def peer_maps(fov: float, rotation: np.ndarray, size: int, face: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (float32, atlas pixels) of an ``size x size`` equidistant fisheye of
    ``fov`` (circle inscribed), rotated by ``rotation``; invalid pixels map outside the atlas."""
    focal = (size / 2 - 0.5) / (fov / 2)
    centre = (size - 1) / 2
    coords = (np.arange(size, dtype=np.float32) - centre) / focal
    x, y = np.meshgrid(coords, coords)  # x along columns (u), y along rows (v)
    theta = np.hypot(x, y)
    scale = np.sinc(theta / np.pi)  # sin(theta) / theta, 1 at 0
    rays = np.stack((x * scale, y * scale, np.cos(theta)), axis=-1)  # (S, S, 3)
    return atlas_maps(rays @ rotation.astype(np.float32).T, theta > fov / 2, face)


def atlas_maps(rays: np.ndarray, invalid: np.ndarray, face: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (float32) into :func:`peer_atlas` of cube-frame ``rays (S, S, 3)``:
    the face each ray looks at (argmax of the six face axes) and its face pixel; the
    ``invalid`` pixels map outside the atlas."""
    dots = rays @ FACE_A.T  # (S, S, 6)
    k = np.argmax(dots, axis=-1)
    along = np.take_along_axis(dots, k[..., None], axis=-1)[..., 0]
    right = np.einsum("hwc,hwc->hw", rays, FACE_R[k])
    down = np.einsum("hwc,hwc->hw", rays, FACE_B[k])
    half, c_face, n_pad = face / 2, (face - 1) / 2, face + 2
    map_x = (c_face + 1 + half * right / along).astype(np.float32)
    map_y = (k * n_pad + c_face + 1 + half * down / along).astype(np.float32)
    map_x[invalid] = -10.0
    map_y[invalid] = -10.0
    return map_x, map_y


def peer_atlas(faces: np.ndarray) -> np.ndarray:
    """``(6, F, F[, C])`` faces -> ``(6 (F + 2), F + 2[, C])``, each face edge-padded by 1."""
    pad = ((0, 0), (1, 1), (1, 1)) + ((0, 0),) * (faces.ndim - 3)
    padded = np.pad(faces, pad, mode="edge")
    return padded.reshape((-1,) + padded.shape[2:])


def peer_remap(rgb_faces: np.ndarray, label_faces: np.ndarray, map_x: np.ndarray,
               map_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rgb = cv2.remap(peer_atlas(rgb_faces), map_x, map_y, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    labels = cv2.remap(peer_atlas(label_faces), map_x, map_y, cv2.INTER_NEAREST,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=255)
    return rgb, labels


def peer_batch(rgb: list[np.ndarray], labels: list[np.ndarray], rng: np.random.Generator,
               size: int, face: int) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for rgb_faces, label_faces in zip(rgb, labels):
        fov, rotation = peer_draw(rng)
        map_x, map_y = peer_maps(fov, rotation, size, face)
        out.append(peer_remap(rgb_faces, label_faces, map_x, map_y))
    return out


# --------------------------------------------------------------------------------------------
# The benchmark
# --------------------------------------------------------------------------------------------

def run(args: argparse.Namespace) -> dict:
    load_start = begin_run(args.threads, cv2)
    set_heap(args.heap)
    device = torch.device("cpu")
    batch, face, size = args.batch, args.face, args.size

    gen = torch.Generator().manual_seed(SEED)
    cube = torch.rand(batch, 6, 3, face, face, generator=gen)
    labels = torch.randint(0, 13, (batch, 6, face, face), generator=gen, dtype=torch.uint8)
    rgb_np = [np.ascontiguousarray(c.permute(0, 2, 3, 1).numpy()) for c in cube]  # (6, F, F, 3)
    labels_np = [np.ascontiguousarray(lab.numpy()) for lab in labels]

    aug = RandomOmniCamera((size, size), face, mode="fisheye", seed=SEED)
    # uint8 cubes: modules of the same settings and seed, so the k-th call of each draws the
    # same cameras as the k-th call of ``aug`` (every row is called equally often)
    cube_u8 = (cube * 255).round().to(torch.uint8)  # [B, 6, 3, F, F]

    def same(**kwargs) -> RandomOmniCamera:
        return RandomOmniCamera((size, size), face, mode="fisheye", seed=SEED, **kwargs)

    aug_u8, aug_rgb_f32, aug_rgb_u8 = same(), same(), same()
    aug_rgb_u8_hwc = same(channels_last=True)
    # one sample per call, as a Dataset's __getitem__ applies it (each module's k-th call
    # draws the same camera as the other's), and the fixed cost of a call: one 16 x 16 image
    aug_f32_one, aug_u8_one = same(), same()
    aug_tiny = RandomOmniCamera((16, 16), 8, mode="fisheye", seed=SEED)
    cube_tiny = torch.rand(1, 6, 3, 8, 8, generator=gen)
    cube_u8_hwc = cube_u8.permute(0, 1, 3, 4, 2).contiguous()  # [B, 6, F, F, 3]
    part_gen = torch.Generator().manual_seed(SEED + 1)

    # Our parts, on one fixed draw, chunked as render chunks a batch (a fresh layer per chunk,
    # as render builds one per chunk).
    params0 = aug.forward_parameters(batch, generator=torch.Generator().manual_seed(SEED + 2))
    (name0, (_, camera0)), = aug.cameras(params0).items()
    geometry0 = dict(rotation=params0["rotation"].float(), fov=params0["fov"].float(),
                     blind_fov=params0["blind_fov"].float())
    step = max(1, CHUNK_PIXELS // (size * size))
    chunks = [slice(i, i + step) for i in range(0, batch, step)]

    def new_proj(part: slice) -> OmniProjection:
        return OmniProjection(Camera(name0, camera0.params[part], (size, size)), face,
                              interpolation=aug.interpolation, ignore_index=aug.ignore_index)

    pad = new_proj(chunks[0]).pad

    def rays() -> list:
        grids = [camera_grid(name0, camera0.params[part], (size, size), face, pad, lazy=True,
                             **{k: v[part] for k, v in geometry0.items()}) for part in chunks]
        for grid in grids:   # its rays, made on first use
            grid.valid
        return grids

    projs = [new_proj(part) for part in chunks]
    grids = rays()

    def sample() -> list:
        return [proj.render(rgb=cube[part], labels=labels[part], grid=g)
                for proj, part, g in zip(projs, chunks, grids)]

    rng_peer = np.random.default_rng(SEED)
    rng_maps = np.random.default_rng(SEED + 1)
    maps0 = [peer_maps(*peer_draw(np.random.default_rng(SEED + 2 + i)), size, face)
             for i in range(batch)]

    cases: list[tuple[str, str, Callable[[], object]]] = [
        ("ours", "ours", lambda: aug(cube, labels=labels)),
        ("ours_u8", "ours", lambda: aug_u8(cube_u8, labels=labels)),
        ("rgb_f32", "ours", lambda: aug_rgb_f32(cube)),
        ("rgb_u8", "ours", lambda: aug_rgb_u8(cube_u8)),
        ("rgb_u8_hwc", "ours", lambda: aug_rgb_u8_hwc(cube_u8_hwc)),
        ("rgb_f32_per_sample", "ours", lambda: [aug_f32_one(cube[i:i + 1]) for i in range(batch)]),
        ("rgb_u8_per_sample", "ours",
         lambda: [aug_u8_one(cube_u8[i:i + 1]) for i in range(batch)]),
        ("call_16px", "part", lambda: aug_tiny(cube_tiny)),
        ("params", "part", lambda: aug.forward_parameters(batch, generator=part_gen)),
        ("rays", "part", rays),
        ("sample", "part", sample),
    ]
    agreement: dict[str, float] = {}
    u8_agreement: dict[str, float] = {}
    with torch.no_grad():  # uint8 against the float path on the same values, rounded half up
        got = aug(cube_u8, params=params0)["rgb"].to(torch.int16)
        floats = aug(cube_u8.float(), params=params0)["rgb"]
        u8_agreement["u8_vs_rounded_float_max_abs_diff"] = float(
            (got - (floats + 0.5).floor().clamp(0, 255).to(torch.int16)).abs().max())
    if cv2 is not None:
        cases += [
            ("peer", "peer", lambda: peer_batch(rgb_np, labels_np, rng_peer, size, face)),
            ("peer_maps", "peer part",
             lambda: [peer_maps(*peer_draw(rng_maps), size, face) for _ in range(batch)]),
            ("peer_remap", "peer part",
             lambda: [peer_remap(r, lab, *m) for r, lab, m in zip(rgb_np, labels_np, maps0)]),
        ]
        # Agreement: the peer rendered with our drawn fov and rotation.
        out = aug(cube, labels=labels, params=params0)
        ours_rgb = out["rgb"].permute(0, 2, 3, 1).numpy()
        ours_lab = out["labels"].numpy()
        ours_valid = out["valid"][:, 0].numpy()
        same, both, diffs, max_diff = 0, 0, [], 0.0
        for i in range(batch):
            rot = params0["rotation"][i].numpy()
            mx, my = peer_maps(float(params0["fov"][i]), rot, size, face)
            p_rgb, p_lab = peer_remap(rgb_np[i], labels_np[i], mx, my)
            mask = ours_valid[i] & (p_lab != 255)
            both += int(mask.sum())
            same += int((p_lab[mask] == ours_lab[i][mask]).sum())
            d = np.abs(p_rgb[mask] - ours_rgb[i][mask])
            diffs.append(d.mean())
            max_diff = max(max_diff, float(d.max()))
            agreement.setdefault("valid_mismatch_fraction", 0.0)
            agreement["valid_mismatch_fraction"] += float(
                (ours_valid[i] != (p_lab != 255)).mean()) / batch
        agreement["label_agreement"] = same / max(both, 1)
        agreement["rgb_mean_abs_diff"] = float(np.mean(diffs))
        agreement["rgb_max_abs_diff"] = max_diff

    with torch.no_grad():
        results = measure([fn for _, _, fn in cases], args.repeats, args.warmup, device)
    rows = []
    by_name = {}
    for (name, kind, _), res in zip(cases, results):
        images = 1 if name == "call_16px" else batch
        row = {"name": name, "kind": kind, "batch": images, **res,
               "images_per_s": images / res["median_s"],
               "median_per_sample_s": res["median_s"] / images}
        rows.append(row)
        by_name[name] = row
    parts = ("params", "rays", "sample")
    parts_sum = sum(by_name[p]["median_s"] for p in parts)
    breakdown = {p: by_name[p]["median_s"] / by_name["ours"]["median_s"] for p in parts}
    breakdown["rest (cameras, batching, other)"] = 1 - parts_sum / by_name["ours"]["median_s"]
    u8_headline = []
    for ours_name, ref_name in (("rgb_u8", "rgb_f32"), ("rgb_u8_hwc", "rgb_f32"),
                                ("ours_u8", "ours"), ("rgb_u8_per_sample", "rgb_f32_per_sample")):
        if ours_name in by_name:
            ratio = by_name[ours_name]["images_per_s"] / by_name[ref_name]["images_per_s"]
            u8_headline.append({"uint8": ours_name, "float32": ref_name,
                                "throughput_ratio": ratio,
                                "min_ratio": by_name[ref_name]["min_s"]
                                / by_name[ours_name]["min_s"],
                                "target": U8_TARGET, "meets_target": ratio >= U8_TARGET})
    headline = None
    if "peer" in by_name:
        ratio = by_name["ours"]["images_per_s"] / by_name["peer"]["images_per_s"]
        headline = {"ours_images_per_s": by_name["ours"]["images_per_s"],
                    "peer_images_per_s": by_name["peer"]["images_per_s"],
                    "throughput_ratio_ours_over_peer": ratio, "target": TARGET,
                    "meets_target": ratio >= TARGET}

    return {
        **run_record("augment", device, args.threads, cv2),
        "setup": {"batch": batch, "heap": args.heap, "face_size": face,
                  "image_size": [size, size],
                  "mode": "fisheye", "model": "equidistant", "fov_deg": [160.0, 200.0],
                  "roll_deg": [-25.0, 25.0], "pitch_deg": [-10.0, 10.0],
                  "yaw_deg": [-180.0, 180.0], "rgb": "float32, 3 channels",
                  "labels": "uint8 (ours returns int64)", "pad_ours": pad,
                  "border_ours": projs[0].border, "samples_per_chunk_ours": step,
                  "pad_peer": 1, "border_peer": "edge replication",
                  "peer_float": "float32 numpy maps",
                  "rgb_u8": "uint8 round(255 x) of the float32 cube, same module settings and "
                            "seed as ours (same draws per call)"},
        "repeats": args.repeats,
        "warmup": args.warmup,
        "seed": SEED,
        "peer_agreement": agreement,
        "u8_agreement": u8_agreement,
        "timer": ("time.perf_counter around single calls, after warm-up, all rows round-robin; "
                  "median and IQR; an untimed 10 ms pause before every timed call "
                  "(common.SETTLE_S)"),
        "timestamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "loadavg_start": load_start,
        "loadavg_end": loadavg(),
        "rows": rows,
        "breakdown_fraction_of_ours": breakdown,
        "headline": headline,
        "u8_headline": u8_headline,
    }


def markdown(result: dict) -> str:
    def ms(s: float) -> str:
        return f"{1e3 * s:.1f}"

    s = result["setup"]
    lines = [f"augment: B = {s['batch']}, 6 x {s['face_size']} -> {s['image_size'][0]} x "
             f"{s['image_size'][1]} fisheye (random camera + attitude per sample), RGB + labels, "
             f"{result['threads']} threads, heap {s.get('heap', 'default')}, commit "
             f"{result['commit'][:12]}"
             f"{' (dirty)' if result['dirty'] else ''}", "",
             "| row | kind | median ms / batch | IQR ms | min ms | images/s | page faults |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        faults = "" if r.get("page_faults") is None else f"{r['page_faults']:.0f}"
        lines.append(f"| {r['name']} | {r['kind']} | {ms(r['median_s'])} | {ms(r['iqr_s'])} | "
                     f"{ms(r['min_s'])} | {r['images_per_s']:.1f} | {faults} |")
    lines += ["", "where our time goes (part medians / ours median): " + ", ".join(
        f"{k} {100 * v:.0f}%" for k, v in result["breakdown_fraction_of_ours"].items())]
    h = result["headline"]
    if h is not None:
        lines.append(f"throughput ours / peer: {h['throughput_ratio_ours_over_peer']:.2f}x "
                     f"({h['ours_images_per_s']:.1f} vs {h['peer_images_per_s']:.1f} images/s; "
                     f"target >= {h['target']:.0f}x: {'ok' if h['meets_target'] else 'MISSED'})")
    for q in result["u8_headline"]:
        lines.append(f"throughput {q['uint8']} / {q['float32']}: {q['throughput_ratio']:.2f}x "
                     f"(fastest calls {q['min_ratio']:.2f}x; target >= {q['target']:.1f}x: "
                     f"{'ok' if q['meets_target'] else 'MISSED'})")
    if result["u8_agreement"]:
        lines.append("uint8 agreement (same draws, levels): " + ", ".join(
            f"{k} {v:.4g}" for k, v in result["u8_agreement"].items()))
    if result["peer_agreement"]:
        lines.append("peer agreement (same draws): " + ", ".join(
            f"{k} {v:.4g}" for k, v in result["peer_agreement"].items()))
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=None, help="batch size (16; 4 quick)")
    parser.add_argument("--face", type=int, default=None, help="cube face size F (256; 64 quick)")
    parser.add_argument("--size", type=int, default=None,
                        help="output image side S (512; 128 quick)")
    parser.add_argument("--threads", type=int, default=2,
                        help="torch and OpenCV thread count (default 2)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed calls per row (default 15; 3 with --quick)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed calls before timing (default 2; 1 with --quick)")
    parser.add_argument("--quick", action="store_true",
                        help="B = 4, 6 x 64 -> 128 x 128, few repeats: a smoke run (seconds)")
    parser.add_argument("--heap", choices=HEAP_MODES, default="default",
                        help="where the outputs' memory comes from (common.set_heap): glibc's "
                             "own choice (default), memory the heap kept (warm: no page "
                             "faults), or a fresh mapping per output (fresh)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON output (default benchmarks/results/augment.json; "
                             "augment_<heap>.json with --heap warm or fresh; under "
                             "results/quick/ with --quick)")
    args = parser.parse_args(argv)
    defaults = {"batch": (16, 4), "face": (256, 64), "size": (512, 128), "repeats": (15, 3),
                "warmup": (2, 1)}
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    for name in ("batch", "face", "size", "threads", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.out is None:
        suffix = "" if args.heap == "default" else f"_{args.heap}"
        args.out = results_path(f"augment{suffix}.json", quick=args.quick)   # quick: quick/
    if args.warmup < 0:
        parser.error("--warmup must be >= 0")
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
