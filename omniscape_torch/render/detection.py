"""Detection targets through a camera change: keypoints, boxes, and boxes of instance maps.

The geometry that `RandomReproject`,
`RandomOmniCamera` and `reproject_boxes` /
`reproject_keypoints` (next to `reproject`) share. Coordinates
follow torchvision's XYXY convention for boxes and keypoints: corner coordinates, the pixel of
centre ``(u, v)`` spans ``[u, u + 1] x [v, v + 1]`` (the package's pixel-centre coordinates
plus 0.5, converted here and only here).

* Keypoints map exactly: a keypoint's ray from the source camera, rotated, projected by the
  output camera. It is valid where the source sees it (in the source image, its model's domain
  and cones) and the output sees it (in the output image, its model's domain, its ``fov``
  and outside its blind cone), else its coordinates are NaN.
* A box from its outline (``reproject_boxes``): the box region is mapped through the cameras
  and its tight box in the output is taken, clipped to the output's valid area. The outline is
  sampled every `FIRST_STEP` source pixels and mapped; a box whose mapped samples near
  the output image lie more than `OUTLINE_STEP` output pixels apart (a camera that
  magnifies it more than twice) is sampled again that much finer, so a straight edge's curved
  image is missed by at most its sagitta, ``OUTLINE_STEP**2 / (8 rho)`` for a curvature radius
  ``rho`` (against a sampling every 0.25 px: at most 0.018 px over 2303 boxes of 8 to 300 px
  at 512 x 512, equidistant, Kannala-Brandt, EUCM, double sphere, unified and cropped
  equisolid draws). Where the outline leaves the valid area (the ``fov`` and blind cones, the
  output image's edges, the source's), the object's output pixels are found one by one: the
  pixels of a window that holds the whole mapped region (the extent of the mapped outline, its
  points seen or not, one pixel wider; the whole image where a point of the outline is not
  mapped by both models or the output camera's back direction lies in the box) whose rays
  land in the source box and are valid, scanned from each side to the first that does; the box
  is then the tight box of those pixels. ``RandomReproject`` scans the rays its sampler
  samples the image along (the C++ op ``box_pixels``, as ``sample_image`` projects them), so
  these boxes are those of the pixels its labels give the object; elsewhere the window's
  pixels are mapped back here. Elsewhere the tight box of the object's *pixels* (pixel centres
  inside the mapped region) differs from the continuous box by up to half a pixel per side, a
  little more at a sharp corner or for an object thinner than a pixel; tests hold boxes within
  1 px of their objects' pixels.
* A box from an instance map (`instance_boxes`): the tight box of the output pixels of
  its instance id, exact.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from ..cameras._checks import not_a_camera
from ..cameras.registry import get_model
from ..cubemap.faces import face_rotations
from . import polygons as polygon_rings
from .kernels import boxes as boxes_kernels
from .kernels.boxes import extent
from .polygons import check_per_sample, check_polygons

__all__ = ["instance_boxes", "reproject_boxes", "reproject_keypoints", "reproject_polygons",
           "OUTLINE_STEP", "FIRST_STEP"]

#: Largest spacing, in output pixels, of the samples of a box's outline near the image.
OUTLINE_STEP = 16.0
#: Spacing, in source pixels, of the first samples of a box's outline (refined where they land
#: further than OUTLINE_STEP apart: where the camera magnifies more than twice).
FIRST_STEP = 8.0
#: Fewest samples per edge of a box's outline.
_FEWEST = 4
#: Most samples per edge (a box stretched past this is sampled coarser).
_MAX_PER_EDGE = 4096


class Side(NamedTuple):
    """One side of a camera change, per sample: ``model`` (registry name), ``params (n, P)``
    float64, ``image_size (H, W)``, and the cones ``fov``, ``blind_fov`` (``(n,)`` radians, or
    None). ``params`` None: a cubemap (rays given by (face, x, y) points)."""

    model: str | None
    params: Tensor | None
    image_size: tuple[int, int] | None
    fov: Tensor | None = None
    blind_fov: Tensor | None = None

    @staticmethod
    def of(camera: Camera, n: int) -> "Side":
        """A `Camera` (one, or a batch ``(n,)``) for ``n`` samples."""
        params = camera.params.detach().to("cpu", torch.float64)
        params = params.reshape(-1, params.shape[-1]).expand(n, -1)
        cone = (lambda a: None if a is None else torch.full((n,), float(a), dtype=torch.float64))
        return Side(camera.model.name, params, tuple(camera.image_size), cone(camera.fov),
                    cone(camera.blind_fov))

    def rows(self, index: Tensor) -> "Side":
        """The samples ``index`` of this side."""
        pick = (lambda t: None if t is None else t[index])
        return Side(self.model, pick(self.params), self.image_size, pick(self.fov),
                    pick(self.blind_fov))

    def cones(self, rays: Tensor, sample: Tensor | None) -> Tensor:
        """``(T,)`` True where unit ``rays (T, 3)`` of samples ``sample (T,)`` lie in the cones
        (``sample`` None: ``rays (n, M, 3)``, row i of sample i)."""
        ok = torch.ones(rays.shape[:-1], dtype=torch.bool)
        if self.fov is not None:
            ok = ok & (rays[..., 2] >= _rows(torch.cos(0.5 * self.fov), sample))
        if self.blind_fov is not None and bool((self.blind_fov > 0).any()):
            blind = torch.where(self.blind_fov > 0, torch.cos(0.5 * self.blind_fov), 2.0)
            ok = ok & (rays[..., 2] < _rows(blind, sample))
        return ok

    def in_image(self, pixels: Tensor) -> Tensor:
        h, w = self.image_size
        u, v = pixels[..., 0], pixels[..., 1]
        return (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)

    def unproject(self, points: Tensor, sample: Tensor, domain: bool = False) -> tuple:
        """Pixel centres ``(T, 2)`` (a cube: ``(T, 3)`` face, u, v) of samples ``sample`` ->
        unit rays ``(T, 3)`` and where they are seen (``domain``: and where the model maps
        them, wherever they lie)."""
        if self.params is None:
            rays, ok = _cube_rays(points)
            return (rays, ok, ok) if domain else (rays, ok)
        rays, ok = get_model(self.model).unproject(points, _rows(self.params, sample))
        rays = torch.nn.functional.normalize(rays, dim=-1)
        seen = ok & self.in_image(points) & self.cones(rays, sample)
        return (rays, seen, ok) if domain else (rays, seen)

    def project(self, rays: Tensor, sample: Tensor, domain: bool = False) -> tuple:
        """Unit ``rays (T, 3)`` of samples ``sample`` -> pixel centres ``(T, 2)`` and where
        they are seen (``domain``: and where the model maps them, wherever they land)."""
        pixels, ok = get_model(self.model).project(rays, _rows(self.params, sample))
        ok = ok & torch.isfinite(pixels).all(-1)
        seen = ok & self.in_image(pixels) & self.cones(rays, sample)
        return (pixels, seen, ok) if domain else (pixels, seen)


class Change(NamedTuple):
    """A camera change for ``n`` samples: ``ray_source = rotation @ ray_output``."""

    source: Side
    output: Side
    rotation: Tensor          # (n, 3, 3) float64

    def forward(self, points: Tensor, sample: Tensor, domain: bool = False) -> tuple:
        """Source pixel centres ``(T, 2)`` (cube: ``(T, 3)``) -> output pixel centres ``(T, 2)``
        and where both cameras see them (``domain``: and where both models map them, seen or
        not)."""
        rays, ok, mapped = self.source.unproject(points, sample, domain=True)
        rays = _turn(rays, self.rotation, sample, back=True)
        pixels, seen, through = self.output.project(rays, sample, domain=True)
        if domain:
            return pixels, ok & seen, mapped & through
        return pixels, ok & seen

    def backward(self, pixels: Tensor, sample: Tensor) -> tuple[Tensor, Tensor]:
        """Output pixel centres ``(T, 2)`` -> source pixel centres and where both see them."""
        rays, ok = self.output.unproject(pixels, sample)
        rays = _turn(rays, self.rotation, sample)
        points, seen = self.source.project(rays, sample)
        return points, ok & seen


def _rows(t: Tensor, sample: Tensor | None) -> Tensor:
    """Per-sample rows ``t (n, ...)`` for points of samples ``sample (T,)``, or (``sample``
    None) for points ``(n, M, ...)``, broadcasting."""
    return t[sample] if sample is not None else t[:, None]


def _turn(rays: Tensor, rotation: Tensor, sample: Tensor | None, back: bool = False) -> Tensor:
    """``R @ ray`` (``back``: ``R^T @ ray``) of ``rays (T, 3)`` of samples ``sample``, or
    (``sample`` None) ``rays (n, M, 3)`` by ``rotation (n, 3, 3)``."""
    if sample is None:
        return torch.matmul(rays, rotation if back else rotation.transpose(1, 2))
    if back:
        return torch.bmm(rays[:, None, :], rotation[sample])[:, 0]
    return torch.bmm(rotation[sample], rays[:, :, None])[:, :, 0]


def _cube_rays(points: Tensor) -> tuple[Tensor, Tensor]:
    """``(..., 3)`` rows ``(face, x, y)`` of `cube_points` (``x = (u - c) / f``) -> unit
    rays in the cube frame, and where the point lies on its face."""
    face = points[..., 0].long()
    local = torch.cat((points[..., 1:], torch.ones_like(points[..., :1])), -1)
    rays = torch.einsum("...ij,...j->...i", face_rotations(torch.float64)[face], local)
    on_face = (points[..., 1:].abs() <= 1 + 1e-9).all(-1)
    return torch.nn.functional.normalize(rays, dim=-1), on_face


def cube_points(keypoints: Tensor, face_size: int) -> Tensor:
    """Cube keypoints ``(..., 3)`` rows ``(face, x, y)`` in corner coordinates of a face of
    ``face_size`` -> rows ``(face, (u - c) / f, (v - c) / f)`` that `Side` reads (NaN
    rows and faces outside 0..5 are left to the caller's checks)."""
    f, c = face_size / 2, (face_size - 1) / 2
    return torch.cat((keypoints[..., :1], (keypoints[..., 1:] - 0.5 - c) / f), -1)


# -------------------------------------------------------------------------------------------
# Input checks
# -------------------------------------------------------------------------------------------
def check_boxes(boxes: object, batch: int, name: str = "boxes") -> list[Tensor]:
    """``boxes``: a list of ``batch`` ``(N_i, 4)`` XYXY tensors (a tensor ``(B, N, 4)`` is read
    as that list) -> the list as float64 on the CPU; raises naming the sample."""
    if isinstance(boxes, Tensor) and boxes.dim() == 3:
        boxes = list(boxes.detach().to("cpu", torch.float64))
    check_per_sample(boxes, batch, name, "a list of B (N_i, 4) XYXY tensors")
    out = []
    for i, b in enumerate(boxes):
        b = torch.as_tensor(b)
        if b.numel() == 0:
            b = b.reshape(0, 4)
        if b.dim() != 2 or b.shape[-1] != 4 or b.is_complex():
            raise ValueError(f"{name}[{i}]: expected (N, 4) x0, y0, x1, y1, got "
                             f"{tuple(b.shape)}")
        out.append(b)
    flat = torch.cat(out).detach().to("cpu", torch.float64)   # one conversion for the batch
    sizes = [len(b) for b in out]
    for bad, what in ((~torch.isfinite(flat).all(-1), "boxes must be finite: NaN or inf"),
                      ((flat[:, 2:] < flat[:, :2]).any(-1),
                       "expected x0 <= x1 and y0 <= y1 (XYXY corner coordinates)")):
        if bool(bad.any()):
            first = int(bad.nonzero()[0, 0])
            i = int(torch.searchsorted(torch.tensor(sizes).cumsum(0), first, right=True))
            raise ValueError(f"{name}[{i}]: {what} (sample {i}: {flat[first].tolist()})")
    return list(flat.split(sizes))


def check_keypoints(keypoints: object, batch: int, columns: int = 2,
                    name: str = "keypoints") -> Tensor:
    """``(B, K, columns)`` keypoints (``(K, columns)`` shared by the batch) as float64 on the
    CPU; NaN rows are missing keypoints (they come back invalid)."""
    kp = torch.as_tensor(keypoints).detach()
    if kp.dim() == 2:
        kp = kp.expand(batch, *kp.shape)
    layout = "(x, y)" if columns == 2 else "(face, x, y)"
    if kp.dim() != 3 or kp.shape[-1] != columns or kp.is_complex():
        raise ValueError(f"{name}: expected (B, K, {columns}) rows {layout}, got "
                         f"{tuple(kp.shape)}")
    if kp.shape[0] != batch:
        raise ValueError(f"{name}: {kp.shape[0]} samples, the batch has {batch}")
    kp = kp.to("cpu", torch.float64)
    if bool(torch.isinf(kp).any()):
        raise ValueError(f"{name}: infinite coordinates (sample "
                         f"{int(torch.isinf(kp).any(-1).any(-1).nonzero()[0])}); mark a missing "
                         f"keypoint with NaN")
    if columns == 3:
        face = kp[..., 0]
        bad = torch.isfinite(face) & ((face != face.round()) | (face < 0) | (face > 5))
        if bool(bad.any()):
            raise ValueError(f"{name}: face index must be an integer 0..5 (sample "
                             f"{int(bad.any(-1).nonzero()[0])})")
    return kp


def check_box_ids(ids: object, boxes: list[Tensor] | None, batch: int,
                  name: str = "box_instance_ids") -> list[Tensor]:
    """Per sample ``(N_i,)`` integer instance ids (one per box where ``boxes`` are given)."""
    if isinstance(ids, Tensor) and ids.dim() == 2:
        ids = list(ids)
    if not isinstance(ids, (list, tuple)) or len(ids) != batch:
        raise ValueError(f"{name}: expected a list of {batch} (N_i,) integer tensors, got "
                         f"{type(ids).__name__}"
                         f"{f' of length {len(ids)}' if hasattr(ids, '__len__') else ''}")
    out = []
    for i, t in enumerate(ids):
        t = torch.as_tensor(t).detach().reshape(-1).cpu()
        if t.is_floating_point() or t.is_complex():
            raise ValueError(f"{name}[{i}]: expected integer instance ids, got {t.dtype}")
        if boxes is not None and len(t) != len(boxes[i]):
            raise ValueError(f"{name}[{i}]: {len(t)} ids for {len(boxes[i])} boxes")
        out.append(t.long())
    return out


def check_ids_present(instances: Tensor, ids: list[Tensor], key: str = "box_instance_ids",
                      where: str = "instances") -> None:
    """Raise where a sample's id has no pixel in its ``instances`` map (any layout whose first
    dimension is the batch); one pass over the map per id (called for the few ids that the
    output lacks: an id the output shows is in the source)."""
    for i, t in enumerate(ids):
        for value in t.tolist():
            if not bool((instances[i] == value).any()):
                raise ValueError(f"{key}[{i}]: instance id {value} has no pixel in "
                                 f"{where}[{i}]")


# -------------------------------------------------------------------------------------------
# Keypoints
# -------------------------------------------------------------------------------------------
def _keypoint_points(keypoints: Tensor, source_size: tuple[int, int] | None
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """Keypoints ``(n, K, 2)`` (cube: ``(n, K, 3)`` from `cube_points`), corner
    coordinates -> the source points to map ``(n K, 2 or 3)`` (pixel centres), their samples
    ``(n K,)`` and where they are given and in the source image ``[0, W] x [0, H]``
    (``source_size``; None for a cube)."""
    n, k, _ = keypoints.shape
    flat = keypoints.reshape(n * k, -1)
    sample = torch.arange(n).repeat_interleave(k)
    given = torch.isfinite(flat).all(-1)
    points = torch.where(given[:, None], flat, torch.zeros_like(flat))
    if source_size is not None:
        h, w = source_size
        x, y = points[:, 0], points[:, 1]
        given = given & (x >= 0) & (x <= w) & (y >= 0) & (y <= h)
        points = points - 0.5
    return points, sample, given


def _keypoint_result(pixels: Tensor, ok: Tensor, given: Tensor, shape: tuple[int, int]
                     ) -> tuple[Tensor, Tensor]:
    """Mapped keypoints (pixel centres) -> ``(n, K, 2)`` corner coordinates, NaN where invalid,
    and ``valid (n, K)``."""
    ok = ok & given
    out = torch.where(ok[:, None], pixels + 0.5, torch.full_like(pixels, math.nan))
    return out.reshape(*shape, 2), ok.reshape(shape)


def map_keypoints(change: Change, keypoints: Tensor, source_size: tuple[int, int] | None
                  ) -> tuple[Tensor, Tensor]:
    """Keypoints ``(n, K, 2)`` (cube: ``(n, K, 3)`` from `cube_points`) of the ``n``
    samples of ``change``, corner coordinates -> ``(n, K, 2)`` corner coordinates (NaN where
    invalid) and ``valid (n, K)``. ``source_size``: the source image's ``(H, W)`` (corner
    coordinates in ``[0, W] x [0, H]``), None for a cube."""
    points, sample, given = _keypoint_points(keypoints, source_size)
    pixels, ok = change.forward(points, sample)
    return _keypoint_result(pixels, ok, given, keypoints.shape[:2])


# -------------------------------------------------------------------------------------------
# Boxes from outlines
# -------------------------------------------------------------------------------------------
def _in_rects(points: Tensor, rects: Tensor) -> Tensor:
    """Where source pixel centres ``points (T, 2)`` lie in their ``rects (T, 4)``."""
    return (points[:, 0] >= rects[:, 0]) & (points[:, 0] <= rects[:, 2]) & \
        (points[:, 1] >= rects[:, 1]) & (points[:, 1] <= rects[:, 3])


#: Pixels a window reaches past the extent of its box's mapped outline samples (which miss the
#: mapped outline's extreme by its sagitta between two samples, far below a pixel).
_MARGIN = 1.0
#: Most pixels mapped back in one call of the scans in torch (`_scan_back`).
_SCAN_CHUNK = 1 << 20


def _scan_back(change: Change, sample: Tensor, windows: Tensor, rects: Tensor) -> Tensor:
    """The pixel scan of `Outline` in torch: per box the extent ``(m, 4)`` (min column,
    min row, max column, max row; -1 where none) of the output pixels of ``windows (m, 4)``
    (inclusive) of its ``sample`` that ``change.backward`` maps, valid, into its source
    ``rects (m, 4)`` (pixel centres)."""
    out = torch.full((len(windows), 4), -1, dtype=torch.long)
    sizes = ((windows[:, 2] - windows[:, 0] + 1) * (windows[:, 3] - windows[:, 1] + 1)).tolist()
    first = 0
    while first < len(windows):
        last, total = first + 1, sizes[first]
        while last < len(windows) and total + sizes[last] <= _SCAN_CHUNK:
            total, last = total + sizes[last], last + 1
        grids = [torch.stack(torch.meshgrid(torch.arange(c0, c1 + 1), torch.arange(r0, r1 + 1),
                                            indexing="xy"), -1).reshape(-1, 2)
                 for c0, r0, c1, r1 in windows[first:last].tolist()]
        box = torch.arange(first, last).repeat_interleave(torch.tensor(sizes[first:last]))
        pixels = torch.cat(grids)
        src, ok = change.backward(pixels.to(torch.float64), sample[box])
        ok = ok & _in_rects(src, rects[box])
        found = extent(pixels.to(torch.float64), ok, box - first, last - first)
        out[first:last] = torch.where(torch.isfinite(found), found, -1.0).long()
        first = last
    return out


def _outlines(change: Change, rects: Tensor, counts: Tensor, owner: Tensor,
              extra: Tensor | None, backend: str = "auto") -> tuple:
    """The outlines of ``rects (m, 4)`` (pixel centres) of samples ``owner (m,)`` (sorted),
    ``counts (m,)`` points per edge, mapped by ``change`` in one call, each sample's points a
    row after its points ``extra (n, K, 2)`` (or None) -> per box ``extents (m, 8)``: the
    extent of its seen points within the output's outer pixel centres, then of its mapped
    points (both models map them, seen or not; inf where none); ``longest (m,)``: the longest
    step between consecutive mapped points of its closed outline of which one lies within
    `OUTLINE_STEP` pixels of those centres; ``flags (m,)``: 1 where a point is not seen
    within them, 2 where one is not mapped; and ``extra``'s output pixels and where seen
    ``(n K, 2), (n K,)`` (None without). ``kernels.boxes.outlines``: the C++ ops or their
    torch twin, by ``backend``."""
    n = len(change.rotation)
    k = 0 if extra is None else extra.shape[1]
    sizes = torch.zeros(n, dtype=torch.long).index_add_(0, owner, 4 * counts)
    columns = k + int(sizes.max()) if len(rects) else k
    m = len(rects)
    if columns == 0:
        return (torch.full((m, 8), math.inf, dtype=torch.float64),
                torch.zeros(m, dtype=torch.float64), torch.zeros(m, dtype=torch.long), None,
                torch.zeros(m, dtype=torch.bool))
    padded = torch.zeros(n, columns, 2, dtype=torch.float64)
    if k:
        padded[:, :k] = extra
    extents, longest, flags, pix, ok = boxes_kernels.outlines(
        rects, counts, owner, padded, k, lambda points: change.forward(points, None, domain=True),
        change.output.image_size, OUTLINE_STEP, backend=backend)
    mapped_extra = None if not k else (pix[:, :k].reshape(-1, 2), ok[:, :k].reshape(-1))
    slots = torch.arange(columns)[None]
    slots = (slots >= k) & (slots < k + sizes[:, None])
    return extents, longest, flags, mapped_extra, _a_side_seen(ok[slots], counts)


def _a_side_seen(seen: Tensor, counts: Tensor) -> Tensor:
    """``(m,)`` True where one side of a box's outline is seen whole: its samples and the
    corner it ends at. ``seen``: the outline points of the ``m`` boxes in their layout
    (``kernels.boxes.outline``: per box its top, right, bottom and left edges, ``counts``
    points each from the edge's first corner)."""
    m = len(counts)
    which = torch.arange(m).repeat_interleave(4 * counts)
    pos = torch.arange(len(which)) - (torch.cumsum(4 * counts, 0) - 4 * counts)[which]
    side = pos // counts[which]
    missed = torch.zeros(4 * m, dtype=torch.long).index_add_(0, 4 * which + side,
                                                             (~seen).long())
    corner = seen[pos % counts[which] == 0].reshape(m, 4)         # each side's first corner
    return ((missed.reshape(m, 4) == 0) & corner.roll(-1, 1)).any(-1)


class Outline:
    """Boxes of the ``n`` samples of a `Change` mapped by their outlines (module
    docstring), in two steps: the outlines (on construction), then the pixels of the boxes that
    the valid area cuts, read from the rays a renderer samples along (`scan`) or mapped
    back here (`result`).

    ``boxes``: per sample ``(N_i, 4)`` XYXY corner coordinates, clipped to the source image
    ``source_size`` first (none left: dropped); ``extra``: points ``(n, K, 2)`` mapped by
    ``change.forward`` in the same call as the outlines (``mapped``: their pixels and where
    seen, ``(n K, 2), (n K,)``; None without)."""

    def __init__(self, change: Change, boxes: list[Tensor], source_size: tuple[int, int],
                 extra: Tensor | None = None, backend: str = "auto"):
        self.change, self.n, self.backend = change, len(boxes), backend
        h, w = source_size
        counts = torch.tensor([len(b) for b in boxes])
        flat = torch.cat(boxes)
        owner = torch.arange(self.n).repeat_interleave(counts)
        number = torch.arange(len(flat)) - (torch.cumsum(counts, 0) - counts).repeat_interleave(
            counts)
        clipped = torch.cat((flat[:, :2].clamp(min=0), torch.minimum(
            flat[:, 2:], torch.tensor([w, h], dtype=flat.dtype))), -1)
        keep = (clipped[:, 2:] > clipped[:, :2]).all(-1)
        rects, owner, number = clipped[keep] - 0.5, owner[keep], number[keep]  # pixel centres
        self.rects, self.owner, self.number = rects, owner, number
        r = len(rects)
        oh, ow = change.output.image_size
        self.pixels = torch.full((r, 4), -1, dtype=torch.long)
        self.waiting = []   # (box, sample) of the cut boxes whose pixels are still to read
        # the outlines sampled OUTLINE_STEP source pixels apart, mapped with the points
        # ``extra``; where their mapped samples (near the image) lie further apart, sampled
        # again that much finer (a few boxes, where the camera magnifies)
        src_len = (rects[:, 2:] - rects[:, :2]).amax(-1)
        counts = (src_len / FIRST_STEP).ceil().clamp(_FEWEST, _MAX_PER_EDGE).long()
        extents, longest, flags, self.mapped, self.visible = _outlines(
            change, rects, counts, owner, extra, backend)
        for _ in range(3):
            redo = (longest > OUTLINE_STEP) & (counts < _MAX_PER_EDGE)
            if not bool(redo.any()):
                break
            sub = redo.nonzero()[:, 0]
            counts[sub] = (counts[sub] * longest[sub] / OUTLINE_STEP).ceil().clamp(
                max=_MAX_PER_EDGE).long()
            extents[sub], longest[sub], flags[sub], _, self.visible[sub] = _outlines(
                change, rects[sub], counts[sub], owner[sub], None, backend)
        self.box, span = extents[:, :4], extents[:, 4:]
        if r == 0:
            self.cut, self.windows = torch.zeros(0, dtype=torch.bool), self.pixels
            return
        # the boxes whose outline leaves the valid area, or whose region holds the direction
        # the output camera cannot map (its back, -z), are scanned pixel by pixel in a window
        # that holds the whole mapped region: the extent of its mapped outline, or the image
        back = -change.rotation[:, None, :, 2]           # the output's -z in the source frame
        pole = torch.zeros(r, dtype=torch.bool)
        if change.source.model != "pinhole" or bool((back[..., 2] > 0).any()):   # (z > 0)
            at, seen = (t[:, 0][owner] for t in change.source.project(back, None))
            pole = seen & _in_rects(at, rects)
        self.cut = ((flags & 1) > 0) | pole
        whole = ((flags & 2) > 0) | pole | (longest > OUTLINE_STEP)
        lo = (span[:, :2] - _MARGIN).floor().clamp(min=0)
        hi = torch.minimum((span[:, 2:] + _MARGIN).ceil(),
                           torch.tensor([ow - 1.0, oh - 1.0], dtype=span.dtype))
        image = torch.tensor([0, 0, ow - 1, oh - 1], dtype=torch.long)
        windows = torch.where(whole[:, None], image, torch.cat((lo, hi), -1).long())
        empty = (windows[:, 2:] < windows[:, :2]).any(-1)   # the region misses the image
        self.windows = windows
        todo = (self.cut & ~empty).nonzero()[:, 0]
        self.waiting = list(zip(todo.tolist(), owner[todo].tolist()))

    def scan(self, index: list[int], rays: Tensor, rotation: Tensor | None, k: Tensor,
             valid: Tensor | None) -> None:
        """Read the pixels of the cut boxes of the samples ``index`` (m, of this change) from
        the rays ``(m, h, w, 3)`` a renderer samples the source along: the C++ op
        ``box_pixels`` or its twin (``kernels.boxes``), as ``sample_image`` projects them (``rotation (m, 3, 3)`` or
        None, the pinhole ``k (1 or m, 4)``, ``valid (m, h, w)``)."""
        at = {sample: i for i, sample in enumerate(index)}
        todo = [(j, at[sample]) for j, sample in self.waiting if sample in at]
        if not todo:
            return
        self.waiting = [(j, sample) for j, sample in self.waiting if sample not in at]
        rows, samples = (torch.tensor(t) for t in zip(*todo))
        self.pixels[rows] = boxes_kernels.box_pixels(
            rays, rotation, k, valid, samples, self.windows[rows], self.rects[rows],
            backend=self.backend)

    def result(self, dtype: torch.dtype = torch.float64, visible: bool = False) -> tuple:
        """Per sample the output boxes in ``dtype`` and ``box_index (M_i,)``, the cut boxes
        not scanned yet mapped back here (`_scan_back`); ``visible``: and per sample
        ``box_visible (M_i,)`` bool, True where one side of the box is seen whole in the
        output (its object, which touches every side of its tight box, then has a point in
        view), False where none is (the object may lie wholly outside the valid area while
        the box frames the part of the box's region that is seen)."""
        if self.waiting:
            rows, samples = (torch.tensor(t) for t in zip(*self.waiting))
            self.pixels[rows] = _scan_back(self.change, samples, self.windows[rows],
                                           self.rects[rows])
            self.waiting = []
        # a cut box: the extent of its pixels (their edges, in pixel-centre coordinates)
        found = (self.pixels >= 0).all(-1)
        pixel_box = torch.where(found[:, None], self.pixels.to(torch.float64)
                                + torch.tensor([-0.5, -0.5, 0.5, 0.5], dtype=torch.float64),
                                math.inf)
        box = torch.where(self.cut[:, None], pixel_box, self.box)
        # pixel-centre extent -> corner coordinates: +0.5, and the image's edge where it
        # reaches the outer pixel centres
        oh, ow = self.change.output.image_size
        limit = torch.tensor([ow - 1.0, oh - 1.0], dtype=box.dtype)
        lo = torch.where(box[:, :2] <= 1e-6, torch.zeros_like(box[:, :2]), box[:, :2] + 0.5)
        hi = torch.where(box[:, 2:] >= limit - 1e-6, limit + 1, box[:, 2:] + 0.5)
        box = torch.cat((lo, hi), -1)
        kept = torch.isfinite(box).all(-1) & (box[:, 2:] > box[:, :2]).all(-1)
        sizes = torch.bincount(self.owner[kept], minlength=self.n).tolist()   # owner sorted
        out = (list(box[kept].to(dtype).split(sizes)), list(self.number[kept].split(sizes)))
        return (*out, list(self.visible[kept].split(sizes))) if visible else out


# -------------------------------------------------------------------------------------------
# Boxes from instance maps
# -------------------------------------------------------------------------------------------
def _hits(instances: Tensor, ids: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The pixels of one map ``instances (H, W)`` holding one of ``ids (M,)``: their flat
    indices ``(T,)``, the position in ``ids`` of each ``(T,)``, and the order sorting ``ids``."""
    order = torch.argsort(ids)
    ordered = ids[order].to(instances.device)
    flat = instances.reshape(-1).long()
    pos = torch.searchsorted(ordered, flat).clamp_(max=len(ids) - 1)
    where = (ordered[pos] == flat).nonzero()[:, 0]
    return where.cpu(), order[pos[where].cpu()], order


def _instance_extent(instances: Tensor, ids: Tensor) -> Tensor:
    """``(M, 4)`` tight XYXY corner box of the pixels of each id of ``ids (M,)`` in one map
    ``instances (H, W)`` (inf where an id has no pixel)."""
    if len(ids) == 0:
        return torch.zeros(0, 4, dtype=torch.float64)
    w = instances.shape[1]
    where, which, _ = _hits(instances, ids)
    points = torch.stack((where % w, where // w), -1).to(torch.float64)
    box = extent(points, torch.ones(len(where), dtype=torch.bool), which, len(ids))
    box[:, 2:] += 1                          # the last pixel's far edge
    return box


def instance_boxes(instances: Tensor, ids: Sequence[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
    """Tight boxes of instance ids in instance maps.

    Args:
        instances: ``(B, H, W)`` (or ``(B, 1, H, W)``) integer instance ids, any range.
        ids: per sample, the ``(N_i,)`` ids to box.

    Returns:
        per sample ``boxes (M_i, 4)`` float64 XYXY corner coordinates (the tight box of the
        id's pixels: columns ``u0..u1`` give ``x0 = u0``, ``x1 = u1 + 1``) and ``box_index
        (M_i,)`` int64, the position in ``ids[i]`` of each box; ids with no pixel are dropped.

    Examples:
        >>> inst = torch.zeros(1, 8, 8, dtype=torch.int64); inst[0, 2:4, 3:7] = 300
        >>> boxes, index = instance_boxes(inst, [torch.tensor([300, 7])])
        >>> boxes[0].tolist(), index[0].tolist()
        ([[3.0, 2.0, 7.0, 4.0]], [0])
    """
    if not isinstance(instances, Tensor) or instances.is_floating_point():
        raise TypeError("instances: expected an integer tensor (B, H, W)")
    if instances.dim() == 4 and instances.shape[1] == 1:
        instances = instances[:, 0]
    if instances.dim() != 3:
        raise ValueError(f"instances: expected (B, H, W), got {tuple(instances.shape)}")
    ids = check_box_ids(ids, None, instances.shape[0], "ids")
    boxes, index = [], []
    for i, t in enumerate(ids):
        extent = _instance_extent(instances[i], t)
        kept = torch.isfinite(extent).all(-1)
        boxes.append(extent[kept])
        index.append(kept.nonzero()[:, 0])
    return boxes, index


class Targets:
    """Keypoints, boxes and polygons of a batch through its camera changes, one per group of
    samples ``(sample indices (n,), change)`` (e.g. one per drawn model): the keypoints and the
    boxes' outlines on construction, the cut boxes' pixels from a renderer's rays
    (`scan`, optional), then `result` (the polygons there, clipped to the valid
    mask the renderer made). A box with rings in ``polygons`` (``polygon_box`` says whose) is
    the tight box of its mapped rings; the others come from their outlines."""

    def __init__(self, changes: Sequence[tuple[Tensor, Change]], batch: int, *,
                 keypoints: Tensor | None = None, boxes: list[Tensor] | None = None,
                 source_size: tuple[int, int] | None = None, backend: str = "auto",
                 polygons: list[list[Tensor]] | None = None,
                 polygon_box: list[Tensor] | None = None):
        self.batch, self.keypoints = batch, keypoints
        self.polygons, self.polygon_box = polygons, polygon_box
        self.has_boxes = boxes is not None
        self.outlined = None   # per sample, the input index of each box mapped by its outline
        if boxes is not None and polygons is not None:
            self.outlined = []
            for i, b in enumerate(boxes):
                alone = torch.ones(len(b), dtype=torch.bool)
                alone[polygon_box[i]] = False
                self.outlined.append(alone.nonzero()[:, 0])
            boxes = [b[rows] for b, rows in zip(boxes, self.outlined)]
        self.parts = []   # (sample indices, change, Outline or None, keypoints or None)
        for index, change in changes:
            points = outline = mapped = None
            if keypoints is not None:
                points, _, given = _keypoint_points(keypoints[index], source_size)
            rows = None if points is None else points.reshape(len(index), -1, points.shape[-1])
            if boxes is not None:   # the keypoints mapped with the boxes' outlines
                outline = Outline(change, [boxes[i] for i in index.tolist()], source_size,
                                  extra=rows, backend=backend)
                mapped = outline.mapped
            kp = None
            if points is not None:
                pixels, ok = mapped if mapped is not None else (
                    t.reshape(-1, *t.shape[2:]) for t in change.forward(rows, None))
                kp = _keypoint_result(pixels, ok, given, (len(index), keypoints.shape[1]))
            self.parts.append((index, change, outline, kp))

    def scan(self, index: Tensor, rays: Tensor, rotation: Tensor | None, k: Tensor,
             valid: Tensor | None) -> None:
        """The cut boxes' pixels of the samples ``index (m,)`` of one change (all drawn with
        one model) from the rays a renderer samples them along (`Outline.scan`)."""
        index = index.tolist()
        for part, _, outline, _ in self.parts:
            if outline is None:
                continue
            at = {sample: i for i, sample in enumerate(part.tolist())}
            if all(sample in at for sample in index):
                outline.scan([at[sample] for sample in index], rays, rotation, k, valid)

    def result(self, dtype: torch.dtype = torch.float32,
               box_dtype: torch.dtype = torch.float32, valid: Tensor | None = None,
               polygon_dtype: torch.dtype = torch.float32) -> dict:
        """A dict ``keypoints (B, K, 2)`` in ``dtype``, ``keypoints_valid (B, K)``, ``boxes``
        in ``box_dtype``, ``box_index`` and ``box_visible``, ``polygons`` (per sample a list of
        rings in ``polygon_dtype``) and ``polygon_index`` (per sample lists), those given.
        ``valid``: ``(B, H, W)`` bool, the renderer's valid mask that the polygons are clipped
        to (None: made here, `polygons.map_rings`)."""
        out = {}
        if self.keypoints is not None:
            k = self.keypoints.shape[1]
            out["keypoints"] = torch.full((self.batch, k, 2), math.nan, dtype=dtype)
            out["keypoints_valid"] = torch.zeros(self.batch, k, dtype=torch.bool)
        if self.has_boxes:
            for key in ("boxes", "box_index", "box_visible"):
                out[key] = [None] * self.batch
        if self.polygons is not None:
            out["polygons"], out["polygon_index"] = [None] * self.batch, [None] * self.batch
        for index, change, outline, kp in self.parts:
            if outline is not None:
                got, which, seen = outline.result(box_dtype, visible=True)
                for i, b, w, v in zip(index.tolist(), got, which, seen):
                    if self.outlined is not None:
                        w = self.outlined[i][w]
                    out["boxes"][i], out["box_index"][i], out["box_visible"][i] = b, w, v
            if kp is not None:
                out["keypoints"][index], out["keypoints_valid"][index] = kp[0].to(dtype), kp[1]
            if self.polygons is not None:
                rings, which = polygon_rings.map_rings(
                    change, [self.polygons[i] for i in index.tolist()], OUTLINE_STEP,
                    None if valid is None else valid[index.to(valid.device)])
                for i, r, w in zip(index.tolist(), rings, which):
                    out["polygons"][i] = [torch.from_numpy(ring).to(polygon_dtype) for ring in r]
                    out["polygon_index"][i] = torch.from_numpy(w)
                    if self.has_boxes:
                        self._ring_boxes(out, i, r, w, change.output.image_size, box_dtype)
        return out

    def _ring_boxes(self, out: dict, i: int, rings: list, which, size: tuple[int, int],
                    dtype: torch.dtype) -> None:
        """Sample ``i``'s boxes with rings: the tight box of their mapped rings (clipped to the
        image), merged into ``out``'s outline boxes in the order of the input boxes."""
        boxes, index = out["boxes"][i], out["box_index"][i]
        if boxes is None:
            boxes, index = torch.zeros(0, 4, dtype=dtype), torch.zeros(0, dtype=torch.long)
        extra = torch.zeros(0, 4, dtype=torch.float64)
        number = torch.zeros(0, dtype=torch.long)
        if len(rings):
            owner = self.polygon_box[i][torch.from_numpy(which)].numpy()
            count = int(owner.max()) + 1
            lo = np.full((count, 2), np.inf)
            hi = np.full((count, 2), -np.inf)
            np.minimum.at(lo, owner, np.stack([r.min(0) for r in rings]))
            np.maximum.at(hi, owner, np.stack([r.max(0) for r in rings]))
            h, w = size
            box = torch.from_numpy(np.concatenate((np.maximum(lo, 0.0),
                                                   np.minimum(hi, [float(w), float(h)])), 1))
            kept = torch.isfinite(box).all(-1) & (box[:, 2:] > box[:, :2]).all(-1)
            extra, number = box[kept], kept.nonzero()[:, 0]
        if len(extra):
            boxes = torch.cat((boxes, extra.to(dtype)))
            index = torch.cat((index, number))
        order = torch.argsort(index)
        visible = torch.cat((out["box_visible"][i] if out["box_visible"][i] is not None else
                             torch.zeros(0, dtype=torch.bool),
                             torch.ones(len(number), dtype=torch.bool)))
        out["boxes"][i], out["box_index"][i], out["box_visible"][i] = (
            boxes[order], index[order], visible[order])


def map_targets(changes: Sequence[tuple[Tensor, Change]], batch: int, *,
                keypoints: Tensor | None = None, boxes: list[Tensor] | None = None,
                source_size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float32,
                box_dtype: torch.dtype = torch.float32) -> dict:
    """`Targets`' result, every cut box's pixels mapped back here."""
    return Targets(changes, batch, keypoints=keypoints, boxes=boxes,
                   source_size=source_size).result(dtype, box_dtype)


def boxes_of_instances(instances: Tensor, ids: list[Tensor], source: Tensor,
                       dtype: torch.dtype = torch.float32) -> dict:
    """``boxes`` and ``box_index`` (per sample lists) of the ids ``ids`` in the output instance
    map ``instances (B, H, W)`` (`instance_boxes`), boxes in ``dtype``; raises where an
    id the output lacks has no pixel in the ``source`` instance map either."""
    boxes, index = instance_boxes(instances, ids)
    missing = []
    for t, kept in zip(ids, index):
        lost = torch.ones(len(t), dtype=torch.bool)
        lost[kept] = False
        missing.append(t[lost])
    check_ids_present(source, missing)
    return {"boxes": [b.to(dtype) for b in boxes], "box_index": index,
            "box_visible": [torch.ones(len(t), dtype=torch.bool) for t in index]}


# -------------------------------------------------------------------------------------------
# The functional API, beside ot.reproject
# -------------------------------------------------------------------------------------------
def _change(src_camera: Camera | Tensor, dst_camera: Camera, rotation: Tensor | None,
            batch: int, source_size: tuple[int, int] | None) -> tuple[Change, tuple[int, int]]:
    """The `Change` of ``ot.reproject``'s arguments for ``batch`` samples."""
    from .reproject import intrinsics_from_matrix
    if isinstance(src_camera, Tensor):
        if source_size is None:
            raise ValueError("source_size: a camera matrix K needs the source image's (H, W)")
        src_camera = Camera("pinhole", intrinsics_from_matrix(src_camera, "src_camera"),
                            source_size)
    for name, cam in (("src_camera", src_camera), ("dst_camera", dst_camera)):
        if not isinstance(cam, Camera):
            raise not_a_camera(name, cam)
        shape = tuple(cam.batch_shape)
        if shape not in ((), (batch,)):
            raise ValueError(f"{name}: a batch {shape} for {batch} samples")
    if rotation is None:
        rot = torch.eye(3, dtype=torch.float64).expand(batch, 3, 3)
    else:
        rot = torch.as_tensor(rotation).detach().to("cpu", torch.float64)
        rot = rot.expand(batch, 3, 3) if rot.dim() == 2 else rot
        if rot.shape != (batch, 3, 3):
            raise ValueError(f"rotation: expected (3, 3) or ({batch}, 3, 3), got "
                             f"{tuple(rot.shape)}")
    return (Change(Side.of(src_camera, batch), Side.of(dst_camera, batch), rot),
            tuple(src_camera.image_size))


def reproject_keypoints(keypoints: Tensor, src_camera: Camera | Tensor, dst_camera: Camera, *,
                        rotation: Tensor | None = None,
                        source_size: tuple[int, int] | None = None) -> tuple[Tensor, Tensor]:
    """Keypoints of an image of ``src_camera`` where `reproject`'s image
    in ``dst_camera`` (same arguments) shows them.

    Args:
        keypoints: ``(B, K, 2)`` or ``(K, 2)`` XYXY-convention corner coordinates ``(x, y)``
            (the pixel of centre ``(u, v)`` spans ``[u, u + 1]``); NaN rows are missing.
        src_camera: as for ``ot.reproject`` (a camera matrix ``K`` needs ``source_size``).
        dst_camera: as for ``ot.reproject``.
        rotation: as for ``ot.reproject``: ``ray_src = R @ ray_dst``.
        source_size: ``(H, W)`` of the source image, for a camera matrix ``K``.

    Returns:
        ``keypoints (B, K, 2)`` float64 corner coordinates in the output, NaN where invalid, and
        ``valid (B, K)``: the source sees the keypoint (in its image, model domain and cones)
        and so does the output camera.

    Examples:
        >>> src = Camera("pinhole", [32.0, 32.0, 31.5, 31.5], (64, 64))
        >>> fish = Camera("equidistant", [20.0, 20.0, 31.5, 31.5], (64, 64))
        >>> kp, ok = reproject_keypoints(torch.tensor([[32.0, 32.0]]), src, fish)
        >>> kp.tolist(), ok.tolist()
        ([[[32.0, 32.0]]], [[True]])
    """
    kp = torch.as_tensor(keypoints)
    batch = kp.shape[0] if kp.dim() == 3 else max(
        [c.batch_shape[0] for c in (src_camera, dst_camera)
         if isinstance(c, Camera) and len(c.batch_shape) == 1] + [1])
    kp = check_keypoints(kp, batch)
    change, size = _change(src_camera, dst_camera, rotation, batch, source_size)
    return map_keypoints(change, kp, size)


def reproject_boxes(boxes: Sequence[Tensor] | Tensor, src_camera: Camera | Tensor,
                    dst_camera: Camera, *, rotation: Tensor | None = None,
                    source_size: tuple[int, int] | None = None
                    ) -> tuple[list[Tensor], list[Tensor]]:
    """Boxes of an image of ``src_camera`` as `reproject`'s image in
    ``dst_camera`` (same arguments) shows them: the tight box of each box's region mapped
    through the cameras (its outline, sampled densely), clipped to the valid area (module
    docstring for the bounds).

    Args:
        boxes: per sample ``(N_i, 4)`` XYXY corner coordinates (a list of B, or ``(B, N, 4)``).
            Boxes are clipped to the source image; a box left with no area is dropped.
        src_camera: as for ``ot.reproject`` (a camera matrix ``K`` needs ``source_size``).
        dst_camera: as for ``ot.reproject``.
        rotation: as for ``ot.reproject``: ``ray_src = R @ ray_dst``.
        source_size: ``(H, W)`` of the source image, for a camera matrix ``K``.

    Returns:
        per sample ``boxes (M_i, 4)`` float64 XYXY corner coordinates and ``box_index (M_i,)``
        int64: the input box each output box comes from (so class labels follow).

    Examples:
        >>> src = Camera("pinhole", [32.0, 32.0, 31.5, 31.5], (64, 64))
        >>> fish = Camera("equidistant", [20.0, 20.0, 31.5, 31.5], (64, 64))
        >>> out, index = reproject_boxes([torch.tensor([[24.0, 24.0, 40.0, 40.0]])], src, fish)
        >>> [round(v, 1) for v in out[0][0].tolist()], index[0].tolist()
        ([27.1, 27.1, 36.9, 36.9], [0])
    """
    batch = len(boxes)
    boxes = check_boxes(boxes, batch)
    change, size = _change(src_camera, dst_camera, rotation, batch, source_size)
    return Outline(change, boxes, size).result()


def reproject_polygons(polygons: Sequence[Sequence[object]], src_camera: Camera | Tensor,
                       dst_camera: Camera, *, rotation: Tensor | None = None,
                       source_size: tuple[int, int] | None = None
                       ) -> tuple[list[list[Tensor]], list[Tensor]]:
    """Polygons of an image of ``src_camera`` as `omniscape_torch.reproject`'s image in
    ``dst_camera`` (same arguments) shows them: each ring densified, mapped and clipped to the
    valid area (module docstring for the bounds).

    Args:
        polygons: per sample a list of rings, each ``(N_k, 2)`` corner coordinates ``(x, y)``
            or COCO's flat ``[x0, y0, x1, y1, ...]`` list (a list of B).
        src_camera: as for ``ot.reproject`` (a camera matrix ``K`` needs ``source_size``).
        dst_camera: as for ``ot.reproject``.
        rotation: as for ``ot.reproject``: ``ray_src = R @ ray_dst``.
        source_size: ``(H, W)`` of the source image, for a camera matrix ``K``.

    Returns:
        per sample the output rings ``(M_j, 2)`` float64 corner coordinates (none where a ring
        leaves the view, several where the valid area's border cuts it apart) and
        ``polygon_index (M,)`` int64: the input ring of each.

    Examples:
        >>> src = Camera("pinhole", [32.0, 32.0, 31.5, 31.5], (64, 64))
        >>> fish = Camera("equidistant", [20.0, 20.0, 31.5, 31.5], (64, 64))
        >>> square = [[24.0, 24.0], [40.0, 24.0], [40.0, 40.0], [24.0, 40.0]]
        >>> rings, index = reproject_polygons([[square]], src, fish)
        >>> len(rings[0][0]) > 4, index[0].tolist()   # the edges bent: more points
        (True, [0])
    """
    if not isinstance(polygons, (list, tuple)):
        raise TypeError(f"polygons: expected per sample a list of rings, got "
                        f"{type(polygons).__name__}")
    batch = len(polygons)
    rings, _ = check_polygons(polygons, batch)
    change, _ = _change(src_camera, dst_camera, rotation, batch, source_size)
    got, index = polygon_rings.map_rings(change, rings, OUTLINE_STEP)
    return ([[torch.from_numpy(r) for r in rs] for rs in got],
            [torch.from_numpy(i) for i in index])
