"""The built-in town on Embree: frames per second against image size, and the cubemap path's
error against face size (issue 20).

Speed (``--sizes``, default 256 512 1024 2048): per image size, the rig's four cameras (stereo
fisheye, stereo catadioptric) of ``generate``'s default configuration at that size, with each
``--antialias`` value (default 1 2 3), rows timed round-robin over ``--repeats`` frames after a
warm-up frame (``benchmarks/common.py``'s conventions: medians, IQR, the load before and after):

* ``frame`` (per antialias): ``FrameRenderer.render``, what ``generate`` does per frame: each
  camera's cubemap (the texels it reads, traced and shaded), the layer, the PNG/EXR files
  written;
* ``cubemaps`` (per antialias): the four cubemaps alone (``Town.render_cubemap`` of the same
  texels, in the frame's weather: the share of texels anti-aliasing supersamples depends on it);
* ``direct``: the peer, the ground truth: every valid pixel's own ray traced and shaded
  (``Town.render_rays``), no cube, no files;
* ``embree floor`` (antialias 1, frame 1): the trace-only floor of the cubemaps, Embree's own
  calls on the same rays (`embree_floor`: every closest-hit, back-face and shadow query of the
  frame's cubemaps, replayed with nothing else).

Each row also records the process's CPU time per frame (all threads): on a shared machine the
wall time depends on the other loads, the CPU time much less (on 2 free cores the wall time
would be about half of it, the tracing and shading running on both).

Frames differ from repeat to repeat (the ride goes on), so each row sees the same frames.
Face sizes are ``generate``'s (``required_face_size``, capped at ``max_face_size`` 1024: at
2048 pixels the faces stay at 1024 and the images are upsampled from them).

Accuracy (``--faces``, multiples of the default face size, at ``--accuracy-size`` pixels,
default 256): per camera kind, over ``--accuracy-frames`` frames of the default ride, the
cubemap path (``render_cubemap`` + ``OmniProjection``) against the direct trace of the same
camera at the same pose, per ``--antialias`` value of the cube (``render_cubemap(antialias=k)``:
the texels on an edge the mean of ``k x k`` rays): PSNR of the 8-bit RGB over the valid area,
the same away from edges (pixels whose 3 x 3 neighbourhood in the direct image holds one label
and ranges within 5 %), label agreement over the valid area, the share of the texels in the
camera's cone that ``antialias > 1`` supersamples, and an anti-aliased PSNR: the layer averaging
2 x 2 rays a pixel (``supersample=2``, what ``generate`` does with ``antialias > 1``) against the
mean of 8 x 8 traced rays a pixel (``REFERENCE_RAYS``; both estimate the pixel's area, where a
point sample of a hard edge or texture cell is a coin toss).

Usage::

    python benchmarks/bench_town.py                  # both parts (about 10 min on 2 cores)
    python benchmarks/bench_town.py --quick          # 256 and 512, fewer frames and faces

Results: ``benchmarks/results/town.json`` and ``town.png`` (``--out``).
"""

from __future__ import annotations

import argparse
import math
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as nnf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import (begin_run, loadavg, measure, results_path, run_record,  # noqa: E402
                    write_json_atomic)
from omniscape_torch.data.generate import (DatasetConfig, FrameRenderer,  # noqa: E402
                                           _frame_weather, camera_cone, cone_texels)
from omniscape_torch.render.layer import OmniProjection  # noqa: E402
from omniscape_torch.scenes.town import edge_texels  # noqa: E402


def _camera_rays(layer: OmniProjection, rotation: torch.Tensor, supersample: bool = False):
    """Unit world rays of a layer's pixel centres (or sub-pixel samples) and their validity."""
    rays_s, valid_s, rays_c, valid_c = layer.camera_rays()
    rays, valid = (rays_s, valid_s) if supersample else (rays_c, valid_c)
    d = rays.reshape(-1, 3).double() @ rotation.double().T
    return (d / d.norm(dim=-1, keepdim=True)).float().reshape(rays.shape), valid


