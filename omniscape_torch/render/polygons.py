"""Polygons through a camera change: each ring densified where the camera bends it, mapped,
and clipped to the output's valid area (a ring may become several, or none).

Rings are in the corner coordinates of `render.detection` (the pixel of centre `(u, v)` spans
`[u, u + 1] x [v, v + 1]`), COCO's convention for polygons; they are converted to pixel centres
here and back on the way out. Each input ring is a simple closed polygon (its last point joins
its first; a repeated first point is dropped); its region is the area it encloses.

How a ring is mapped:

* **Densified** where the camera bends it: each edge (a straight segment in the source) is
  halved until, wherever it lies within `OUTLINE_STEP` pixels of the output image, its mapped
  points lie at most `OUTLINE_STEP` output pixels apart and the mapped midpoint of each piece
  is within `RING_TOLERANCE` (0.05) output pixels of the chord that stands for it; a piece whose
  midpoint is seen by the output while its ends are not (or not while they are) is halved too.
  The mapped ring thus follows the curved image of every edge within 0.05 px.
* **Cut** where it leaves the valid area (the source's image and cones, the output's image,
  field of view and blind cone: what `Change.forward` sees): the points where an edge crosses
  the valid area's border are found by bisection along the source edge (to 1e-6 of the piece's
  length), and between the point where the ring leaves the valid area and the next point where
  it enters it again, the clipped ring follows the border of the valid area itself.
* **The border of the valid area** is traced by marching squares on the validity of the output
  pixel centres (the renderer's `valid` mask where it is given, else `Change.backward`'s), one
  pixel of padding outside the image, each vertex of the parts used moved onto the border by
  bisection along its grid edge (to 1/1024 px). Its vertices lie on the border; between two of
  them (at most one pixel apart) a chord misses a curved border by its sagitta (under 0.01 px
  for curvature radii over 12 px) and cuts a corner where two curved parts of the border meet
  (two cameras' edges) by at most about a pixel; the image's own corners are kept exactly.
* Parts of the valid area that lie wholly inside a ring (a blind cone's hole that an object
  surrounds, the whole view inside a large object) come out too: a hole is joined to the ring
  around it by a zero-width cut, so that every output ring is one closed polygon whose filling
  (even-odd or non-zero) is the region.

`polygon_index` says which input ring each output ring comes from. A part of an edge that leaves
the valid area and comes back between two samples (closer than `OUTLINE_STEP` px, both inside,
the midpoint inside too) is missed; it is shallower than the samples' sagitta (about 0.1 px).
"""

from __future__ import annotations

import math
from typing import Protocol, Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = ["RING_TOLERANCE", "check_polygons", "map_rings"]

#: Most distance, in output pixels, between the mapped midpoint of a piece of a ring's edge and
#: the chord that stands for that piece in the mapped ring.
RING_TOLERANCE = 0.05
#: Most halvings of an edge (a piece of 1/65536 of the edge).
_ROUNDS = 16
#: Bisection steps of a crossing along the source edge (of at most OUTLINE_STEP output px:
#: to 2e-5 px), and of a border vertex along its grid edge (one pixel: to 1/1024 px).
_CROSSING_STEPS = 20
_BORDER_STEPS = 10
#: Crossings closer than this along the border (in border vertices, about a pixel each) whose
#: order the chords may have swapped: the one just behind is taken, with no border between.
_BEHIND = 0.02


class _Change(Protocol):
    """What the rings need of a camera change (`render.detection.Change`): ``forward`` (source
    pixel centres -> output ones and where both cameras see them), ``backward``, the
    ``rotation (n, 3, 3)`` and the two sides."""

    rotation: Tensor
    source: object
    output: object

    def forward(self, points: Tensor, sample: Tensor, domain: bool = False) -> tuple: ...

    def backward(self, pixels: Tensor, sample: Tensor) -> tuple[Tensor, Tensor]: ...


# -------------------------------------------------------------------------------------------
# Input checks
# -------------------------------------------------------------------------------------------
def _ring(value: object, where: str) -> Tensor:
    """One ring: ``(N, 2)`` points or COCO's flat ``[x0, y0, x1, y1, ...]`` -> ``(N, 2)``
    float64 on the CPU (a repeated closing point dropped); raises naming ``where``."""
    try:
        ring = torch.as_tensor(np.asarray(value, dtype=np.float64) if not isinstance(
            value, Tensor) else value.detach())
    except (TypeError, ValueError) as err:
        raise TypeError(f"{where}: expected (N, 2) points or a flat [x0, y0, x1, y1, ...] list, "
                        f"got {type(value).__name__} ({err})") from None
    if ring.is_complex() or not (ring.is_floating_point() or ring.dtype in (
            torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)):
        raise TypeError(f"{where}: expected real coordinates, got {ring.dtype}")
    ring = ring.to("cpu", torch.float64)
    if ring.dim() == 1:
        if len(ring) % 2:
            raise ValueError(f"{where}: a flat [x0, y0, x1, y1, ...] list of odd length "
                             f"{len(ring)}")
        ring = ring.reshape(-1, 2)
    if ring.dim() != 2 or ring.shape[1] != 2:
        raise ValueError(f"{where}: expected (N, 2) points (x, y) or a flat [x0, y0, ...] list, "
                         f"got shape {tuple(ring.shape)}")
    if not bool(torch.isfinite(ring).all()):
        raise ValueError(f"{where}: coordinates must be finite (NaN or inf)")
    if len(ring) > 1 and bool((ring[0] == ring[-1]).all()):
        ring = ring[:-1]
    if len(ring) < 3:
        raise ValueError(f"{where}: a ring needs at least 3 points, got {len(ring)}")
    return ring


