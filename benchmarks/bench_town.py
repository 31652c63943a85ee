"""The built-in town on Embree: frames per second against image size, and the cubemap path's
error against face size (issue 20).

Speed (``--sizes``, default 256 512 1024 2048): per image size, the rig's four cameras (stereo
fisheye, stereo catadioptric) of ``generate``'s default configuration at that size, three rows
timed round-robin over ``--repeats`` frames after a warm-up frame (``benchmarks/common.py``'s
conventions: medians, IQR, the load before and after):

* ``frame``: ``FrameRenderer.render``, what ``generate`` does per frame: each camera's cubemap
  (the texels it reads, traced and shaded), the layer, the PNG/EXR files written;
* ``cubemaps``: the four cubemaps alone (``Town.render_cubemap`` of the same texels);
* ``direct``: the peer, the ground truth: every valid pixel's own ray traced and shaded
  (``Town.render_rays``), no cube, no files.

Each row also records the process's CPU time per frame (all threads): on a shared machine the
wall time depends on the other loads, the CPU time much less (on 2 free cores the wall time
would be about half of it, the tracing and shading running on both).

Frames differ from repeat to repeat (the ride goes on), so each row sees the same frames.
Face sizes are ``generate``'s (``required_face_size``, capped at ``max_face_size`` 1024: at
2048 pixels the faces stay at 1024 and the images are upsampled from them).

Accuracy (``--faces``, multiples of the default face size, at ``--accuracy-size`` pixels,
default 256): per camera kind, over ``--accuracy-frames`` frames of the default ride, the
cubemap path (``render_cubemap`` + ``OmniProjection``) against the direct trace of the same
camera at the same pose: PSNR of the 8-bit RGB over the valid area, the same away from edges
(pixels whose 3 x 3 neighbourhood in the direct image holds one label and ranges within 5 %),
label agreement over the valid area, and an anti-aliased PSNR: the layer averaging 2 x 2 rays a
pixel (``supersample=2``) against the mean of 4 x 4 traced rays a pixel (both estimate the
pixel's area, where a point sample of a hard edge or texture cell is a coin toss).

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

import torch
import torch.nn.functional as nnf

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import begin_run, loadavg, measure, run_record, write_json_atomic  # noqa: E402
from omniscape_torch.data.generate import DatasetConfig, FrameRenderer  # noqa: E402
from omniscape_torch.render.layer import OmniProjection  # noqa: E402


def _camera_rays(layer: OmniProjection, rotation: torch.Tensor, supersample: bool = False):
    """Unit world rays of a layer's pixel centres (or sub-pixel samples) and their validity."""
    rays_s, valid_s, rays_c, valid_c = layer.camera_rays()
    rays, valid = (rays_s, valid_s) if supersample else (rays_c, valid_c)
    d = rays.reshape(-1, 3).double() @ rotation.double().T
    return (d / d.norm(dim=-1, keepdim=True)).float().reshape(rays.shape), valid