def speed(args) -> list[dict]:
    rows = []
    for size in args.sizes:
        # one renderer per antialias (its layers and buffers); the same frames for every row
        renderers = {aa: FrameRenderer(DatasetConfig(frames=args.repeats + 1,
                                                     image_size=(size, size), antialias=aa))
                     for aa in args.antialias}
        renderer = renderers[args.antialias[0]]
        plan, town = renderer.plan, renderer.town
        out = Path(tempfile.mkdtemp(prefix="bench_town_"))
        layers = {n: renderer._layer(n, c["camera"], c["face_size"])
                  for n, c in plan.cameras.items()}
        keys = [(name, aa) for aa in args.antialias for name in ("frame", "cubemaps")] + \
            [("direct", None)]
        frame = {key: 0 for key in keys}

        def render_frame(aa):
            def run():
                renderers[aa].render(out / f"aa{aa}", frame["frame", aa])
                frame["frame", aa] += 1
            return run

        def cubemaps(aa):
            def run():
                r = renderers[aa]
                for name in plan.cameras:
                    r.cubemap(name, frame["cubemaps", aa])
                frame["cubemaps", aa] += 1
            return run

        def direct():
            k = frame["direct", None]
            t = float(plan.frames["time"][k])
            for name in plan.cameras:
                d, valid = _camera_rays(layers[name], plan.rotation(name, k).float())
                town.render_rays(plan.centre(name, k).float(), d[valid], t=t,
                                 weather=_frame_weather(renderer.config, k))
            frame["direct", None] += 1

        cpu: dict[tuple, list[float]] = {key: [] for key in keys}

        def with_cpu(key, fn):
            """``fn``, its process CPU time (every thread's) recorded: the figure a busy
            machine inflates least (2 free cores would take about half of it as wall time)."""
            def timed():
                start = time.process_time()
                fn()
                cpu[key].append(time.process_time() - start)
            return timed

        fns = {"frame": render_frame, "cubemaps": cubemaps}
        stats = measure([with_cpu(key, fns[key[0]](key[1]) if key[1] is not None else direct)
                         for key in keys], args.repeats, 1, progress=True)
        shutil.rmtree(out, ignore_errors=True)
        texels = sum(int(renderer.texels(n, 0).sum()) for n in plan.cameras)
        pixels = sum(int(layers[n].camera_rays()[3].sum()) for n in plan.cameras)
        for (name, aa), s in zip(keys, stats):
            timed_cpu = cpu[name, aa][1:]   # the warm-up call first
            rows.append({"name": name, "antialias": aa, "image_size": size,
                         "face_sizes": {n: c["face_size"] for n, c in plan.cameras.items()},
                         "texels": texels, "valid_pixels": pixels,
                         "frames_per_s": 1.0 / s["median_s"],
                         "cpu_median_s": statistics.median(timed_cpu),
                         "cpu_s": timed_cpu, **s})
            label = name if aa is None else f"{name} aa={aa}"
            print(f"{size:5d} px  {label:14s} {s['median_s']:7.2f} s/frame (IQR "
                  f"{s['iqr_s']:.2f}, CPU {rows[-1]['cpu_median_s']:.2f} s)  "
                  f"{1 / s['median_s']:6.2f} frames/s", flush=True)
        rows.append(embree_floor(renderer, 1, args.repeats, size))
    return rows


