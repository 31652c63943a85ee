"""PNG writing and reading: Pillow against OpenCV, the measurement behind the package's choice
of image library (issue 32: ``pip install omniscape_torch`` with no extras writes its PNGs).

Two parts:

* size: each peer's wheel for this platform (``pip download --no-deps``, into a temporary
  folder; skipped with ``--no-download`` or offline) and its installed size (the wheel
  unpacked: what ``pip install`` puts in ``site-packages``);
* speed at 1024 x 1024 (``--size``): encode to PNG bytes and decode them back, for
  - ``rgb``: a real photo, ``../shared/data/ocamcalib_real/img0.jpg`` (1600 x 1600 fisheye),
    resampled to the size (nearest, by index arithmetic: the same pixels for every peer);
  - ``labels``: 1-channel class ids of a real CARLA frame,
    ``../shared/data/omniscape_equirect/carla_left_semantic_palette_quantized.png`` mapped to the
    nearest palette colour (``palette_to_labels``), resampled the same way;
  - ``uint16``: 1-channel 16-bit, the photo's luminance times 257 (a 16-bit PNG as
    ``write_image`` writes one).
  Peers: ``pillow`` at ``compress_level`` 1 with zlib's Z_RLE strategy (``compress_type=3``:
  OpenCV's settings, what ``omniscape_torch.io.write_image`` uses), at level 1 with the default
  strategy, and at level 6 (Pillow's default); ``cv2`` with its defaults (level 1, Z_RLE). Each row is checked to
  decode to the very pixels encoded; the bytes written are reported too.

A peer that is not installed is skipped (its rows say why). Timing: ``--warmup`` untimed then
``--repeats`` timed calls, round-robin over every peer's encode and decode of one image
(``benchmarks/common.py``: a change of load hits them alike), median and IQR; one thread
(``cv2.setNumThreads(1)``; PNG coding is single-threaded in both).

Usage::

    python benchmarks/bench_png.py                  # 1024 x 1024, 15 repeats, wheel sizes
    python benchmarks/bench_png.py --quick          # 256 x 256, 3 repeats, no download

Results: a table on stdout and JSON, ``benchmarks/results/png.json`` (``--quick``:
``benchmarks/results/quick/png.json``; ``--out`` to choose).
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import (ROOT, begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_main, run_record)

DATA = ROOT.parent / "shared" / "data"
PHOTO = DATA / "ocamcalib_real" / "img0.jpg"
SEMANTIC = DATA / "omniscape_equirect" / "carla_left_semantic_palette_quantized.png"

#: zlib's run-length strategy (OpenCV's default for PNG; Pillow's ``compress_type``).
Z_RLE = 3

#: pip distribution of each peer (the headless wheel: the one a library would require).
WHEELS = {"pillow": "pillow", "cv2": "opencv-python-headless"}


def _peers() -> dict:
    """The importable peers: ``{"pillow": PIL.Image, "cv2": cv2}`` (the missing left out) and
    why each missing one is."""
    found, missing = {}, {}
    try:
        from PIL import Image
        found["pillow"] = Image
    except ImportError as err:
        missing["pillow"] = str(err)
    try:
        import cv2
        found["cv2"] = cv2
    except ImportError as err:
        missing["cv2"] = str(err)
    return found, missing


def _resample(image: np.ndarray, size: int) -> np.ndarray:
    """Nearest resampling by index arithmetic (no library: the same pixels for every peer)."""
    rows = np.arange(size) * image.shape[0] // size
    cols = np.arange(size) * image.shape[1] // size
    return np.ascontiguousarray(image[rows][:, cols])


def images(size: int) -> dict[str, np.ndarray]:
    """The three test images (module docstring), from the shared real data."""
    from omniscape_torch.io import palette_to_labels, read_image

    photo = read_image(PHOTO).numpy()
    semantic = read_image(SEMANTIC)
    labels = palette_to_labels(semantic).numpy().astype(np.uint8)
    rgb = _resample(photo, size)
    grey = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    return {"rgb": rgb, "labels": _resample(labels, size),
            "uint16": (np.round(grey) * 257).astype(np.uint16)}


def coders(peers: dict) -> dict[str, tuple]:
    """``{peer row name: (encode(array) -> bytes, decode(bytes) -> array)}``."""
    out = {}
    if "pillow" in peers:
        Image = peers["pillow"]

        def pil_encode(level, strategy=-1):
            def encode(a):
                buf = io.BytesIO()
                Image.fromarray(a).save(buf, format="PNG", compress_level=level,
                                        compress_type=strategy)
                return buf.getvalue()
            return encode

        def pil_decode(data):
            return np.asarray(Image.open(io.BytesIO(data)))

        out["pillow_level1_rle"] = (pil_encode(1, Z_RLE), pil_decode)
        out["pillow_level1"] = (pil_encode(1), pil_decode)
        out["pillow_level6"] = (pil_encode(6), pil_decode)
    if "cv2" in peers:
        cv2 = peers["cv2"]

        def cv_encode(a):
            if a.ndim == 3:
                a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
            ok, data = cv2.imencode(".png", a)
            assert ok
            return data.tobytes()

        def cv_decode(data):
            a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            return cv2.cvtColor(a, cv2.COLOR_BGR2RGB) if a.ndim == 3 else a

        out["cv2_default"] = (cv_encode, cv_decode)
    return out


def wheel_sizes(peers_wanted: list[str]) -> dict:
    """Per peer: its wheel file, the wheel's bytes and the unpacked (installed) bytes, from
    ``pip download --no-deps --only-binary=:all:`` for this interpreter and platform."""
    out = {}
    with tempfile.TemporaryDirectory(prefix="bench-png-") as tmp:
        for peer in peers_wanted:
            dist = WHEELS[peer]
            folder = Path(tmp) / peer
            proc = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps",
                                   "--only-binary=:all:", "-q", "-d", str(folder), dist],
                                  capture_output=True, text=True, timeout=600)
            wheels = sorted(folder.glob("*.whl")) if folder.is_dir() else []
            if proc.returncode != 0 or not wheels:
                out[peer] = {"distribution": dist, "skipped": (proc.stderr.strip().splitlines()
                                                               or ["no wheel"])[-1]}
                continue
            with zipfile.ZipFile(wheels[0]) as z:
                installed = sum(i.file_size for i in z.infolist())
            out[peer] = {"distribution": dist, "wheel": wheels[0].name,
                         "wheel_bytes": wheels[0].stat().st_size, "installed_bytes": installed}
    return out


def run(args: argparse.Namespace) -> dict:
    peers, missing = _peers()
    cv2 = peers.get("cv2")
    load = begin_run(1, cv2)
    record = run_record("png", "cpu", 1, cv2)
    record["versions"]["pillow"] = getattr(peers.get("pillow"), "__version__", None) or (
        __import__("PIL").__version__ if "pillow" in peers else None)
    record.update(size=args.size, repeats=args.repeats, warmup=args.warmup,
                  loadavg_start=load, missing=missing)
    record["wheels"] = {} if args.no_download else wheel_sizes(list(WHEELS))
    data = images(args.size)
    rows = []
    table = coders(peers)
    for kind, image in data.items():
        # every peer's encode and decode of this image round-robin: a change of load hits all
        blobs = {name: encode(image) for name, (encode, _) in table.items()}
        fns = [f for name, (encode, decode) in table.items()
               for f in (lambda e=encode: e(image), lambda d=decode, b=blobs[name]: d(b))]
        timings = measure(fns, args.repeats, args.warmup)
        for i, (name, (_, decode)) in enumerate(table.items()):
            back = decode(blobs[name])
            enc, dec = timings[2 * i], timings[2 * i + 1]
            rows.append({"peer": name, "image": kind, "shape": list(image.shape),
                         "dtype": str(image.dtype), "bytes": len(blobs[name]),
                         "identical": back.dtype == image.dtype and np.array_equal(back, image),
                         "encode_ms": 1e3 * enc["median_s"], "encode_iqr_ms": 1e3 * enc["iqr_s"],
                         "decode_ms": 1e3 * dec["median_s"], "decode_iqr_ms": 1e3 * dec["iqr_s"]})
    record["rows"] = rows
    record["loadavg_end"] = loadavg()
    return record


def markdown(result: dict) -> str:
    lines = [f"PNG coding at {result['size']} x {result['size']}, median of "
             f"{result['repeats']} (load {result['loadavg_start']} -> {result['loadavg_end']})",
             "", "| peer | image | encode ms (IQR) | decode ms (IQR) | bytes | lossless |",
             "|---|---|---:|---:|---:|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['peer']} | {r['image']} | {r['encode_ms']:.1f} "
                     f"({r['encode_iqr_ms']:.1f}) | {r['decode_ms']:.1f} ({r['decode_iqr_ms']:.1f})"
                     f" | {r['bytes']:,} | {'yes' if r['identical'] else 'NO'} |")
    for peer, why in result["missing"].items():
        lines.append(f"| {peer} | skipped: {why} | | | | |")
    if result["wheels"]:
        lines += ["", "| peer | wheel | wheel MB | installed MB |", "|---|---|---:|---:|"]
        for peer, w in result["wheels"].items():
            if "skipped" in w:
                lines.append(f"| {peer} | skipped: {w['skipped']} | | |")
            else:
                lines.append(f"| {peer} | {w['wheel']} | {w['wheel_bytes'] / 1e6:.1f} | "
                             f"{w['installed_bytes'] / 1e6:.1f} |")
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=positive_int, default=None, help="image side (1024; 256 quick)")
    p.add_argument("--repeats", type=positive_int, default=None, help="timed calls (15; 3 quick)")
    p.add_argument("--warmup", type=int, default=None, help="untimed calls first (2; 1 quick)")
    p.add_argument("--no-download", action="store_true",
                   help="skip the wheel sizes (pip download); implied by --quick")
    p.add_argument("--quick", action="store_true", help="a smoke run (seconds)")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON output (default benchmarks/results/png.json; quick: "
                        "benchmarks/results/quick/png.json)")
    args = p.parse_args(argv)
    for name, (full, quick) in {"size": (1024, 256), "repeats": (15, 3),
                                "warmup": (2, 1)}.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    args.no_download = args.no_download or args.quick
    if args.out is None:
        args.out = results_path("png.json", quick=args.quick)
    return args


def main(argv: list[str] | None = None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