def speed(args) -> list[dict]:
    rows = []
    for size in args.sizes:
        config = DatasetConfig(frames=args.repeats + 1, image_size=(size, size))
        renderer = FrameRenderer(config)
        plan, town = renderer.plan, renderer.town
        out = Path(tempfile.mkdtemp(prefix="bench_town_"))
        layers = {n: renderer._layer(n, c["camera"], c["face_size"])
                  for n, c in plan.cameras.items()}
        frame = {"frame": 0, "cubemaps": 0, "direct": 0}

        def render_frame():
            renderer.render(out, frame["frame"])
            frame["frame"] += 1

        def cubemaps():
            k = frame["cubemaps"]
            t = float(plan.frames["time"][k])
            for name, c in plan.cameras.items():
                town.render_cubemap(plan.centre(name, k).float(), None, c["face_size"],
                                    faces=plan.faces(name, k), texels=plan.texels(name, k),
                                    t=t, out=renderer._cube_buffers(c["face_size"]))
            frame["cubemaps"] += 1

        def direct():
            k = frame["direct"]
            t = float(plan.frames["time"][k])
            for name in plan.cameras:
                d, valid = _camera_rays(layers[name], plan.rotation(name, k).float())
                town.render_rays(plan.centre(name, k).float(), d[valid], t=t)
            frame["direct"] += 1

        cpu: dict[str, list[float]] = {"frame": [], "cubemaps": [], "direct": []}

        def with_cpu(name, fn):
            """``fn``, its process CPU time (every thread's) recorded: the figure a busy
            machine inflates least (2 free cores would take about half of it as wall time)."""
            def timed():
                start = time.process_time()
                fn()
                cpu[name].append(time.process_time() - start)
            return timed

        stats = measure([with_cpu("frame", render_frame), with_cpu("cubemaps", cubemaps),
                         with_cpu("direct", direct)], args.repeats, 1, progress=True)
        shutil.rmtree(out, ignore_errors=True)
        texels = sum(int(plan.texels(n, 0).sum()) for n in plan.cameras)
        pixels = sum(int(layers[n].camera_rays()[3].sum()) for n in plan.cameras)
        for name, s in zip(("frame", "cubemaps", "direct"), stats):
            timed_cpu = cpu[name][1:]   # the warm-up call first
            rows.append({"name": name, "image_size": size,
                         "face_sizes": {n: c["face_size"] for n, c in plan.cameras.items()},
                         "texels": texels, "valid_pixels": pixels,
                         "frames_per_s": 1.0 / s["median_s"],
                         "cpu_median_s": statistics.median(timed_cpu),
                         "cpu_s": timed_cpu, **s})
            print(f"{size:5d} px  {name:9s} {s['median_s']:7.2f} s/frame (IQR "
                  f"{s['iqr_s']:.2f}, CPU {rows[-1]['cpu_median_s']:.2f} s)  "
                  f"{1 / s['median_s']:6.2f} frames/s", flush=True)
    return rows


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
            probe = OmniProjection(camera, default, supersample=4, fused_grid=False)
            d, valid = _camera_rays(probe, rot)
            direct = town.render_rays(pos, d, t=t)
            ds, vs = _camera_rays(probe, rot, supersample=True)
            fine = town.render_rays(pos, ds, t=t)["rgb"]
            h, w = valid.shape
            vs = vs.float().reshape(h, 4, w, 4)
            area = (fine.reshape(h, 4, w, 4, 3) * vs[..., None]).sum((1, 3)) / \
                vs.sum((1, 3)).clamp(min=1)[..., None]
            truth[k] = (direct, valid, _edges(direct["labels"], direct["range"]), area)
        for scale in args.faces:
            F = max(8, round(default * scale))
            layer = OmniProjection(camera, F, fused_grid=False)
            layer2 = OmniProjection(camera, F, supersample=2, fused_grid=False)
            acc = {"rgb": [], "clean": [], "aa": [], "agree": 0, "valid": 0}
            for k in frames:
                rot, pos = plan.rotation(name, k).float(), plan.centre(name, k).float()
                t = float(plan.frames["time"][k])
                direct, valid, edge, area = truth[k]
                cube = town.render_cubemap(pos, None, F, t=t)
                with torch.no_grad():
                    res = layer.render(rgb=cube["rgb"], depth=cube["depth"],
                                       labels=cube["labels"], rotation=rot)
                    aa = layer2.render(rgb=cube["rgb"], rotation=rot)["rgb"]
                rgb = res["rgb"][0].permute(1, 2, 0)
                acc["rgb"].append((rgb[valid], direct["rgb"][valid]))
                acc["clean"].append((rgb[valid & ~edge], direct["rgb"][valid & ~edge]))
                acc["aa"].append((aa[0].permute(1, 2, 0)[valid], area[valid]))
                acc["agree"] += int((res["labels"][0] == direct["labels"])[valid].sum())
                acc["valid"] += int(valid.sum())
            row = {"camera": name, "image_size": size, "face_size": F,
                   "default_face_size": default, "frames": frames}
            for key in ("rgb", "clean", "aa"):
                a = torch.cat([p[0] for p in acc[key]])
                b = torch.cat([p[1] for p in acc[key]])
                row[{"rgb": "psnr_db", "clean": "psnr_away_from_edges_db",
                     "aa": "psnr_antialiased_db"}[key]] = _psnr(a, b)
            row["label_agreement"] = acc["agree"] / acc["valid"]
            row["edge_share"] = float(torch.cat([(e & v)[v].float() for _, v, e, _ in
                                                 truth.values()]).mean())
            rows.append(row)
            print(f"{name:18s} F={F:5d}{' (default)' if F == default else '':10s} "
                  f"PSNR {row['psnr_db']:5.2f} dB, away from edges "
                  f"{row['psnr_away_from_edges_db']:5.2f}, anti-aliased "
                  f"{row['psnr_antialiased_db']:5.2f}; labels {row['label_agreement']:.2%}",
                  flush=True)
    return rows


def figure(speed_rows: list[dict], accuracy_rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ax = axes[0]
    for name, style in (("frame", "o-"), ("cubemaps", "s--"), ("direct", "^:")):
        r = [x for x in speed_rows if x["name"] == name]
        if r:
            ax.plot([x["image_size"] for x in r], [x["frames_per_s"] for x in r], style,
                    label={"frame": "generate frame (4 cameras, files)",
                           "cubemaps": "cubemaps only", "direct": "direct trace (peer)"}[name])
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
            r = [x for x in accuracy_rows if x["camera"] == cam]
            if not r:
                continue
            fs = [x["face_size"] for x in r]
            if key == "psnr":
                ax.plot(fs, [x["psnr_db"] for x in r], "o-", color=colour,
                        label=f"{cam.split('_')[0]}: point samples")
                ax.plot(fs, [x["psnr_antialiased_db"] for x in r], "s--", color=colour,
                        label=f"{cam.split('_')[0]}: anti-aliased")
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
    ap.add_argument("--accuracy-size", type=int, default=256)
    ap.add_argument("--accuracy-frames", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--quick", action="store_true", help="256 and 512, 2 repeats, 3 faces")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "town.json")
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.repeats, args.faces, args.accuracy_frames = [256, 512], 2, \
            [0.5, 1.0, 2.0], 1
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