def embree_floor(renderer: FrameRenderer, k: int, repeats: int, size: int) -> dict:
    """The trace-only floor of frame ``k``'s cubemaps: every Embree query the town makes for
    them (closest hits, the back-face passes, the shadow rays; recorded during one untimed
    ``cubemaps`` pass), replayed as Embree's own calls (``embreex``'s ``run``) on the town's
    threads, in the same batches, with nothing else: no shading, no gathers, no files. The
    median of ``repeats`` replays, wall and process CPU time."""
    from concurrent.futures import ThreadPoolExecutor

    plan, town = renderer.plan, renderer.town
    scene = town.scene(float(plan.frames["time"][k]))
    calls = []

    def recorder(name):
        method = getattr(type(scene), name)

        def record(o, d, tfar=1e37):
            n = d.shape[0]
            dists = np.array(np.broadcast_to(np.float32(tfar), (n,)) if np.ndim(tfar) == 0
                             else tfar, np.float32)
            calls.append((name, np.ascontiguousarray(np.broadcast_to(o, (n, 3)), np.float32),
                          np.ascontiguousarray(d, np.float32), dists))
            return method(scene, o, d, tfar)
        return record

    scene.intersect, scene.occluded = recorder("intersect"), recorder("occluded")
    try:
        for name in plan.cameras:
            renderer.cubemap(name, k)
    finally:
        del scene.intersect, scene.occluded

    def replay(call):
        name, o, d, dists = call
        if name == "intersect":
            scene._scene.run(o, d, dists=dists.copy(), output=True)
        else:
            scene._scene.run(o, d, dists=dists.copy(), query="OCCLUDED")

    walls, cpus = [], []
    threads = town.threads or torch.get_num_threads()
    for _ in range(repeats + 1):   # the first: a warm-up
        start, cpu = time.perf_counter(), time.process_time()
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(replay, calls))
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
    primary = sum(c[2].shape[0] for c in calls if c[0] == "intersect")
    shadow = sum(c[2].shape[0] for c in calls if c[0] == "occluded")
    row = {"name": "embree floor", "antialias": 1, "image_size": size, "frame": k,
           "primary_rays": primary, "shadow_rays": shadow, "queries": len(calls),
           "median_s": statistics.median(walls[1:]), "times_s": walls[1:],
           "cpu_median_s": statistics.median(cpus[1:]), "cpu_s": cpus[1:]}
    row["frames_per_s"] = 1.0 / row["median_s"]
    print(f"{size:5d} px  {'embree floor':14s} {row['median_s']:7.2f} s/frame (CPU "
          f"{row['cpu_median_s']:.2f} s; {primary / 1e6:.2f} M closest-hit, {shadow / 1e6:.2f} M "
          "shadow rays)", flush=True)
    return row


def _edges(labels: torch.Tensor, rng: torch.Tensor) -> torch.Tensor:
    def pool(x):
        x = nnf.pad(x[None, None].float(), (1, 1, 1, 1), mode="replicate")
        return nnf.max_pool2d(x, 3, 1)[0, 0], -nnf.max_pool2d(-x, 3, 1)[0, 0]
    lmax, lmin = pool(labels)
    rmax, rmin = pool(rng)
    return (lmax != lmin) | (rmax - rmin > 0.05 * rmin)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR (dB) of two ``(N, 3)`` colour sets in [0, 1], quantised to 8 bits as written."""
    a, b = (a * 255).round(), (b * 255).round()
    mse = float(((a - b) ** 2).mean())
    return 10 * math.log10(255 ** 2 / max(mse, 1e-12))


#: Rays a pixel (per side) of the anti-aliased reference: the mean of 8 x 8 traced rays. 4 x 4
#: rays lie 44.6-46.0 dB from it (default faces, 256 x 256, frames 0 and 2), a sampling noise
#: that takes 1.1-1.3 dB off an anti-aliased cube's 40-42 dB.
REFERENCE_RAYS = 8


def _area_mean(town, layer: OmniProjection, rotation, position, t: float) -> torch.Tensor:
    """``(H, W, 3)`` mean RGB of ``layer``'s valid sub-pixel rays (its ``supersample``) per
    pixel: the pixel's area, traced."""
    s = layer.supersample
    ds, vs = _camera_rays(layer, rotation, supersample=True)
    fine = town.render_rays(position, ds, t=t)["rgb"]
    h, w = ds.shape[0] // s, ds.shape[1] // s
    vs = vs.float().reshape(h, s, w, s)
    return (fine.reshape(h, s, w, s, 3) * vs[..., None]).sum((1, 3)) / \
        vs.sum((1, 3)).clamp(min=1)[..., None]


