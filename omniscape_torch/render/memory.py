"""Large CPU output buffers: huge pages, and kept for reuse once freed.

A fresh tensor of 32 MB or more (glibc's largest ``mmap`` threshold) is a new mapping whose
pages fault on first touch, one per 4 KiB: on a small VM that costs more than the arithmetic
that fills it (measured: writing a fresh 96 MB tensor 28-35 ms, the same in reused memory
3 ms). Renderers return such tensors on every call (a batch of images, its labels), so
:func:`empty` maps them itself, with ``madvise(MADV_HUGEPAGE)`` (one fault per 2 MiB: 4 ms),
and when the last tensor viewing a buffer is freed, the buffer goes back to a pool from which
the next :func:`empty` of the same size takes it, already faulted in. The pool holds at most
:data:`POOL_BYTES`; :func:`release` empties it.

Why keep them: in a virtual machine whose host takes freed memory back (free page reporting),
a fresh huge page can cost a host-side fault as well. Measured on the 2-core VM of the
benchmarks, sampling 8 x 1M pixels into a fresh buffer took a median 53 ms with huge pages (a
sixth of the calls 150-220 ms), 76 ms with ordinary pages, 48 ms into a reused buffer.

A buffer is reused only after every tensor and view of it is gone (the pool learns of it from
the buffer's own finaliser, which runs when the last one is freed), so reuse never aliases
live data. Buffers below :data:`HUGE_BYTES`, and everything where ``mmap`` or its advice is
unavailable, are ordinary ``torch.empty``.
"""

from __future__ import annotations

import ctypes
import functools
import math
import mmap
import threading

import torch

__all__ = ["empty", "release", "pooled_bytes", "HUGE_BYTES", "POOL_BYTES"]

#: Buffers from this size on are mapped here (huge pages) and pooled.
HUGE_BYTES = 32 * 2 ** 20
#: Most bytes the pool keeps for reuse (beyond it, freed buffers are unmapped).
POOL_BYTES = 2 ** 30

_LOCK = threading.Lock()
_FREE: dict[int, list[mmap.mmap]] = {}   # size -> freed mappings


def empty(shape: tuple[int, ...], dtype: torch.dtype,
          device: torch.device | str | None = None) -> torch.Tensor:
    """``torch.empty(shape, dtype=dtype, device=device)``; on the CPU from :data:`HUGE_BYTES`
    on, a pooled, huge-page mapping (contents undefined, as ``torch.empty``)."""
    size = math.prod(shape) * torch.empty((), dtype=dtype).element_size()
    if (size < HUGE_BYTES or not hasattr(mmap, "MADV_HUGEPAGE")
            or (device is not None and torch.device(device).type != "cpu")):
        return torch.empty(shape, dtype=dtype, device=device)
    with _LOCK:
        free = _FREE.get(size)
        buffer = free.pop() if free else None
    if buffer is None:
        buffer = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        try:
            buffer.madvise(mmap.MADV_HUGEPAGE)
        except OSError:   # no transparent huge pages here: ordinary pages
            pass
    # the tensor keeps the holder alive; the holder's finaliser returns the mapping
    holder = _holder_type(size).from_buffer(buffer)
    holder.mapping = buffer
    return torch.frombuffer(holder, dtype=dtype).view(shape)


def release() -> int:
    """Unmap every pooled buffer; returns the bytes released."""
    with _LOCK:
        freed = [b for buffers in _FREE.values() for b in buffers]
        _FREE.clear()
    total = sum(len(b) for b in freed)
    for buffer in freed:
        buffer.close()
    return total


def pooled_bytes() -> int:
    """Bytes the pool holds for reuse."""
    with _LOCK:
        return sum(len(b) for buffers in _FREE.values() for b in buffers)


def _give_back(buffer: mmap.mmap) -> None:
    with _LOCK:
        held = sum(len(b) for buffers in _FREE.values() for b in buffers)
        if held + len(buffer) <= POOL_BYTES:
            _FREE.setdefault(len(buffer), []).append(buffer)
            return
    # beyond the pool: unmapped once its last export is gone (its own finaliser)


@functools.lru_cache(maxsize=64)
def _holder_type(size: int) -> type:
    """A ctypes array of ``size`` bytes over a mapping, exporting it to torch, whose finaliser
    gives the mapping back to the pool."""

    class Holder(ctypes.c_char * size):
        def __del__(self):
            try:
                _give_back(self.mapping)
            except Exception:   # interpreter shutdown: nothing left to give back to
                pass

    return Holder