def check_per_sample(value: object, batch: int, name: str, expected: str) -> None:
    """A list (or tuple) of `batch` per-sample values, else an error naming `name`."""
    if not isinstance(value, (list, tuple)):
        raise TypeError(f"{name}: expected {expected}, got {type(value).__name__}")
    if len(value) != batch:
        raise ValueError(f"{name}: {len(value)} samples, the batch has {batch}")


def check_polygons(polygons: object, batch: int, boxes: Sequence[Tensor] | None = None,
                   polygon_box: object = None, name: str = "polygons"
                   ) -> tuple[list[list[Tensor]], list[Tensor]]:
    """``polygons``: per sample a list of rings (each ``(N_k, 2)`` corner coordinates or a flat
    COCO list) and ``polygon_box``: per sample ``(R_i,)`` the box (or object) of each ring
    (None: ring k belongs to box k) -> the rings as ``(N_k, 2)`` float64 CPU tensors and
    ``polygon_box`` as int64 tensors; raises naming ``polygons[i][k]`` or ``polygon_box[i]``.
    With ``boxes``, a ring's box must be one of its sample's."""
    check_per_sample(polygons, batch, name, f"per sample a list of rings (a list of {batch})")
    rings = []
    for i, sample in enumerate(polygons):
        if isinstance(sample, (Tensor, np.ndarray)) or not isinstance(sample, (list, tuple)):
            raise TypeError(f"{name}[{i}]: expected a list of rings ((N, 2) points or flat "
                            f"[x0, y0, ...] lists), got {type(sample).__name__}")
        rings.append([_ring(r, f"{name}[{i}][{k}]") for k, r in enumerate(sample)])
    if polygon_box is not None:
        if isinstance(polygon_box, Tensor) and polygon_box.dim() == 2:
            polygon_box = list(polygon_box)
        if not isinstance(polygon_box, (list, tuple)) or len(polygon_box) != batch:
            raise ValueError(f"polygon_box: expected a list of {batch} (R_i,) integer tensors, "
                             f"got {type(polygon_box).__name__}")
    owners = []
    for i, sample in enumerate(rings):
        if polygon_box is None:
            owner = torch.arange(len(sample))
            if boxes is not None and len(sample) > len(boxes[i]):
                raise ValueError(f"polygon_box[{i}]: not given, ring k belongs to box k, but "
                                 f"sample {i} has {len(sample)} rings and {len(boxes[i])} boxes; "
                                 f"pass polygon_box (the box of each ring)")
        else:
            owner = torch.as_tensor(polygon_box[i]).detach().reshape(-1).cpu()
            if owner.is_floating_point() or owner.is_complex() or owner.dtype == torch.bool:
                raise ValueError(f"polygon_box[{i}]: expected integer box indices, got "
                                 f"{owner.dtype}")
            if len(owner) != len(sample):
                raise ValueError(f"polygon_box[{i}]: {len(owner)} indices for {len(sample)} "
                                 f"rings")
            owner = owner.long()
            top = None if boxes is None else len(boxes[i])
            bad = (owner < 0) | (owner >= top) if top is not None else owner < 0
            if bool(bad.any()):
                k = int(bad.nonzero()[0, 0])
                span = f"0..{top - 1} (sample {i} has {top} boxes)" if top else (
                    "a box index >= 0" if top is None else f"none (sample {i} has no box)")
                raise ValueError(f"polygon_box[{i}][{k}]: box {int(owner[k])} out of range, "
                                 f"expected {span}")
        owners.append(owner)
    return rings, owners


# -------------------------------------------------------------------------------------------
# Densified rings and their crossings of the valid area's border
# -------------------------------------------------------------------------------------------
def _near(pixels: Tensor, size: tuple[int, int], s: float) -> Tensor:
    """Where output pixel centres lie within ``s`` px of the image's outer centres."""
    h, w = size
    u, v = pixels[..., 0], pixels[..., 1]
    return (u > -s) & (u < w - 1 + s) & (v > -s) & (v < h - 1 + s)