def accuracy(args) -> list[dict]:
    size = args.accuracy_size
    config = DatasetConfig(frames=max(args.accuracy_frames * 2, 2), image_size=(size, size))
    renderer = FrameRenderer(config)
    plan, town = renderer.plan, renderer.town
    frames = list(range(0, 2 * args.accuracy_frames, 2))
    rows = []
    for name in ("fisheye_left", "catadioptric_left"):
        camera, default = plan.cameras[name]["camera"], plan.cameras[name]["face_size"]
        truth = {}
        for k in frames:
            rot, pos = plan.rotation(name, k).float(), plan.centre(name, k).float()
            t = float(plan.frames["time"][k])
            probe = OmniProjection(camera, default, supersample=REFERENCE_RAYS, fused_grid=False)
            d, valid = _camera_rays(probe, rot)
            direct = town.render_rays(pos, d, t=t)
            truth[k] = (direct, valid, _edges(direct["labels"], direct["range"]),
                        _area_mean(town, probe, rot, pos, t))
        for scale in args.faces:
            F = max(8, round(default * scale))
            layer = OmniProjection(camera, F, fused_grid=False)
            layer2 = OmniProjection(camera, F, supersample=2, fused_grid=False)
            centres: dict[int, dict] = {}
            for aa in args.antialias:
                acc = {"rgb": [], "clean": [], "aa": [], "agree": 0, "valid": 0,
                       "edge_texels": 0, "texels": 0}
                for k in frames:
                    rot, pos = plan.rotation(name, k).float(), plan.centre(name, k).float()
                    t = float(plan.frames["time"][k])
                    direct, valid, edge, area = truth[k]
                    if k not in centres:   # the cube of centre rays (antialias 1)
                        centres[k] = town.render_cubemap(pos, None, F, t=t)
                    cube = centres[k] if aa == 1 else \
                        town.render_cubemap(pos, None, F, t=t, antialias=aa)
                    # the texels the camera reads, and those antialias > 1 supersamples: the
                    # edges of the centre rays' cube
                    seen = cone_texels(F, plan.rotation(name, k)[:, 2], camera_cone(camera, F))
                    acc["texels"] += int(seen.sum())
                    c1 = centres[k]
                    acc["edge_texels"] += sum(int((edge_texels(
                        c1["labels"][0, f], c1["range"][0, f], c1["rgb"][0, f]) &
                        seen[f]).sum()) for f in range(6)) if aa > 1 else 0
                    with torch.no_grad():
                        res = layer.render(rgb=cube["rgb"], depth=cube["depth"],
                                           labels=cube["labels"], rotation=rot)
                        aa_rgb = layer2.render(rgb=cube["rgb"], rotation=rot)["rgb"]
                    rgb = res["rgb"][0].permute(1, 2, 0)
                    acc["rgb"].append((rgb[valid], direct["rgb"][valid]))
                    acc["clean"].append((rgb[valid & ~edge], direct["rgb"][valid & ~edge]))
                    acc["aa"].append((aa_rgb[0].permute(1, 2, 0)[valid], area[valid]))
                    acc["agree"] += int((res["labels"][0] == direct["labels"])[valid].sum())
                    acc["valid"] += int(valid.sum())
                row = {"camera": name, "image_size": size, "face_size": F,
                       "default_face_size": default, "antialias": aa, "frames": frames,
                       "reference_rays": REFERENCE_RAYS ** 2}
                for key in ("rgb", "clean", "aa"):
                    a = torch.cat([p[0] for p in acc[key]])
                    b = torch.cat([p[1] for p in acc[key]])
                    row[{"rgb": "psnr_db", "clean": "psnr_away_from_edges_db",
                         "aa": "psnr_antialiased_db"}[key]] = _psnr(a, b)
                row["label_agreement"] = acc["agree"] / acc["valid"]
                row["edge_share"] = float(torch.cat([(e & v)[v].float() for _, v, e, _ in
                                                     truth.values()]).mean())
                # edge_texels of the centre rays' cube (the same labels, ranges; the colours of
                # the texels not supersampled), among the texels in the camera's cone
                row["supersampled_share"] = acc["edge_texels"] / acc["texels"]
                rows.append(row)
                print(f"{name:18s} F={F:5d}{' (default)' if F == default else '':10s} aa={aa} "
                      f"PSNR {row['psnr_db']:5.2f} dB, away from edges "
                      f"{row['psnr_away_from_edges_db']:5.2f}, anti-aliased "
                      f"{row['psnr_antialiased_db']:5.2f}; labels {row['label_agreement']:.2%}"
                      f"; supersampled {row['supersampled_share']:.1%}", flush=True)
    return rows


