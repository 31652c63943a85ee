"""Messages a newcomer reads (issue 46): no library's internals in them, no stray lines."""

from __future__ import annotations

import numpy as np
import pytest

from omniscape_torch.io.images import read_image


def test_a_file_pillow_cannot_read_is_named_without_its_buffer(tmp_path):
    bad = tmp_path / "photo.png"
    bad.write_bytes(b"not a png at all" * 10)
    with pytest.raises(ValueError) as err:
        read_image(bad)
    message = str(err.value)
    assert message.startswith(f"{bad}: not an image Pillow can read (")
    assert "BytesIO" not in message and " at 0x" not in message, message


def test_undecodable_images_leave_no_opencv_lines_on_stderr(tmp_path, capfd):
    """Broken PNG, TIFF and BMP files among the views: each skipped with its reason, and none
    of OpenCV's `[ WARN:0@...]` / `[ERROR:0@...]` lines (nor libpng's) on stderr."""
    cv2 = pytest.importorskip("cv2")
    from omniscape_torch.calibration.detect import detect_corners

    image = np.random.default_rng(0).integers(0, 256, (64, 64), dtype=np.uint8)
    for suffix in (".png", ".tif", ".bmp"):
        data = cv2.imencode(suffix, image)[1].tobytes()
        (tmp_path / f"cut_{suffix[1:]}{suffix}").write_bytes(data[:len(data) // 2])
        (tmp_path / f"junk_{suffix[1:]}{suffix}").write_bytes(data[:8] + bytes(range(256)) * 4)
    capfd.readouterr()
    with pytest.raises(ValueError, match="none of the 6 images can be read") as err:
        detect_corners(tmp_path, "checkerboard:9x6:0.03", min_views=1, workers=1)
    captured = capfd.readouterr()
    assert captured.err == "", captured.err
    assert "cut_png: a truncated PNG (its end is missing)" in str(err.value)
    assert "junk_png: a truncated PNG (its end is missing)" in str(err.value)
    assert str(err.value).count("not an image OpenCV can decode") == 4
    level = cv2.utils.logging.getLogLevel()
    assert level != cv2.utils.logging.LOG_LEVEL_SILENT   # restored


def _fisheye_json(tmp_path, fov_deg=190.0):
    import math

    import omniscape_torch as ot

    path = tmp_path / "fisheye.json"
    ot.presets.fisheye((64, 64), fov=math.radians(fov_deg), model="kannala_brandt").save_json(path)
    return path


def test_convert_model_refuses_a_fold_at_90_deg_before_fitting(tmp_path, capsys, monkeypatch):
    """`--format opencv --to kannala_brandt` of a 190-degree lens: refused at once, with what
    to do, not after the fit (14 s before issue 46)."""
    import omniscape_torch.calibration as calibration
    from omniscape_torch import cli

    def no_fit(*args, **kwargs):
        raise AssertionError("the conversion ran")

    monkeypatch.setattr(calibration, "convert", no_fit)
    argv = ["convert-model", "--json", str(_fisheye_json(tmp_path)), "--to", "kannala_brandt",
            "--format", "opencv", "--out", str(tmp_path / "cam.yaml")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("omniscape-torch convert-model: error: --format opencv: the "
                          "kannala_brandt camera sees up to 95.00 deg off its optical axis")
    assert "--accept-fov" in err and "--fov" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "cam.yaml").exists()
    for more in (["--fov", "170"], ["--accept-fov"]):   # within 90 deg, or accepted: it fits
        assert cli.main([*argv, *more]) == 1
        assert "AssertionError: the conversion ran" in capsys.readouterr().err


def test_info_says_what_each_field_of_view_is(tmp_path, capsys):
    from omniscape_torch import cli

    assert cli.main(["info", "--json", str(_fisheye_json(tmp_path))]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("whole image"))
    assert "corners included" in line and "extrapolated" in line
    assert "circular fisheye" in next(ln for ln in out.splitlines()
                                      if ln.strip().startswith("horizontal"))