class _Dense:
    """The rings of one change densified (module docstring): points sorted by ring, edge and
    parameter, with their source ``src``, output ``pix``, ``ok`` (seen by both cameras) and
    ``cross`` (a crossing of the valid area's border, inserted on the seen side)."""

    def __init__(self, change: _Change, rings: list[Tensor], sample: Tensor, step: float):
        size = change.output.image_size
        counts = torch.tensor([len(r) for r in rings])
        a = torch.cat(rings)                                          # (E, 2) edge starts
        ring_of = torch.arange(len(rings)).repeat_interleave(counts)
        first = torch.cumsum(counts, 0) - counts
        nxt = torch.arange(len(a)) + 1
        last = first + counts - 1
        nxt[last] = first
        b = a[nxt]
        esample = sample[ring_of]
        self.a, self.b, self.esample, self.ring_of = a, b, esample, ring_of
        self.change = change
        edge = torch.arange(len(a))
        t = torch.zeros(len(a), dtype=torch.float64)
        pix, ok, thr = change.forward(a, esample, domain=True)
        open_ = torch.ones(len(a), dtype=torch.bool)
        for _ in range(_ROUNDS):
            succ, t_end = self._successors(edge, t)
            cand = open_.nonzero()[:, 0]
            if len(cand) == 0:
                break
            e = edge[cand]
            tm = 0.5 * (t[cand] + t_end[cand])
            src = a[e] + tm[:, None] * (b[e] - a[e])
            pm, okm, thrm = change.forward(src, esample[e], domain=True)
            pa, pb = pix[cand], pix[succ[cand]]
            oka, okb = ok[cand], ok[succ[cand]]
            tha, thb = thr[cand], thr[succ[cand]]
            near = _near(pa, size, step) | _near(pb, size, step)
            far = tha & thb & near & ((pb - pa).norm(dim=-1) > step)
            bent = tha & thb & thrm & (near | _near(pm, size, step)) & (
                (pm - 0.5 * (pa + pb)).norm(dim=-1) > RING_TOLERANCE)
            graze = (oka == okb) & (okm != oka)
            long_ = (t_end[cand] - t[cand]) * (b[e] - a[e]).norm(dim=-1) > 1e-6
            split = (far | bent | graze) & long_
            open_[cand[~split]] = False
            if not bool(split.any()):
                break
            edge = torch.cat((edge, e[split]))
            t = torch.cat((t, tm[split]))
            pix, ok, thr = (torch.cat((x, y[split])) for x, y in ((pix, pm), (ok, okm),
                                                                    (thr, thrm)))
            open_ = torch.cat((open_, torch.ones(int(split.sum()), dtype=torch.bool)))
            order = torch.argsort(edge.to(torch.float64) + t)
            edge, t, pix, ok, thr, open_ = (x[order] for x in (edge, t, pix, ok, thr, open_))
        # the crossings: bisection along the source edge between a seen and an unseen point
        succ, t_end = self._successors(edge, t)
        flip = (ok != ok[succ]).nonzero()[:, 0]
        cross = torch.zeros(len(edge), dtype=torch.bool)
        if len(flip):
            e = edge[flip]
            lo = torch.where(ok[flip], t[flip], t_end[flip])
            hi = torch.where(ok[flip], t_end[flip], t[flip])
            for _ in range(_CROSSING_STEPS):
                mid = 0.5 * (lo + hi)
                _, okm = change.forward(a[e] + mid[:, None] * (b[e] - a[e]), esample[e])
                lo, hi = torch.where(okm, mid, lo), torch.where(okm, hi, mid)
            pc, _ = change.forward(a[e] + lo[:, None] * (b[e] - a[e]), esample[e])
            # sorted strictly between the two points it lies between (its bisection may end
            # on one of them)
            key_lo = torch.minimum(torch.maximum(lo, torch.nextafter(t[flip], t_end[flip])),
                                   torch.nextafter(t_end[flip], t[flip]))
            edge = torch.cat((edge, e))
            t = torch.cat((t, key_lo))
            pix = torch.cat((pix, pc))
            ok = torch.cat((ok, torch.ones(len(e), dtype=torch.bool)))
            cross = torch.cat((cross, torch.ones(len(e), dtype=torch.bool)))
            order = torch.argsort(edge.to(torch.float64) + t, stable=True)
            edge, t, pix, ok, cross = (x[order] for x in (edge, t, pix, ok, cross))
        self.edge, self.t, self.pix, self.ok, self.cross = edge, t, pix, ok, cross
        self.ring = ring_of[edge]
        self.sizes = torch.bincount(self.ring, minlength=len(rings))

    def _successors(self, edge: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """The next point of each (sorted) point along its ring, and the parameter on the
        point's own edge at which that next point lies (1 where it starts the next edge)."""
        ring = self.ring_of[edge]
        k = len(edge)
        idx = torch.arange(k)
        last = torch.ones(k, dtype=torch.bool)
        last[:-1] = ring[1:] != ring[:-1]
        start = torch.ones(k, dtype=torch.bool)
        start[1:] = ring[1:] != ring[:-1]
        first_of = torch.zeros(int(ring.max()) + 1 if k else 0, dtype=torch.long)
        first_of[ring[start]] = idx[start]
        succ = torch.where(last, first_of[ring], idx + 1)
        t_end = torch.where(edge[succ] == edge, t[succ], torch.ones_like(t))
        return succ, t_end

    def source(self, index: Tensor) -> Tensor:
        """Source pixel centres of the points ``index``."""
        e = self.edge[index]
        return self.a[e] + self.t[index][:, None] * (self.b[e] - self.a[e])


# -------------------------------------------------------------------------------------------
# The valid area's border: marching squares on the validity of the pixel centres
# -------------------------------------------------------------------------------------------
def _segment_table() -> np.ndarray:
    """``(16, 2, 2, 2)`` int: per cell code (bit k: corner k valid; corners counter-clockwise
    in (u, v): (u, v), (u + 1, v), (u + 1, v + 1), (u, v + 1), edge k from corner k to k + 1)
    and centre validity, up to two segments (from edge, to edge), -1 where none. Each segment
    goes from the edge where the valid corners end to the edge where they begin, so the valid
    area lies on its left (positive shoelace area around it)."""
    table = np.full((16, 2, 2, 2), -1, dtype=np.int64)
    for code in range(16):
        bit = [(code >> k) & 1 for k in range(4)]
        flips = [k for k in range(4) if bit[k] != bit[(k + 1) % 4]]
        exits = [k for k in flips if bit[k]]
        enters = [k for k in flips if not bit[k]]
        for centre in (0, 1):
            if len(flips) == 2:
                table[code, centre, 0] = (exits[0], enters[0])
            elif len(flips) == 4:
                for s, k in enumerate(exits):
                    table[code, centre, s] = (k, (k + 1) % 4 if centre else (k - 1) % 4)
    return table


_TABLE = _segment_table()


class _Border:
    """The valid area's border of one sample: closed contours of grid edges (marching squares),
    the valid area on their left, each vertex at first its grid edge's midpoint and moved onto
    the border (bisection) when asked for (`_refine`)."""

    def __init__(self, valid: np.ndarray, centre_valid):
        h, w = valid.shape
        g = np.zeros((h + 2, w + 2), dtype=bool)
        g[1:-1, 1:-1] = valid
        c0, c1, c2, c3 = g[:-1, :-1], g[:-1, 1:], g[1:, 1:], g[1:, :-1]
        code = (c0.astype(np.int64) | (c1 << 1) | (c2 << 2) | (c3 << 3))
        rows, cols = np.nonzero((code != 0) & (code != 15))
        code = code[rows, cols]
        saddle = (code == 5) | (code == 10)
        centre = np.zeros(len(code), dtype=np.int64)
        if saddle.any():   # the cell centre's validity joins or parts the diagonal corners
            at = np.stack((cols[saddle] - 0.5, rows[saddle] - 0.5), -1)   # (u, v) centres
            centre[saddle] = centre_valid(at).astype(np.int64)
        nh = (h + 2) * (w + 1)
        # global edge ids: horizontal (r, c)-(r, c + 1), vertical (r, c)-(r + 1, c)
        local = np.stack((rows * (w + 1) + cols, nh + rows * (w + 2) + cols + 1,
                          (rows + 1) * (w + 1) + cols, nh + rows * (w + 2) + cols), -1)
        segs = _TABLE[code, centre]                                    # (n, 2, 2)
        keep = segs[:, :, 0] >= 0
        cell = np.nonzero(keep)[0]
        frm = local[cell, segs[:, :, 0][keep]]
        to = local[cell, segs[:, :, 1][keep]]
        ids = np.unique(frm)
        nxt = np.searchsorted(ids, to[np.argsort(frm)])
        # each edge's two grid points (pixel centres), the valid one first
        horiz = ids < nh
        r = np.where(horiz, ids // (w + 1), (ids - nh) // (w + 2))
        c = np.where(horiz, ids % (w + 1), (ids - nh) % (w + 2))
        p = np.stack((c, r), -1)
        q = p + np.where(horiz[:, None], [1, 0], [0, 1])
        p_valid = g[p[:, 1], p[:, 0]]
        first = np.where(p_valid[:, None], p, q) - 1.0
        second = np.where(p_valid[:, None], q, p) - 1.0
        self.valid_end, self.invalid_end = first, second
        self.points = 0.5 * (first + second)
        self.refined = np.zeros(len(ids), dtype=bool)
        self.contours = []
        seen = [False] * len(ids)
        follow = nxt.tolist()
        for start in range(len(ids)):
            if seen[start]:
                continue
            loop, k = [], start
            while not seen[k]:
                seen[k] = True
                loop.append(k)
                k = follow[k]
            self.contours.append(np.asarray(loop, dtype=np.int64))
        self.size = (h, w)
        # the segments (each contour vertex to the next), bucketed by the pixel of their start
        lengths = [len(c) for c in self.contours]
        self.seg_start = np.concatenate(self.contours)
        self.seg_owner = np.repeat(np.arange(len(lengths)), lengths)
        self.seg_pos = np.concatenate([np.arange(n) for n in lengths])
        self.seg_end = np.concatenate([np.roll(c, -1) for c in self.contours])
        key = self._key(self.points[self.seg_start])[:, 0]
        self.seg_order = np.argsort(key, kind="stable")
        self.seg_keys = key[self.seg_order]

    def _key(self, points: np.ndarray, reach: int = 0) -> np.ndarray:
        """Bucket keys ``(Q, (2 reach + 1)^2)`` of output points ``(Q, 2)``: the pixel each
        lies in and those up to ``reach`` pixels around it."""
        w = self.size[1] + 8
        shift = np.arange(-reach, reach + 1)
        u = np.floor(points[:, 0]).astype(np.int64)[:, None] + 3 + shift
        v = np.floor(points[:, 1]).astype(np.int64)[:, None] + 3 + shift
        u = np.clip(u, 0, w - 1)
        return (v[:, :, None] * w + u[:, None, :]).reshape(len(points), -1)

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per point of ``points (Q, 2)`` (each within a pixel or so of the border) the nearest
        segment of the contours: contour ``(Q,)``, position of its start ``(Q,)`` and the
        fraction along it ``(Q,)``; segments starting within two pixels are looked at, all of
        them for a point with none there."""
        q = len(points)
        key = self._key(points, 2).ravel()
        lo = np.searchsorted(self.seg_keys, key, "left")
        counts = np.searchsorted(self.seg_keys, key, "right") - lo
        query = np.repeat(np.repeat(np.arange(q), 25), counts)
        offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        cand = self.seg_order[np.repeat(lo, counts) + offset]
        lonely = np.setdiff1d(np.arange(q), query)
        if len(lonely):   # far from every bucketed segment: all of them
            query = np.concatenate((query, np.repeat(lonely, len(self.seg_start))))
            cand = np.concatenate((cand, np.tile(np.arange(len(self.seg_start)), len(lonely))))
        a, b = self.points[self.seg_start[cand]], self.points[self.seg_end[cand]]
        d = b - a
        x = points[query]
        t = np.clip(((x - a) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-30), 0.0, 1.0)
        dist = ((x - a - t[:, None] * d) ** 2).sum(-1)
        order = np.lexsort((dist, query))
        first = order[np.r_[True, query[order][1:] != query[order][:-1]]]
        best = cand[first]
        return self.seg_owner[best], self.seg_pos[best], t[first]

    def path(self, index: int, vertices: np.ndarray, start: np.ndarray | None = None,
             end: np.ndarray | None = None, closed: bool = False) -> np.ndarray:
        """``start``, the (refined) points ``vertices`` (positions along contour ``index``, in
        order) and ``end`` as ``(n, 2)``, with the image's corners that the pixel-centre grid
        cuts put back: between two consecutive points of the border on two edges of the image
        (``closed``: the last and the first too)."""
        parts = [p[None] for p in (start,) if p is not None]
        parts.append(self.points[self.contours[index][vertices]])
        parts += [p[None] for p in (end,) if p is not None]
        pts = np.concatenate(parts)
        if len(pts) < 2:
            return pts
        h, w = self.size
        lines = np.array([-0.5, -0.5, w - 0.5, h - 0.5])
        on = np.abs(pts[:, [0, 1, 0, 1]] - lines) < 2e-3              # (n, 4): on each edge
        upright = on[:, 0] | on[:, 2]
        level = on[:, 1] | on[:, 3]
        nxt = np.roll(np.arange(len(pts)), -1)
        pairs = np.arange(len(pts) if closed else len(pts) - 1)
        a, b = pairs, nxt[pairs]
        near = np.abs(pts[b] - pts[a]).max(-1) < 3
        turn_a = upright[a] & ~level[a] & level[b] & ~upright[b] & near   # corner (a.u, b.v)
        turn_b = level[a] & ~upright[a] & upright[b] & ~level[b] & near   # corner (b.u, a.v)
        if not (turn_a.any() or turn_b.any()):
            return pts
        corner = np.where(turn_a[:, None], np.stack((pts[a, 0], pts[b, 1]), -1),
                          np.stack((pts[b, 0], pts[a, 1]), -1))
        out = []
        for k in range(len(pts)):
            out.append(pts[k])
            if k < len(pairs) and (turn_a[k] or turn_b[k]):
                out.append(corner[k])
        return np.asarray(out)


def _valid_grid(change: _Change, sample: int, valid: Tensor | None) -> np.ndarray:
    """``(H, W)`` bool: where the output pixel centres of ``sample`` are valid (``valid``, the
    renderer's mask of that sample, else ``change.backward``'s)."""
    if valid is not None:
        return valid.detach().to("cpu", torch.bool).numpy()
    h, w = change.output.image_size
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                          torch.arange(w, dtype=torch.float64), indexing="ij")
    points = torch.stack((u, v), -1).reshape(-1, 2)
    _, ok = change.backward(points, torch.full((len(points),), sample, dtype=torch.long))
    return ok.reshape(h, w).numpy()


def _refine(change: _Change, borders: dict[int, _Border], wanted: dict[int, list]) -> None:
    """Move the border vertices ``wanted[sample]`` (lists of arrays of grid edge indices) onto
    the border, every sample's in one bisection."""
    samples, vertices = [], []
    for sample, lists in wanted.items():
        if not lists:
            continue
        border = borders[sample]
        v = np.unique(np.concatenate(lists))
        v = v[~border.refined[v]]
        samples.append(np.full(len(v), sample))
        vertices.append(v)
    if not vertices or sum(len(v) for v in vertices) == 0:
        return
    sample = np.concatenate(samples)
    vertex = np.concatenate(vertices)
    lo = np.empty((len(vertex), 2))
    hi = np.empty((len(vertex), 2))
    for s in np.unique(sample):
        at = sample == s
        lo[at] = borders[int(s)].valid_end[vertex[at]]
        hi[at] = borders[int(s)].invalid_end[vertex[at]]
    lo_t, hi_t = torch.from_numpy(lo), torch.from_numpy(hi)
    st = torch.from_numpy(sample).long()
    for _ in range(_BORDER_STEPS):
        mid = 0.5 * (lo_t + hi_t)
        _, ok = change.backward(mid, st)
        lo_t, hi_t = torch.where(ok[:, None], mid, lo_t), torch.where(ok[:, None], hi_t, mid)
    lo = lo_t.numpy()
    for s in np.unique(sample):
        at = sample == s
        border = borders[int(s)]
        border.points[vertex[at]] = lo[at]
        border.refined[vertex[at]] = True


def _pip(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """``(Q,)`` True where ``points (Q, 2)`` lie inside the closed ``ring (N, 2)`` (even-odd)."""
    a, b = ring, np.roll(ring, -1, axis=0)
    py = points[:, None, 1]
    cond = (a[None, :, 1] > py) != (b[None, :, 1] > py)
    dy = np.where(b[:, 1] == a[:, 1], 1.0, b[:, 1] - a[:, 1])
    x = a[None, :, 0] + (py - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / dy[None]
    return ((cond & (points[:, None, 0] < x)).sum(-1) % 2) == 1


def _area(ring: np.ndarray) -> float:
    """Shoelace area of ``ring (N, 2)``: positive where its inside lies on its left."""
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _bridge(outer: np.ndarray, hole: np.ndarray) -> np.ndarray | None:
    """``outer`` with ``hole`` (inside it, the other way round) joined by a zero-width cut along
    the ray from the hole's rightmost point to the first edge of ``outer`` it meets (None where
    none: the hole is dropped)."""
    k = int(hole[:, 0].argmax())
    m = hole[k]
    a, b = outer, np.roll(outer, -1, axis=0)
    cond = (a[:, 1] > m[1]) != (b[:, 1] > m[1])
    dy = np.where(cond, b[:, 1] - a[:, 1], 1.0)
    x = a[:, 0] + (m[1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
    hit = cond & (x >= m[0])
    if not hit.any():
        return None
    j = int(np.where(hit, x, np.inf).argmin())
    i = np.array([x[j], m[1]])
    turned = np.concatenate((hole[k:], hole[:k], m[None]))
    return np.concatenate((outer[:j + 1], i[None], turned, i[None], outer[j + 1:]))


def _with_holes(rings: list[np.ndarray]) -> list[np.ndarray]:
    """Closed rings of one input ring's region (outer ones counter-clockwise, holes clockwise)
    -> the outer rings, each hole joined to the smallest outer ring around it."""
    areas = [_area(r) for r in rings]
    outers = [r for r, a in zip(rings, areas) if a > 1e-9]
    holes = [r for r, a in zip(rings, areas) if a < -1e-9]
    if not holes or not outers:
        return outers
    outer_areas = [_area(r) for r in outers]
    for hole in sorted(holes, key=lambda r: -float(r[:, 0].max())):
        around = [j for j, r in enumerate(outers) if _pip(hole[:1], r)[0]]
        if not around:
            continue
        j = min(around, key=lambda j: outer_areas[j])
        joined = _bridge(outers[j], hole)
        if joined is not None:
            outers[j] = joined
    return outers


def _axes(change: _Change, n: int) -> tuple[Tensor, Tensor]:
    """Per sample the source pixels ``(n, 3, 2)`` (and where seen ``(n, 3)``) of the directions
    around which the valid area may have a hole that a ring's inside holds: the output's blind
    cone axis (its +z), its back (-z, which it cannot map) and the source's blind cone axis."""
    sample = torch.arange(n)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    rays = torch.stack((z, -z), 1)                                   # output frame
    rays = torch.einsum("nij,nkj->nki", change.rotation, rays)       # R @ ray: source frame
    pixels, seen = change.source.project(rays.reshape(-1, 3), sample.repeat_interleave(2))
    pixels, seen = pixels.reshape(n, 2, 2), seen.reshape(n, 2)
    blind = change.output.blind_fov
    seen[:, 0] &= torch.zeros(n, dtype=torch.bool) if blind is None else blind > 0
    src_blind = change.source.blind_fov
    if change.source.params is not None and src_blind is not None and bool((src_blind > 0).any()):
        p, s = change.source.project(z, sample)
        s = s & (src_blind > 0)
    else:
        p, s = torch.zeros(n, 2, dtype=torch.float64), torch.zeros(n, dtype=torch.bool)
    return torch.cat((pixels, p[:, None]), 1), torch.cat((seen, s[:, None]), 1)


def map_rings(change: _Change, rings: Sequence[Sequence[Tensor]], step: float,
              valid: Tensor | None = None) -> tuple[list[list[np.ndarray]], list[np.ndarray]]:
    """Rings of the ``n`` samples of ``change`` through it, clipped to the valid area (module
    docstring).

    Args:
        change: the camera change of ``n`` samples (``render.detection.Change``).
        rings: per sample, its rings ``(N_k, 2)`` float64 corner coordinates.
        step: the most distance, in output pixels, of two consecutive points of a mapped ring
            near the image (``render.detection.OUTLINE_STEP``).
        valid: ``(n, H, W)`` bool, the renderer's valid mask of each sample (None: from
            ``change.backward`` at the output's pixel centres).

    Returns:
        per sample the output rings ``(M_j, 2)`` float64 corner coordinates and ``(M,)`` int64
        the input ring of each.
    """
    n = len(rings)
    flat, where = [], []
    for i, sample in enumerate(rings):
        for k, ring in enumerate(sample):
            r = ring - 0.5
            keep = (r != torch.roll(r, 1, 0)).any(-1)
            if int(keep.sum()) >= 3:
                flat.append(r[keep])
                where.append((i, k))
    out = [[] for _ in range(n)]
    index = [[] for _ in range(n)]
    if not flat:
        return out, [np.zeros(0, dtype=np.int64) for _ in range(n)]
    sample_of = torch.tensor([i for i, _ in where])
    dense = _Dense(change, flat, sample_of, step)
    parts = list(zip(*(t.split(dense.sizes.tolist()) for t in (
        dense.pix, dense.ok, dense.cross, torch.arange(len(dense.edge))))))
    axes, axes_seen = _axes(change, n)
    borders: dict[int, _Border] = {}
    slow = []
    for r, (pix, ok, cross, at) in enumerate(parts):
        i, k = where[r]
        if bool(ok.all()) and not bool(cross.any()):
            seen = axes_seen[i]
            if not bool(seen.any()) or not _pip(axes[i][seen].numpy(), flat[r].numpy()).any():
                out[i].append(pix.numpy() + 0.5)
                index[i].append(k)
                continue
        if not bool(ok.any()) and not bool(cross.any()):
            # no seen point: only a part of the valid area wholly inside could come out, which
            # needs the ring to reach over the source image
            hs, ws = change.source.image_size
            lo, hi = flat[r].amin(0), flat[r].amax(0)
            if (valid is not None and not bool(valid[i].any())) or bool(
                    (hi[0] < -0.5) | (lo[0] > ws - 0.5) | (hi[1] < -0.5) | (lo[1] > hs - 0.5)):
                continue
        slow.append(r)
    if slow:
        for r in slow:
            i = where[r][0]
            if i not in borders:
                borders[i] = _Border(_valid_grid(change, i, None if valid is None else valid[i]),
                                     _centre_validity(change, i))
        _clip(change, dense, parts, flat, where, slow, borders, out, index)
    return ([[np.asarray(r) for r in rs] for rs in out],
            [np.asarray(ix, dtype=np.int64) for ix in index])


def _centre_validity(change: _Change, sample: int):
    """A function: output points ``(Q, 2)`` (numpy) -> where ``sample`` sees them."""
    def valid_at(points: np.ndarray) -> np.ndarray:
        pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float64))
        _, ok = change.backward(pts, torch.full((len(pts),), sample, dtype=torch.long))
        return ok.numpy()
    return valid_at


def _orientations(change: _Change, dense: _Dense, parts: list, slow: list[int],
                  flat: list[Tensor]) -> dict[int, bool]:
    """Per slow ring with a seen point: whether its mapped ring has its inside on its right
    (then it is walked backwards): the sign of its source area times that of the change's
    Jacobian at its first seen point."""
    rings = [r for r in slow if bool(parts[r][1].any())]
    if not rings:
        return {}
    at = torch.stack([parts[r][3][parts[r][1]][0] for r in rings])
    src = dense.source(at)
    h = 1e-3
    sample = dense.esample[dense.edge[at]]
    pts = torch.cat((src, src + torch.tensor([h, 0.0], dtype=torch.float64),
                     src + torch.tensor([0.0, h], dtype=torch.float64)))
    pix, _ = change.forward(pts, sample.repeat(3))
    p0, px, py = pix.split(len(rings))
    dx, dy = px - p0, py - p0
    det = dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]
    return {r: _area(flat[r].numpy()) * float(d) < 0 for r, d in zip(rings, det.tolist())}


def _clip(change: _Change, dense: _Dense, parts: list, flat: list[Tensor], where: list,
          slow: list[int], borders: dict[int, _Border], out: list, index: list) -> None:
    """The rings ``slow`` (cut by the valid area's border, or holding a part of it) clipped:
    their seen runs joined along the border, and the parts of the border inside them."""
    backwards = _orientations(change, dense, parts, slow, flat)
    plans = {}
    # 1. each ring's crossings, kinds (entry / exit) and their places on the border
    for r in slow:
        pix, ok, cross = (t.numpy() for t in parts[r][:3])
        if backwards.get(r, False):
            pix, ok, cross = pix[::-1].copy(), ok[::-1].copy(), cross[::-1].copy()
        at = np.nonzero(cross)[0]
        kind = np.where(ok[(at + 1) % len(ok)], 1, -1)              # +1 entry, -1 exit
        plans[r] = {"pix": pix, "ok": ok, "at": at, "kind": kind}
    wanted: dict[int, list] = {}
    for r in slow:
        plan, border = plans[r], borders[where[r][0]]
        if len(plan["at"]):
            contour, pos, _ = border.locate(plan["pix"][plan["at"]])
            for c, p in zip(contour.tolist(), pos.tolist()):
                loop = border.contours[c]
                near = np.arange(p - 2, p + 4) % len(loop)
                wanted.setdefault(where[r][0], []).append(loop[near])
        for loop in border.contours:   # one vertex per contour: is it inside the ring?
            wanted.setdefault(where[r][0], []).append(loop[:1])
    _refine(change, borders, wanted)
    # probes: the source point of each contour's first vertex
    probes = {}
    for i, border in borders.items():
        first = np.array([border.points[loop[0]] for loop in border.contours])
        src, _ = change.backward(torch.from_numpy(first),
                                 torch.full((len(first),), i, dtype=torch.long))
        probes[i] = src.numpy()
    # 2. links along the border, and the parts of the border inside each ring
    wanted = {}
    for r in slow:
        i = where[r][0]
        plan, border = plans[r], borders[i]
        inside = _pip(probes[i], flat[r].numpy())
        plan["links"], plan["islands"] = {}, []
        touched = set()
        if len(plan["at"]):
            contour, pos, frac = border.locate(plan["pix"][plan["at"]])
            s = pos + frac
            touched = set(contour.tolist())
            links = _link(plan["kind"], contour, s, [len(c) for c in border.contours])
            if links is None:   # the border's order contradicts itself: chords between runs
                links = _chords(plan["kind"])
            plan["links"] = links
            for _, c, verts in links.values():
                if len(verts):
                    wanted.setdefault(i, []).append(border.contours[c][verts])
        for c, loop in enumerate(border.contours):
            if c not in touched and inside[c]:
                plan["islands"].append(c)
                wanted.setdefault(i, []).append(loop)
    _refine(change, borders, wanted)
    # 3. the rings
    for r in slow:
        i, k = where[r]
        plan, border = plans[r], borders[i]
        rings = _assemble(plan, border)
        rings += [border.path(c, np.arange(len(border.contours[c])), closed=True)
                  for c in plan["islands"]]
        for ring in _with_holes(rings):
            keep = np.abs(ring - np.roll(ring, 1, axis=0)).max(-1) > 1e-9
            if keep.sum() >= 3:
                out[i].append(ring[keep] + 0.5)
                index[i].append(k)


def _link(kind: np.ndarray, contour: np.ndarray, s: np.ndarray, lengths: list[int]
          ) -> dict | None:
    """Per exit (crossing number), the entry where the clipped ring comes back to the ring
    along the border: the next crossing along its contour in the border's direction (the
    valid area on the left), with the contour's vertices between ``(entry, contour,
    positions)``; None where that is not a one-to-one match of exits and entries."""
    links, taken = {}, set()
    exits = np.nonzero(kind < 0)[0]
    for x in exits.tolist():
        c = int(contour[x])
        n = lengths[c]
        same = np.nonzero((contour == c) & (kind > 0))[0]
        if len(same) == 0:
            return None
        ahead = (s[same] - s[x]) % n
        behind = np.where(ahead > n - _BEHIND, n - ahead, np.inf)
        if np.isfinite(behind).any():
            y = int(same[behind.argmin()])
            verts = np.zeros(0, dtype=np.int64)
        else:
            y = int(same[ahead.argmin()])
            start, stop = math.floor(s[x]), math.floor(s[y])
            count = (stop - start) % n
            if count == 0 and s[y] < s[x]:
                count = n
            verts = (start + 1 + np.arange(count)) % n
        if y in taken:
            return None
        taken.add(y)
        links[x] = (y, c, verts)
    return links


def _chords(kind: np.ndarray) -> dict:
    """Each exit joined straight to the next entry along the ring (the fallback of
    `_link`)."""
    n = len(kind)
    links = {}
    for x in np.nonzero(kind < 0)[0].tolist():
        y = next(j % n for j in range(x + 1, x + n + 1) if kind[j % n] > 0)
        links[x] = (y, -1, np.zeros(0, dtype=np.int64))
    return links


def _assemble(plan: dict, border: _Border) -> list[np.ndarray]:
    """The closed rings of one ring's seen runs and the border paths between them; the whole
    mapped ring where it is seen all along."""
    pix, ok, at, kind = plan["pix"], plan["ok"], plan["at"], plan["kind"]
    if len(at) == 0:
        return [pix] if ok.all() else []
    n = len(pix)
    rings, used = [], set()
    for e0 in np.nonzero(kind > 0)[0].tolist():
        if e0 in used:
            continue
        pieces, e = [], e0
        while e not in used:
            used.add(e)
            start = int(at[e])
            x = (e + 1) % len(at)                      # the next crossing along the ring: an exit
            stop = int(at[x])
            run = (start + np.arange((stop - start) % n + 1)) % n
            pieces.append(pix[run])
            y, c, verts = plan["links"][x]
            if c >= 0:
                path = border.path(c, verts, start=pix[stop], end=pix[int(at[y])])
                pieces.append(path[1:-1])
            e = y
        if e == e0 and pieces:
            rings.append(np.concatenate(pieces))
    return rings

