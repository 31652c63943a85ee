"""OpenEXR depth I/O: bit-exact round trips, atomic writes, clear errors."""

from __future__ import annotations

import math

import numpy as np
import OpenEXR
import pytest
import torch

from omniscape_torch.io.exr import exr_channels, read_exr, write_exr


def _depth(h=5, w=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.rand(h, w, generator=g, dtype=torch.float32) * 1000
    d[0, 0] = math.inf       # sky
    d[0, 1] = 0.0
    d[1, 1] = -0.0
    d[2, 2] = torch.finfo(torch.float32).tiny / 4   # subnormal
    d[3, 3] = torch.finfo(torch.float32).max
    d[4, 4] = 1.0 + torch.finfo(torch.float32).eps
    return d


def test_round_trip_bit_exact(tmp_path):
    d = _depth()
    p = write_exr(tmp_path / "d.exr", d)
    assert p == tmp_path / "d.exr"
    back = read_exr(p)
    assert back.dtype == torch.float32 and back.shape == d.shape
    assert torch.equal(back.view(torch.int32), d.view(torch.int32))
    assert torch.isinf(back[0, 0]) and back[0, 0] > 0
    assert back[0, 1] == 0


def test_nan_and_numpy_input(tmp_path):
    a = np.array([[np.nan, 1.0], [-np.inf, 2.5]], dtype=np.float32)
    back = read_exr(write_exr(tmp_path / "n.exr", a)).numpy()
    assert np.array_equal(back, a, equal_nan=True)


def test_channel_name_and_default(tmp_path):
    d = _depth(5, 6, seed=1)
    write_exr(tmp_path / "r.exr", d, channel="range")
    assert exr_channels(tmp_path / "r.exr") == ["range"]
    assert torch.equal(read_exr(tmp_path / "r.exr"), d)            # only channel
    assert torch.equal(read_exr(tmp_path / "r.exr", "range"), d)
    with pytest.raises(ValueError, match=r"no channel 'Z'.*\['range'\]"):
        read_exr(tmp_path / "r.exr", "Z")


def test_multichannel_prefers_z(tmp_path):
    z = np.full((2, 3), 4.0, np.float32)
    r = np.full((2, 3), 1.0, np.float32)
    OpenEXR.File({}, {"R": r, "G": r, "B": r, "Z": z}).write(str(tmp_path / "m.exr"))
    assert torch.equal(read_exr(tmp_path / "m.exr"), torch.from_numpy(z))
    assert torch.equal(read_exr(tmp_path / "m.exr", "G"), torch.from_numpy(r))
    OpenEXR.File({}, {"A": r, "B": z}).write(str(tmp_path / "ab.exr"))
    with pytest.raises(ValueError, match="name the one"):
        read_exr(tmp_path / "ab.exr")


def test_half_channel_widened(tmp_path):
    h = np.array([[0.5, np.inf]], dtype=np.float16)
    OpenEXR.File({}, {"Z": h}).write(str(tmp_path / "h.exr"))
    back = read_exr(tmp_path / "h.exr")
    assert back.dtype == torch.float32 and back.tolist() == [[0.5, math.inf]]


def test_uint_channel_rejected(tmp_path):
    OpenEXR.File({}, {"Z": np.ones((2, 2), np.uint32)}).write(str(tmp_path / "u.exr"))
    with pytest.raises(TypeError, match="uint32"):
        read_exr(tmp_path / "u.exr")


def test_atomic_replace_and_no_temp_left(tmp_path):
    target = tmp_path / "sub" / "d.exr"
    write_exr(target, torch.zeros(2, 2))
    write_exr(target, torch.ones(3, 4))          # replaces the existing file
    assert torch.equal(read_exr(target), torch.ones(3, 4))
    assert sorted(p.name for p in target.parent.iterdir()) == ["d.exr"]


def test_failed_write_leaves_old_file_and_no_temp(tmp_path, monkeypatch):
    target = tmp_path / "d.exr"
    write_exr(target, torch.full((2, 2), 7.0))

    class Boom(Exception):
        pass

    def fail(*args, **kwargs):
        raise Boom

    monkeypatch.setattr("omniscape_torch.io.exr.os.replace", fail)
    with pytest.raises(Boom):
        write_exr(target, torch.zeros(2, 2))
    assert torch.equal(read_exr(target), torch.full((2, 2), 7.0))
    assert [p.name for p in tmp_path.iterdir()] == ["d.exr"]


def test_write_errors(tmp_path):
    with pytest.raises(TypeError, match="float32"):
        write_exr(tmp_path / "x.exr", torch.zeros(2, 2, dtype=torch.float64))
    with pytest.raises(TypeError, match="float32"):
        write_exr(tmp_path / "x.exr", np.zeros((2, 2), np.float16))
    with pytest.raises(TypeError, match="Tensor"):
        write_exr(tmp_path / "x.exr", [[1.0]])
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        write_exr(tmp_path / "x.exr", torch.zeros(1, 2, 2))
    with pytest.raises(ValueError, match="non-empty"):
        write_exr(tmp_path / "x.exr", torch.zeros(0, 2))
    with pytest.raises(ValueError, match="channel"):
        write_exr(tmp_path / "x.exr", torch.zeros(2, 2), channel="")
    assert list(tmp_path.iterdir()) == []


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        read_exr(tmp_path / "missing.exr")
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr file")
    with pytest.raises(ValueError, match="not a readable OpenEXR"):
        read_exr(bad)
    with pytest.raises(ValueError, match="not a readable OpenEXR"):
        exr_channels(bad)