def figure(speed_rows: list[dict], accuracy_rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    aas = sorted({x["antialias"] for x in speed_rows if x["antialias"] is not None})
    for name, style in (("frame", "o-"), ("cubemaps", "s--"), ("direct", "^:")):
        for i, aa in enumerate(aas if name != "direct" else [None]):
            r = [x for x in speed_rows if x["name"] == name and x["antialias"] == aa]
            if r:
                label = {"frame": "generate frame (4 cameras, files)",
                         "cubemaps": "cubemaps only", "direct": "direct trace (peer)"}[name]
                ax.plot([x["image_size"] for x in r], [x["frames_per_s"] for x in r], style,
                        color=f"C{i}" if aa is not None else "k",
                        label=label if aa is None else f"{label}, antialias {aa}")
    floor = [x for x in speed_rows if x["name"] == "embree floor"]
    if floor:
        ax.plot([x["image_size"] for x in floor], [1.0 / x["median_s"] for x in floor], "x-.",
                color="0.45", label="Embree floor (the frame's queries alone), antialias 1")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("image size (pixels, square)")
    ax.set_ylabel("frames / s")
    ax.set_title("speed, 2 CPU cores")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    for i, key in enumerate(("psnr", "label_agreement")):
        ax = axes[1 + i]
        for cam, colour in (("fisheye_left", "C0"), ("catadioptric_left", "C1")):
            every = [x for x in accuracy_rows if x["camera"] == cam]
            if not every:
                continue
            first = min(x["antialias"] for x in every)   # point samples: the first antialias
            r = [x for x in every if x["antialias"] == first]
            fs = [x["face_size"] for x in r]
            if key == "psnr":
                ax.plot(fs, [x["psnr_db"] for x in r], "o-", color=colour,
                        label=f"{cam.split('_')[0]}: point samples, antialias {first}")
                for aa, style in zip(sorted({x["antialias"] for x in every}),
                                     ("s--", "d-.", "v:", "x--")):
                    ra = [x for x in every if x["antialias"] == aa]
                    ax.plot([x["face_size"] for x in ra],
                            [x["psnr_antialiased_db"] for x in ra], style, color=colour,
                            alpha=0.5 + 0.5 / aa,
                            label=f"{cam.split('_')[0]}: antialias {aa}, 2 x 2 rays a pixel")
            else:
                ax.plot(fs, [100 * x["label_agreement"] for x in r], "o-", color=colour,
                        label=cam.split("_")[0])
            ax.axvline(r[0]["default_face_size"], color=colour, alpha=0.3)
        ax.set_xscale("log", base=2)
        ax.set_xlabel(f"face size (image {accuracy_rows[0]['image_size']} px; lines: "
                      "default)" if accuracy_rows else "face size")
        ax.set_ylabel("PSNR (dB) vs direct trace" if key == "psnr" else
                      "label agreement (%) in the valid area")
        ax.axhline(40 if key == "psnr" else 99, color="k", lw=0.8, ls=":")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--faces", type=float, nargs="+",
                    default=[0.5, 0.75, 1.0, 1.5, 2.0, 3.0],
                    help="face sizes, as multiples of each camera's default")
    ap.add_argument("--antialias", type=int, nargs="+", default=[1, 2, 3],
                    help="Town.render_cubemap's antialias values: a frame and a cubemaps row "
                         "each in speed, a row each per face size in accuracy (default 1 2 3)")
    ap.add_argument("--accuracy-size", type=int, default=256)
    ap.add_argument("--accuracy-frames", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--quick", action="store_true", help="256 and 512, 2 repeats, 3 faces, "
                    "antialias 1 and 2")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("town.json", quick=args.quick)
    if args.quick:
        args.sizes, args.repeats, args.faces, args.accuracy_frames, args.antialias = \
            [256, 512], 2, [0.5, 1.0, 2.0], 1, [1, 2]
    load = begin_run(args.threads)
    record = {**run_record("town", torch.device("cpu"), args.threads), "load_start": load,
              "sizes": args.sizes, "repeats": args.repeats}
    t0 = time.perf_counter()
    record["speed"] = [] if args.skip_speed else speed(args)
    record["accuracy"] = [] if args.skip_accuracy else accuracy(args)
    record["load_end"] = loadavg()
    record["seconds"] = time.perf_counter() - t0
    write_json_atomic(record, args.out)
    figure(record["speed"], record["accuracy"], args.out.with_suffix(".png"))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}; load {load} -> "
          f"{record['load_end']}")
    return record


if __name__ == "__main__":
    main()
