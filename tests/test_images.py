"""Images on disk (``omniscape_torch.io.images``): Pillow reads and writes them (a requirement),
with the pixels OpenCV read and wrote before (issue 32); OpenCV, where installed, is the
oracle."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import torch

from omniscape_torch.io import read_image, write_image
from omniscape_torch.io.images import decode_image, encode_image

ROOT = Path(__file__).resolve().parents[1]
PHOTO = ROOT.parent / "shared" / "data" / "ocamcalib_real" / "img0.jpg"
SEMANTIC = (ROOT.parent / "shared" / "data" / "omniscape_equirect" /
            "carla_left_semantic_palette_quantized.png")


def _images() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (37, 53, 3), dtype=np.uint8)
    rgb[:10] = 17                                   # runs as well as noise
    return {"rgb": rgb, "grey": rng.integers(0, 13, (37, 53), dtype=np.uint8),
            "grey16": rng.integers(0, 65536, (37, 53), dtype=np.uint16)}


def _rgb16() -> np.ndarray:
    return np.random.default_rng(2).integers(0, 65536, (37, 53, 3), dtype=np.uint16)


@pytest.mark.parametrize("kind", ["rgb", "grey", "grey16"])
def test_write_read_round_trip_is_lossless(tmp_path, kind):
    image = _images()[kind]
    path = write_image(tmp_path / f"{kind}.png", torch.from_numpy(image))
    back = read_image(path).numpy()
    assert back.dtype == image.dtype and back.shape == image.shape
    np.testing.assert_array_equal(back, image)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temporaries


@pytest.mark.parametrize("kind", ["rgb", "grey", "grey16"])
def test_pixels_are_those_opencv_writes_and_reads(tmp_path, kind):
    """Our PNG decodes in OpenCV to the array written, and OpenCV's PNG decodes in ours to the
    array OpenCV wrote: the same files as before, decoded."""
    cv2 = pytest.importorskip("cv2")
    image = _images()[kind]
    bgr = image[..., ::-1] if image.ndim == 3 else image
    theirs = cv2.imdecode(np.frombuffer(encode_image(image), np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(theirs, bgr)
    ok, data = cv2.imencode(".png", np.ascontiguousarray(bgr))
    assert ok
    np.testing.assert_array_equal(decode_image(data.tobytes()), image)


def test_a_sixteen_bit_colour_png_reads_as_opencv_wrote_it():
    """Pillow reads 8 bits of it; OpenCV reads it where installed."""
    cv2 = pytest.importorskip("cv2")
    image = _rgb16()
    ok, data = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    assert ok
    back = decode_image(data.tobytes())
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, image)


def test_real_files_read_as_opencv_reads_them():
    """A real JPEG photo and a real palette-quantised PNG: the same pixels as OpenCV's."""
    cv2 = pytest.importorskip("cv2")
    for path in (PHOTO, SEMANTIC):
        if not path.is_file():
            pytest.skip(f"{path}: shared data missing")
        ours = read_image(path).numpy()
        theirs = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if theirs.ndim == 3:
            theirs = cv2.cvtColor(theirs, cv2.COLOR_BGRA2RGB if theirs.shape[2] == 4
                                  else cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(ours, theirs)


def test_alpha_and_palette_pngs_read_as_rgb():
    from PIL import Image

    rgba = np.random.default_rng(1).integers(0, 256, (8, 9, 4), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgba).save(buf, format="PNG")
    np.testing.assert_array_equal(decode_image(buf.getvalue()), rgba[..., :3])
    buf = io.BytesIO()
    Image.fromarray(rgba[..., :3]).quantize(7).save(buf, format="PNG")
    assert decode_image(buf.getvalue()).shape == (8, 9, 3)


def test_bad_input_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such image"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="bad.png: not an image"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(TypeError, match="uint8 or uint16"):
        encode_image(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match=r"\(H, W, 3\) or \(H, W\)"):
        encode_image(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(ValueError, match="16-bit colour is not written"):
        encode_image(_rgb16())


def test_sixteen_bit_colour_png_without_opencv_is_refused(monkeypatch):
    import sys
    cv2 = pytest.importorskip("cv2")
    ok, data = cv2.imencode(".png", _rgb16())
    assert ok
    data = data.tobytes()
    monkeypatch.setitem(sys.modules, "cv2", None)
    with pytest.raises(ValueError, match="16-bit colour PNG; reading it needs OpenCV"):
        decode_image(data, "x.png")


def test_jpeg_is_written_as_opencv_writes_it():
    """Quality 95, OpenCV's default (Pillow's is 75): the same pixels decoded."""
    cv2 = pytest.importorskip("cv2")
    if not PHOTO.is_file():
        pytest.skip(f"{PHOTO}: shared data missing")
    image = read_image(PHOTO).numpy()[:256, :256].copy()
    ok, theirs = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]))
    assert ok
    np.testing.assert_array_equal(decode_image(encode_image(image, ".jpg")),
                                  decode_image(theirs.tobytes()))
