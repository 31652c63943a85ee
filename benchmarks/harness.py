"""Speed against accuracy of cubemap -> fisheye rendering: every setting and the peers, one run.

``python benchmarks/run.py`` (this module's :func:`main`) renders a ``6 x F x F`` RGB cube into
a square equidistant fisheye of 190 degrees (default 1024 x 1024 from 6 x 512, the paper's
headline; ``--quick``: 256 x 256 from 6 x 128) and, in one run, times and scores:

* ``OmniProjection`` over the settings a user chooses, one axis at a time around the headline
  (bilinear, ``F`` = half the image side, no supersampling, resampled borders, float32, cached
  grid, batch 1): interpolation x face size (``F / 2``, ``F``, ``required_face_size`` ``F_req``
  and ``2 F_req``: the ``F / F_req`` column), supersampling 2 and 3, borders ``none`` and
  ``copied``, float16 / bfloat16 cubes (float32 grid), half-precision grids (cube, atlas and grid
  in float16 / bfloat16, what ``.half()`` on everything gives), the grid rebuilt per sample (a
  new attitude per sample and call), batch size, and ``fast`` on / off where ``OmniProjection``
  has that argument;
* the peers a user would pick instead, on the same cube: ``cv2.remap`` of the six faces stacked
  into one image (float maps and fixed-point ``CV_16SC2`` maps, float32 and uint8 images),
  py360convert's ``c2e`` (cube -> equirectangular) then ``cv2.remap`` to the fisheye,
  pytorch360convert's ``c2e`` then ``grid_sample``, and six ``grid_sample`` calls, one per face,
  masked and summed (how habitat-lab converts cubemaps). A peer that is not installed is a
  skipped row with a note.

Accuracy of every row (the same code path as its timing; rebuilt grids with the identity
attitude):

* ``psnr_db``: against an analytic sphere texture, ``f(d) = 0.5 + sum_i a_i cos(k_i w . d +
  phi)`` per channel (:func:`sphere_texture`), with wavelengths of 48, 12, 4 and 1.5 output
  pixels at the optical axis: band-limited (its finest wavelength is 1.5 pixels, above the
  output's Nyquist limit, so that aliasing shows). Cube texels are ``f`` of the texel-centre
  directions (a simulator's point samples); the reference is ``f`` averaged over each output
  pixel's footprint (``--reference-samples`` squared sub-rays, :func:`texture_reference`), what a
  real sensor integrates. Without supersampling, a cube much finer than the output reproduces the
  1.5-pixel wave at full amplitude at the pixel centres: aliasing, which supersampling removes.
* ``seam_max_err`` / ``interior_max_err``: the largest error, against ``f`` at the pixel centres,
  for the smooth part of the texture (wavelengths >= 4 pixels), at the pixels whose ray lands
  within ``SEAM_TEXELS`` texels of a cube edge or corner, and elsewhere.
* ``town_psnr_db`` and ``label_accuracy``: on the built-in town (:class:`~omniscape_torch.scenes.
  Town`, from the centre of the road at eye height), at ``--town-pixels`` random valid pixels:
  RGB against the exact ray cast averaged over ``--town-samples`` squared sub-rays per pixel,
  and the share of pixels whose label equals the ray cast's label at the pixel centre (our
  layer only; peers render RGB). Face sizes above ``F_req`` are not ray cast for the town (the
  cube alone would take minutes); those cells are empty.

Timing (``common.measure``): ``--warmup`` untimed calls of every row, then ``--repeats`` timed
calls round-robin over all rows (one call of each per repeat, so a change of load hits every
row alike), ``time.perf_counter`` around single calls, ``torch.cuda.synchronize`` around them
on CUDA; median and inter-quartile range per frame (``median / batch``), frames per second,
and the ratio to ``cv2.remap`` with float maps on float32 images in the same run.

Devices: ``--device cpu`` (default), ``cuda`` or ``auto`` (CUDA when available), several allowed:
our rows, pytorch360convert and the six ``grid_sample`` calls run on each device; OpenCV and
py360convert on the CPU. Nothing needs a GPU.

Outputs (``--out-dir``, default ``benchmarks/results``, each written atomically):
``bench.json`` (machine, threads, commit, versions, devices, setup, every row with its raw
times), ``bench.png`` (ms per frame, log, against PSNR; the Pareto front per device drawn and
labelled) and ``bench.md`` (the table).
"""

from __future__ import annotations

import argparse
import copy
import importlib
import inspect
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

# This folder's helpers (``common``, which also puts the checkout first on ``sys.path``): the
# harness is a module of ``benchmarks/``, imported as ``harness`` by ``run.py`` and the tests.
if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (RESULTS, begin_run, git_commit, loadavg, machine_info,  # noqa: E402
                    measure, positive_int, write_json_atomic)
import omniscape_torch  # noqa: E402
from omniscape_torch import cubemap as cm  # noqa: E402
from omniscape_torch.cameras import Camera  # noqa: E402
from omniscape_torch.cameras.presets import fisheye, yaw_pitch_roll_to_matrix  # noqa: E402
from omniscape_torch.io.atomic import atomic_path, atomic_write_text  # noqa: E402
from omniscape_torch.render.layer import OmniProjection  # noqa: E402
from omniscape_torch.render.reference import grid_sample, pixels_to_grid  # noqa: E402
from omniscape_torch.render.sizing import required_face_size  # noqa: E402
from omniscape_torch.scenes import Town  # noqa: E402

__all__ = ["add_arguments", "main", "markdown", "pareto_front", "run", "sphere_texture",
           "texture_cubemap", "texture_reference"]

SEED = 20240611
FOV = math.radians(190.0)
#: The analytic texture: wavelengths in output pixels at the optical axis, and amplitudes
#: (falling with frequency, like natural images'). Values stay in [0.11, 0.89].
WAVELENGTHS = (48.0, 12.0, 4.0, 1.5)
AMPLITUDES = (0.2, 0.1, 0.06, 0.03)
#: Components of the smooth texture that the seam errors use (wavelengths >= 4 pixels).
SMOOTH = 3
#: A pixel is near a seam when its ray lands within this many texels of a face edge: the reach
#: of the widest kernel (bicubic, 2 texels).
SEAM_TEXELS = 2.0
#: The town's camera: the centre line at eye height, looking along the road.
TOWN_POSITION = (0.0, -1.2, 0.0)
#: Order of our faces in py360convert's and pytorch360convert's F, R, B, L, U, D (the faces
#: themselves need no flip: both libraries see every face as a camera at the centre does).
PEER_FACE_ORDER = (0, 3, 1, 2, 4, 5)
PEER_FACE_KEYS = "FRBLUD"
#: Both libraries put face texel ``k`` at ``tan = 2 k / F - 1`` (first texel on the edge), half
#: a texel off the centres of a simulator's 90-degree camera, ``tan = (2 k + 1) / F - 1``: their
#: ``c2e`` of a cube of the texture is 22x closer to the truth (mean error) when the cube is
#: sampled on their grid instead (checked at F = 64).
PEER_TEXEL_NOTE = "texel k at tan = 2k/F - 1: half a texel off the faces' centres"
#: Share of right labels below which a row gets a "labels" note.
LABEL_NOTE_BELOW = 0.99
#: PSNR gain from supersampling (dB) above which an unsupersampled row is noted as aliased.
ALIAS_NOTE_DB = 1.0


def _optional(name: str):
    """The module ``name``, or None when it is not installed (its rows are skipped)."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


# --------------------------------------------------------------------------------------------
# Accuracy references
# --------------------------------------------------------------------------------------------

def _waves(dtype: torch.dtype, device) -> tuple[Tensor, Tensor]:
    """Per channel and component: unit wave directions ``(3, N, 3)`` and phases ``(3, N)``."""
    g = torch.Generator().manual_seed(SEED)
    n = len(WAVELENGTHS)
    dirs = F.normalize(torch.randn(3, n, 3, generator=g, dtype=torch.float64), dim=-1)
    phase = 2 * math.pi * torch.rand(3, n, generator=g, dtype=torch.float64)
    return dirs.to(dtype=dtype, device=device), phase.to(dtype=dtype, device=device)


def sphere_texture(directions: Tensor, pixels_per_radian: float, *,
                   components: int | None = None, chunk: int = 1 << 20) -> Tensor:
    """An analytic RGB texture on the sphere of directions.

    Per channel ``c``: ``0.5 + sum_i a_i cos(k_i w_ci . d + phi_ci)``, ``k_i = 2 pi
    pixels_per_radian / lambda_i`` with ``lambda_i`` = :data:`WAVELENGTHS` (pixels of a camera
    with ``pixels_per_radian`` at its axis) and ``a_i`` = :data:`AMPLITUDES`; ``w_ci`` and
    ``phi_ci`` fixed (seeded). Along any great circle a component oscillates at most ``k_i``
    times per radian: the texture is band-limited to wavelengths of ``lambda_i`` pixels.

    Args:
        directions: ``(..., 3)`` unit directions, floating (float64 for references).
        pixels_per_radian: the scale: a camera's pixels per radian at its optical axis.
        components: use the first ``components`` waves only (default all).
        chunk: directions per evaluation (memory bound; the result does not depend on it).

    Returns:
        ``(..., 3)`` RGB in ``[0.11, 0.89]``, dtype and device of ``directions``.
    """
    if not isinstance(directions, Tensor) or not directions.is_floating_point() \
            or directions.shape[-1:] != (3,):
        raise ValueError(f"directions: expected a floating tensor (..., 3), got "
                         f"{getattr(directions, 'shape', type(directions).__name__)}")
    if not (isinstance(pixels_per_radian, (int, float)) and pixels_per_radian > 0):
        raise ValueError(f"pixels_per_radian: expected a positive number, got "
                         f"{pixels_per_radian!r}")
    n = len(WAVELENGTHS) if components is None else components
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= len(WAVELENGTHS):
        raise ValueError(f"components: expected 1..{len(WAVELENGTHS)}, got {components!r}")
    dirs, phase = _waves(directions.dtype, directions.device)
    kw = dict(dtype=directions.dtype, device=directions.device)
    k = torch.tensor([2 * math.pi * pixels_per_radian / w for w in WAVELENGTHS[:n]], **kw)
    amp = torch.tensor(AMPLITUDES[:n], **kw)
    flat = directions.reshape(-1, 3)
    out = torch.empty(flat.shape[0], 3, **kw)
    for s in range(0, flat.shape[0], chunk):
        arg = torch.einsum("mj,cij->mci", flat[s:s + chunk], dirs[:, :n]) * k + phase[:, :n]
        out[s:s + chunk] = 0.5 + (amp * torch.cos(arg)).sum(-1)
    return out.reshape(directions.shape)


def texture_cubemap(face_size: int, pixels_per_radian: float, *,
                    components: int | None = None) -> Tensor:
    """The texture sampled at the texel centres of a cube: ``(1, 6, 3, F, F)`` float32
    (evaluated in float64), faces in ``FACES`` order, as a simulator's point samples."""
    rays = cm.face_rays(face_size, normalize=True, dtype=torch.float64)  # [6, F, F, 3]
    rgb = sphere_texture(rays, pixels_per_radian, components=components)
    return rgb.permute(0, 3, 1, 2).unsqueeze(0).float().contiguous()


def _sub_offsets(samples: int) -> Tensor:
    """``(s, )`` float64 offsets of ``s`` sub-samples centred in a pixel (0 among them for odd
    ``s``)."""
    return (torch.arange(samples, dtype=torch.float64) + 0.5) / samples - 0.5


def texture_reference(camera: Camera, pixels_per_radian: float, *, samples: int = 5,
                      components: int | None = None) -> tuple[Tensor, Tensor]:
    """The exact image of :func:`sphere_texture` through ``camera``: the mean of the texture over
    ``samples x samples`` sub-rays per pixel (the pixel's footprint; ``samples = 1``: the pixel
    centre's ray), computed in float64.

    Args:
        camera: one camera (rays in the cube frame: identity attitude).
        pixels_per_radian: the texture's scale (see :func:`sphere_texture`).
        samples: sub-samples per pixel side; sub-rays outside the camera's valid set are left
            out of the mean, as ``OmniProjection``'s supersampling leaves them out.
        components: the texture's components (default all).

    Returns:
        ``image (3, H, W)`` float64 (0 where invalid) and ``valid (H, W)`` (the pixel centre's
        validity).
    """
    if not isinstance(camera, Camera) or camera.batch_shape != ():
        raise TypeError("camera: expected one ot.Camera")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples: expected a positive int, got {samples!r}")
    cam = copy.deepcopy(camera).to("cpu", torch.float64)
    centre = cam.pixel_grid()
    total = torch.zeros(*centre.shape[:2], 3, dtype=torch.float64)
    count = torch.zeros(centre.shape[:2], dtype=torch.float64)
    offsets = _sub_offsets(samples)
    for dv in offsets:
        for du in offsets:
            rays, ok = cam.unproject(centre + torch.stack((du, dv)))
            value = sphere_texture(rays, pixels_per_radian, components=components)
            total += torch.where(ok.unsqueeze(-1), value, torch.zeros_like(value))
            count += ok
    valid = cam.ray_grid()[1]
    image = total / count.clamp(min=1).unsqueeze(-1)
    image = torch.where(valid.unsqueeze(-1), image, torch.zeros_like(image))
    return image.permute(2, 0, 1), valid


def _psnr(image: Tensor, reference: Tensor, mask: Tensor) -> float:
    """PSNR in dB (peak 1) of ``image (C, ...)`` against ``reference`` over ``mask (...)``."""
    err = (image.double() - reference.double())[:, mask]
    mse = float((err * err).mean())
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def label_accuracy(labels: Tensor, reference: Tensor) -> float:
    """Share of the entries of ``labels`` equal to ``reference`` (same shape, integer)."""
    if labels.shape != reference.shape:
        raise ValueError(f"labels: shape {tuple(labels.shape)} does not match the reference "
                         f"{tuple(reference.shape)}")
    if labels.numel() == 0:
        raise ValueError("labels: empty")
    return float((labels == reference).double().mean())


# --------------------------------------------------------------------------------------------
# Pareto front, versions (the timer and the environment records: common.py)
# --------------------------------------------------------------------------------------------

def pareto_front(cost: list[float], score: list[float]) -> list[int]:
    """Indices of the points no other point beats (cost no higher and score no lower, one of
    them strictly), by increasing cost; points with a non-finite cost or score are never on it,
    and of identical points only the first is.

    Example:
        >>> pareto_front([1.0, 2.0, 3.0, 2.5], [10.0, 30.0, 20.0, 40.0])
        [0, 1, 3]
    """
    if len(cost) != len(score):
        raise ValueError(f"cost, score: expected the same length, got {len(cost)} and "
                         f"{len(score)}")
    points = [(c, -s, i) for i, (c, s) in enumerate(zip(cost, score))
              if s is not None and math.isfinite(c) and math.isfinite(s)]
    front, best = [], -math.inf
    for c, neg, i in sorted(points):
        if -neg > best:
            front.append(i)
            best = -neg
    return front


def _versions(modules: dict) -> dict:
    out = {"omniscape_torch": omniscape_torch.__version__, "torch": torch.__version__,
           "numpy": np.__version__}
    for name, module in modules.items():
        out[name] = None if module is None else getattr(module, "__version__", "unknown")
    return out


# --------------------------------------------------------------------------------------------
# The scene: camera, references, cubes
# --------------------------------------------------------------------------------------------

class Scene:
    """The camera, the references, and the cubes per face size (built on demand, cached).

    Args:
        size: image side in pixels (square 190-degree equidistant fisheye).
        reference_samples: sub-samples per pixel side of the texture's reference.
        town_pixels: pixels ray cast for the town's reference (0: no town).
        town_samples: sub-samples per pixel side of the town's reference (odd).

    Attributes:
        required: ``required_face_size`` of the camera, also the largest face size whose town
            cube is rendered.
    """

    def __init__(self, size: int, *, reference_samples: int, town_pixels: int,
                 town_samples: int) -> None:
        self.size = size
        self.camera = fisheye((size, size), fov=FOV)
        self.required = required_face_size(self.camera)
        self.camera64 = fisheye((size, size), fov=FOV, dtype=torch.float64)
        # equidistant: r = f theta, so f is the pixels per radian, here and everywhere radially
        self.pixels_per_radian = float(self.camera64.params[0])
        self.rays, self.valid = self.camera64.ray_grid()  # [H, W, 3] float64, [H, W]
        self.reference, _ = texture_reference(self.camera64, self.pixels_per_radian,
                                              samples=reference_samples)
        self.smooth_reference, _ = texture_reference(self.camera64, self.pixels_per_radian,
                                                     samples=1, components=SMOOTH)
        self.town = Town(0) if town_pixels > 0 else None
        self._cubes: dict[tuple, Tensor] = {}
        if self.town is not None:
            self._town_reference(town_pixels, town_samples)

    def _town_reference(self, pixels: int, samples: int) -> None:
        g = torch.Generator().manual_seed(SEED)
        flat = torch.nonzero(self.valid.flatten()).squeeze(1)
        pick = flat[torch.randperm(flat.numel(), generator=g)[:pixels]].sort().values
        w = self.size
        self.town_v, self.town_u = pick // w, pick % w
        centre = torch.stack((self.town_u, self.town_v), -1).double()  # [M, 2]
        offsets = _sub_offsets(samples)
        sub = torch.stack(torch.meshgrid(offsets, offsets, indexing="xy"), -1).reshape(-1, 2)
        rays, ok = self.camera64.unproject(centre.unsqueeze(1) + sub)  # [M, s*s, 3]
        out = self.town.render_rays(torch.tensor(TOWN_POSITION), rays.float())
        rgb = torch.where(ok.unsqueeze(-1), out["rgb"].double(), torch.zeros(()).double())
        self.town_rgb = (rgb.sum(1) / ok.sum(1, keepdim=True).clamp(min=1)).T  # [3, M]
        self.town_labels = out["labels"][:, sub.shape[0] // 2]  # the centre sub-ray (s odd)

    def cube(self, kind: str, face_size: int) -> Tensor | None:
        """``"texture"``, ``"smooth"`` (1, 6, 3, F, F), ``"town_rgb"`` (1, 6, 3, F, F) or
        ``"town_labels"`` (1, 6, F, F); None for the town beyond ``required``."""
        key = (kind, face_size)
        if key not in self._cubes:
            if kind == "texture":
                self._cubes[key] = texture_cubemap(face_size, self.pixels_per_radian)
            elif kind == "smooth":
                self._cubes[key] = texture_cubemap(face_size, self.pixels_per_radian,
                                                   components=SMOOTH)
            elif self.town is None or face_size > self.required:
                return None
            else:
                out = self.town.render_cubemap(torch.tensor(TOWN_POSITION),
                                               face_size=face_size)
                self._cubes[("town_rgb", face_size)] = out["rgb"]
                self._cubes[("town_labels", face_size)] = out["labels"]
        return self._cubes[key]

    def drop(self, kinds: tuple[str, ...]) -> None:
        """Forget the cached cubes of ``kinds`` (memory)."""
        self._cubes = {k: v for k, v in self._cubes.items() if k[0] not in kinds}

    def near_seam(self, face_size: int) -> Tensor:
        """``(H, W)`` valid pixels whose centre ray lands within ``SEAM_TEXELS`` of a face
        edge of a cube of ``face_size``."""
        _, uv = cm.ray_to_face(self.rays, face_size)
        edge = torch.minimum(uv + 0.5, face_size - 0.5 - uv).amin(-1)
        return self.valid & (edge < SEAM_TEXELS)


# --------------------------------------------------------------------------------------------
# Rows
# --------------------------------------------------------------------------------------------

#: A renderer factory: ``prepare(cube (B, 6, 3, F, F) float32 cpu, rotations) -> fn``, ``fn()``
#: rendering the batch; ``rotations`` is None (cached grid) or a callable giving ``(B, 3, 3)``.
Prepare = Callable[[Tensor, Callable[[], Tensor] | None], Callable[[], object]]


def _tensor_image(out: Tensor) -> Tensor:
    return out.detach().float().cpu()


@dataclass
class Case:
    """One row: a setting of ours or a peer, its renderer, and how to read its output."""
    name: str
    family: str  # "ours" or the peer's name
    settings: dict
    prepare: Prepare | None  # None: skipped
    image: Callable[[object], Tensor] = _tensor_image  # output -> (B, 3, H, W) float cpu
    labels: Callable[[Tensor], Tensor] | None = None  # labels cube -> (1, H, W)
    rebuilt: bool = False
    notes: list[str] = field(default_factory=list)


def _numpy_images(out: list[np.ndarray]) -> Tensor:
    """``B`` HWC numpy images (uint8 scaled by 1/255) -> ``(B, 3, H, W)`` float32."""
    stack = np.stack(out)
    scale = 1 / 255 if stack.dtype == np.uint8 else 1.0
    return torch.from_numpy(stack.astype(np.float32) * scale).permute(0, 3, 1, 2)


def _fast_default() -> bool | None:
    """``OmniProjection``'s default ``fast``, None where it has no such argument."""
    param = inspect.signature(OmniProjection).parameters.get("fast")
    return None if param is None else param.default


def ours_case(scene: Scene, *, face_size: int, interpolation: str = "bilinear",
              supersample: int = 1, border: str = "resampled", dtype: torch.dtype = torch.float32,
              rebuilt: bool = False, batch: int = 1, fast: bool | None = None,
              fused_grid: bool = True, device: torch.device = torch.device("cpu")) -> Case:
    """``OmniProjection`` with these settings (``fast=None``: the argument is not passed)."""
    kwargs = dict(interpolation=interpolation, supersample=supersample, border=border,
                  fused_grid=fused_grid)
    if fast is not None:
        kwargs["fast"] = fast
    layer = OmniProjection(scene.camera, face_size, **kwargs).to(device)

    def prepare(cube, rotations):
        x = cube.to(device=device, dtype=dtype)
        if rotations is None:
            return lambda: layer(x)[0]
        return lambda: layer(x, rotations())[0]

    settings = dict(interpolation=interpolation, face_size=face_size, supersample=supersample,
                    border=border, dtype=str(dtype).replace("torch.", ""), grid="float32",
                    rebuilt=rebuilt, batch=batch, fast=_fast_default() if fast is None else fast,
                    device=str(device))
    return Case(_name(settings), "ours", settings, prepare,
                labels=lambda lab: layer.render(labels=lab.to(device))["labels"].cpu(),
                rebuilt=rebuilt)


def half_grid_case(scene: Scene, *, face_size: int, dtype: torch.dtype,
                   device: torch.device) -> Case:
    """The layer's bilinear sampling of a float32 cube with its (cached) grid rounded to
    ``dtype``, what a grid stored or computed in half precision gives: ``grid_sample``
    coordinates in ``[-1, 1]`` keep 11 (float16) or 8 (bfloat16) significant bits, a step of
    ``2^-11`` or ``2^-8`` of the atlas' height ``6 (F + 2)`` near its edge. (The sampling itself
    stays in float32: ``F.grid_sample`` in half precision on the CPU returns NaN in torch 2.13.)
    """
    layer = OmniProjection(scene.camera, face_size).to(device)
    grid32 = layer.sampling_grid()[0]
    grid = grid32.to(dtype).float()
    n = face_size + 2 * layer.pad
    scale = torch.tensor([n, 6 * n], device=grid32.device) / 2  # texels per grid unit
    err = float(((grid - grid32).abs() * scale).amax())

    def prepare(cube, rotations):
        x = cube.to(device)
        g = grid.expand(x.shape[0], -1, -1, -1)
        return lambda: grid_sample(cm.cubemap_to_atlas(x, layer.pad), g, "bilinear",
                                   padding_mode="zeros")

    settings = dict(interpolation="bilinear", face_size=face_size, supersample=1,
                    border="resampled", dtype="float32", grid=str(dtype).replace("torch.", ""),
                    rebuilt=False, batch=1, fast=None, device=str(device))
    return Case(_name(settings), "ours", settings, prepare,
                notes=[f"grid off by up to {err:.2g} texels"])


def remap_cases(scene: Scene, face_size: int, cv2) -> list[Case]:
    """``cv2.remap`` (bilinear) of the six faces stacked vertically (``np.vstack`` per frame,
    as the faces come from a simulator), float32 maps and fixed-point ``CV_16SC2`` maps, on
    float32 and uint8 images. Invalid pixels map outside the image."""
    names = [f"cv2.remap {m} maps {d}" for m in ("float", "fixed") for d in ("float32", "uint8")]
    if cv2 is None:
        return [Case(n, "cv2.remap", {"face_size": face_size, "device": "cpu", "batch": 1},
                     None, notes=["skipped: cv2 (opencv-python) not installed"]) for n in names]
    face, uv = cm.ray_to_face(scene.rays, face_size)  # [H, W], [H, W, 2]
    x = torch.where(scene.valid, uv[..., 0], torch.full_like(uv[..., 0], -10.0))
    y = torch.where(scene.valid, uv[..., 1] + face * face_size, torch.full_like(x, -10.0))
    map_x, map_y = x.float().numpy(), y.float().numpy()
    fixed = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
    cases = []
    for name in names:
        maps = (map_x, map_y) if " float maps" in name else fixed
        uint8 = name.endswith("uint8")

        def prepare(cube, rotations, maps=maps, uint8=uint8):
            hwc = cube.permute(0, 1, 3, 4, 2).numpy()  # [B, 6, F, F, 3]
            if uint8:
                hwc = np.round(hwc * 255).astype(np.uint8)
            frames = [[np.ascontiguousarray(f) for f in sample] for sample in hwc]
            return lambda: [cv2.remap(np.vstack(faces), *maps, cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REPLICATE) for faces in frames]

        cases.append(Case(name, "cv2.remap", {"face_size": face_size, "device": "cpu",
                                              "batch": 1, "dtype": "uint8" if uint8 else
                                              "float32"}, prepare, _numpy_images))
    return cases


def _equirect_size(face_size: int) -> tuple[int, int]:
    """(h, w) of the intermediate panorama: the libraries' default ``(2 F, 4 F)``, the width
    rounded up to a multiple of 8 (py360convert requires it)."""
    w = 8 * math.ceil(4 * face_size / 8)
    return w // 2, w


def _equirect_coords(scene: Scene, h: int, w: int) -> tuple[Tensor, Tensor]:
    """Column and row of every pixel ray in the libraries' panorama: ``y`` up,
    longitude ``atan2(x, z)`` on ``linspace(-pi, pi, w)``, latitude on ``linspace(pi / 2,
    -pi / 2, h)`` (first and last columns and rows at the limits)."""
    d = scene.rays
    lon = torch.atan2(d[..., 0], d[..., 2])
    lat = torch.atan2(-d[..., 1], torch.hypot(d[..., 0], d[..., 2]))
    col = (lon + math.pi) / (2 * math.pi) * (w - 1)
    row = (math.pi / 2 - lat) / math.pi * (h - 1)
    return col, row


def py360_case(scene: Scene, face_size: int, py360, cv2) -> Case:
    """py360convert ``c2e(dict of faces, h, w, mode="bilinear", cube_format="dict")`` then
    ``cv2.remap`` (bilinear, float maps) of the panorama to the fisheye."""
    name = "py360convert c2e + cv2.remap"
    settings = {"face_size": face_size, "device": "cpu", "batch": 1, "dtype": "float32"}
    missing = [n for n, m in (("py360convert", py360), ("cv2", cv2)) if m is None]
    if missing:
        return Case(name, "py360convert", settings, None,
                    notes=[f"skipped: {', '.join(missing)} not installed"])
    h, w = _equirect_size(face_size)
    col, row = _equirect_coords(scene, h, w)
    map_x, map_y = col.float().numpy(), row.float().numpy()

    def prepare(cube, rotations):
        frames = [{k: np.ascontiguousarray(sample[i].permute(1, 2, 0).numpy())
                   for k, i in zip(PEER_FACE_KEYS, PEER_FACE_ORDER)} for sample in cube]
        return lambda: [cv2.remap(py360.c2e(faces, h, w, mode="bilinear", cube_format="dict"),
                                  map_x, map_y, cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REPLICATE) for faces in frames]

    return Case(name, "py360convert", settings, prepare, _numpy_images,
                notes=[PEER_TEXEL_NOTE])


def torch360_case(scene: Scene, face_size: int, p360, device: torch.device) -> Case:
    """pytorch360convert ``c2e(faces (6, C, F, F), h, w, mode="bilinear",
    cube_format="stack")`` then ``grid_sample`` (bilinear, ``align_corners=True`` as the
    library's own sampling) of the panorama to the fisheye with a precomputed grid."""
    name = "pytorch360convert c2e + grid_sample"
    settings = {"face_size": face_size, "device": str(device), "batch": 1, "dtype": "float32"}
    if p360 is None:
        return Case(name, "pytorch360convert", settings, None,
                    notes=["skipped: pytorch360convert not installed"])
    h, w = _equirect_size(face_size)
    col, row = _equirect_coords(scene, h, w)
    grid = torch.stack((col / (w - 1) * 2 - 1, row / (h - 1) * 2 - 1), -1)
    grid = grid.float().unsqueeze(0).to(device)
    order = list(PEER_FACE_ORDER)

    def prepare(cube, rotations):
        stacks = [sample[order].to(device) for sample in cube]
        return lambda: torch.cat([F.grid_sample(
            p360.c2e(s, h, w, mode="bilinear", cube_format="stack").unsqueeze(0), grid,
            mode="bilinear", padding_mode="border", align_corners=True) for s in stacks])

    return Case(name, "pytorch360convert", settings, prepare,
                notes=[PEER_TEXEL_NOTE])


def six_faces_case(scene: Scene, face_size: int, device: torch.device) -> Case:
    """Six ``grid_sample`` calls, one per face (bilinear, ``padding_mode="border"``), each
    masked to the pixels whose ray hits that face, summed: habitat-lab's way of converting a
    cubemap (per-face grids precomputed)."""
    face, uv = cm.ray_to_face(scene.rays, face_size)  # [H, W], [H, W, 2]
    grid = pixels_to_grid(uv, face_size, face_size).float().to(device)  # [H, W, 2]
    masks = torch.stack([(face == k) & scene.valid for k in range(6)]).float()
    masks = masks.unsqueeze(1).to(device)  # [6, 1, H, W]

    def prepare(cube, rotations):
        x = cube.to(device)
        g = grid.expand(x.shape[0], -1, -1, -1)
        return lambda: sum(F.grid_sample(x[:, k], g, mode="bilinear", padding_mode="border",
                                         align_corners=False) * masks[k] for k in range(6))

    return Case("6 x grid_sample (habitat-lab)", "six grid_sample",
                {"face_size": face_size, "device": str(device), "batch": 1,
                 "dtype": "float32"}, prepare)


def _name(s: dict) -> str:
    """Short row name of our settings: what differs from the headline."""
    parts = [s["interpolation"], f"F{s['face_size']}"]
    if s["supersample"] > 1:
        parts.append(f"ss{s['supersample']}")
    if s["border"] != "resampled":
        parts.append(f"border {s['border']}")
    if s["grid"] != "float32":
        parts.append(f"{s['grid']} grid")
    elif s["dtype"] != "float32":
        parts.append(f"{s['dtype']} cube")
    if s["rebuilt"]:
        parts.append("rebuilt")
    if s["batch"] > 1:
        parts.append(f"b{s['batch']}")
    if s["fast"] is False:
        parts.append("fast off")
    return " ".join(parts)


def build_cases(scene: Scene, *, faces: list[int], head: int, batch: int,
                devices: list[torch.device], fused: bool) -> list[Case]:
    """The sweep: one axis at a time around the headline ``head``, per device, then the
    peers."""
    cases: list[Case] = []
    cv2 = _optional("cv2")
    for device in devices:
        kw = dict(device=device, fused_grid=fused)
        for interp in ("nearest", "bilinear", "bicubic"):
            cases += [ours_case(scene, face_size=f, interpolation=interp, **kw) for f in faces]
        cases += [ours_case(scene, face_size=f, supersample=s, **kw)
                  for s in (2, 3) for f in faces if f >= head]
        cases += [ours_case(scene, face_size=head, interpolation=i, border=b, **kw)
                  for i in ("bilinear", "bicubic") for b in ("copied", "none")]
        cases += [ours_case(scene, face_size=head, dtype=d, **kw)
                  for d in (torch.float16, torch.bfloat16)]
        cases += [half_grid_case(scene, face_size=head, dtype=d, device=device)
                  for d in (torch.float16, torch.bfloat16)]
        cases += [ours_case(scene, face_size=head, rebuilt=r, batch=batch, **kw)
                  for r in (False, True)]
        cases.append(ours_case(scene, face_size=head, rebuilt=True, **kw))
        if _fast_default() is not None:
            cases += [ours_case(scene, face_size=head, rebuilt=r, fast=False, **kw)
                      for r in (False, True)]
        cases.append(torch360_case(scene, head, _optional("pytorch360convert"), device))
        cases.append(six_faces_case(scene, head, device))
    cases += remap_cases(scene, head, cv2)
    cases.append(py360_case(scene, head, _optional("py360convert"), cv2))
    return cases


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------

class _Attitudes:
    """A new batch of vehicle-like attitudes per call (yaw uniform, pitch and roll within 10
    degrees), cycling through a seeded pool: no grid can be reused between calls."""

    def __init__(self, batch: int, calls: int, gen: torch.Generator, device) -> None:
        n = batch * calls
        yaw = (2 * torch.rand(n, generator=gen) - 1) * math.pi
        tilt = (2 * torch.rand(2, n, generator=gen) - 1) * math.radians(10)
        rot = yaw_pitch_roll_to_matrix(yaw, tilt[0], tilt[1])
        self.pool = rot.reshape(calls, batch, 3, 3).to(device)
        self.i = 0

    def __call__(self) -> Tensor:
        rot = self.pool[self.i % len(self.pool)]
        self.i += 1
        return rot


def evaluate(case: Case, scene: Scene) -> dict:
    """Accuracy of one row (see the module docstring); None where not measured."""
    f = case.settings["face_size"]
    rotations = None
    if case.rebuilt:  # the rebuilt path, at the identity attitude of the references
        eye = torch.eye(3, device=torch.device(case.settings["device"])).unsqueeze(0)
        rotations = lambda: eye  # noqa: E731

    def render(cube: Tensor) -> Tensor:
        return case.image(case.prepare(cube, rotations)())[0].double()

    image = render(scene.cube("texture", f))
    smooth = render(scene.cube("smooth", f))
    err = (smooth - scene.smooth_reference).abs().amax(0)
    near = scene.near_seam(f)
    far = scene.valid & ~near
    out = {"psnr_db": _psnr(image, scene.reference, scene.valid),
           "seam_max_err": float(err[near].max()) if bool(near.any()) else None,
           "interior_max_err": float(err[far].max()) if bool(far.any()) else None,
           "town_psnr_db": None, "label_accuracy": None}
    town = scene.cube("town_rgb", f)
    if town is not None:
        rgb = render(town)[:, scene.town_v, scene.town_u]
        out["town_psnr_db"] = _psnr(rgb, scene.town_rgb, torch.ones(rgb.shape[1:], dtype=bool))
        if case.labels is not None:
            labels = case.labels(scene.cube("town_labels", f))[0, scene.town_v, scene.town_u]
            out["label_accuracy"] = label_accuracy(labels, scene.town_labels)
    return out


def _notes(rows: list[dict]) -> None:
    """Failure notes from the measurements: aliasing (supersampling gains more than
    ``ALIAS_NOTE_DB``), visible seams, wrong labels."""
    def key(s: dict) -> tuple:
        return (s["interpolation"], s["face_size"], s["border"], s["dtype"], s["grid"],
                s["device"])

    best_ss: dict[tuple, float] = {}
    for r in rows:
        s, acc = r["settings"], r["accuracy"]
        if r["family"] == "ours" and acc and s["supersample"] > 1:
            best_ss[key(s)] = max(best_ss.get(key(s), -math.inf), acc["psnr_db"])
    for r in rows:
        acc, s = r["accuracy"], r["settings"]
        if not acc:
            continue
        if r["family"] == "ours" and s["supersample"] == 1:
            gain = best_ss.get(key(s), -math.inf) - acc["psnr_db"]
            if gain > ALIAS_NOTE_DB:
                r["notes"].append(f"aliased: supersampling gains {gain:.1f} dB")
        seam, interior = acc["seam_max_err"], acc["interior_max_err"]
        if seam is not None and interior is not None and seam > 3 * interior:
            r["notes"].append(f"seams visible: {seam / interior:.0f}x the interior error")
        if acc["label_accuracy"] is not None and acc["label_accuracy"] < LABEL_NOTE_BELOW:
            r["notes"].append(f"labels: {100 * acc['label_accuracy']:.1f}% right")


def run(args: argparse.Namespace) -> dict:
    """Build the sweep, score every row, time all rows round-robin; the result dict."""
    cv2 = _optional("cv2")
    load_start = begin_run(args.threads, cv2)
    devices = _devices(args.device)
    progress = not args.no_progress
    start = time.perf_counter()
    with torch.no_grad():
        scene = Scene(args.size, reference_samples=args.reference_samples,
                      town_pixels=args.town_pixels, town_samples=args.town_samples)
        required = scene.required
        head = args.face or args.size // 2
        faces = args.faces or sorted({max(1, head // 2), head, required, 2 * required})
        cases = build_cases(scene, faces=faces, head=head, batch=args.batch, devices=devices,
                            fused=not args.no_fused)
        if args.only:
            cases = [c for c in cases if any(s in c.name for s in args.only)]
        setup_s = time.perf_counter() - start

        from tqdm import tqdm
        rows = []
        for case in tqdm(cases, desc="accuracy", unit="row", disable=not progress,
                         file=sys.stderr):
            rows.append({"name": case.name, "family": case.family, "settings": case.settings,
                         "skipped": case.prepare is None, "notes": list(case.notes),
                         "accuracy": None if case.prepare is None else evaluate(case, scene)})
        scene.drop(("smooth", "town_rgb", "town_labels"))
        accuracy_s = time.perf_counter() - start - setup_s

        gen = torch.Generator().manual_seed(SEED)
        timed = [(c, r) for c, r in zip(cases, rows) if c.prepare is not None]
        calls = args.warmup + args.repeats
        fns = []
        for case, _ in timed:
            b = case.settings["batch"]
            cube = scene.cube("texture", case.settings["face_size"])
            cube = cube.expand(b, -1, -1, -1, -1).contiguous()
            rot = (_Attitudes(b, calls, gen, torch.device(case.settings["device"]))
                   if case.rebuilt else None)
            fns.append(case.prepare(cube, rot))
        sync = "cuda" if any(d.type == "cuda" for d in devices) else "cpu"
        timings = measure(fns, args.repeats, args.warmup, sync, progress=progress)
    for (case, row), t in zip(timed, timings):
        b = case.settings["batch"]
        row["timing"] = t
        row["ms_per_frame"] = 1e3 * t["median_s"] / b
        row["iqr_ms_per_frame"] = 1e3 * t["iqr_s"] / b
        row["frames_per_s"] = b / t["median_s"]
    peer = next((r for r in rows if r["name"] == "cv2.remap float maps float32"
                 and not r["skipped"]), None)
    for r in rows:
        r["ratio_to_remap"] = (r["ms_per_frame"] / peer["ms_per_frame"]
                               if peer is not None and "ms_per_frame" in r else None)
    _notes(rows)
    fronts = {}
    for device in sorted({r["settings"]["device"] for r in rows}):
        idx = [i for i, r in enumerate(rows) if r["settings"]["device"] == device
               and not r["skipped"]]
        front = pareto_front([rows[i]["ms_per_frame"] for i in idx],
                             [rows[i]["accuracy"]["psnr_db"] for i in idx])
        fronts[device] = [idx[i] for i in front]
        for i in fronts[device]:
            rows[i]["pareto"] = True
    commit, dirty = git_commit()
    return {
        "benchmark": "speed_vs_accuracy",
        "commit": commit,
        "dirty": dirty,
        "machine": machine_info(devices),
        "versions": _versions({m: _optional(m) for m in ("cv2", "py360convert",
                                                          "pytorch360convert", "kornia")}),
        "threads": args.threads,
        "torch_num_threads": torch.get_num_threads(),
        "cv2_num_threads": None if cv2 is None else cv2.getNumThreads(),
        "devices": [str(d) for d in devices],
        "fast_default": _fast_default(),
        "setup": {"image_size": [args.size, args.size], "model": "equidistant",
                  "fov_deg": math.degrees(FOV), "focal_px": scene.pixels_per_radian,
                  "required_face_size": required, "headline_face_size": head,
                  "face_sizes": faces, "batch": args.batch, "channels": 3,
                  "texture": {"wavelengths_px": WAVELENGTHS, "amplitudes": AMPLITUDES,
                              "smooth_components": SMOOTH, "seed": SEED,
                              "reference_samples": args.reference_samples},
                  "seam_texels": SEAM_TEXELS,
                  "town": {"seed": 0, "position": TOWN_POSITION, "pixels": args.town_pixels,
                           "samples": args.town_samples, "max_face_size": required},
                  "valid_fraction": float(scene.valid.double().mean())},
        "repeats": args.repeats,
        "warmup": args.warmup,
        "seed": SEED,
        "timer": "time.perf_counter around single calls, after warm-up, all rows round-robin; "
                 "median and IQR; an untimed 10 ms pause before every timed call "
                 "(common.SETTLE_S)",
        "phase_s": {"setup": setup_s, "accuracy": accuracy_s,
                    "timing": time.perf_counter() - start - setup_s - accuracy_s},
        "timestamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "loadavg_start": load_start,
        "loadavg_end": loadavg(),
        "pareto": fronts,
        "rows": rows,
    }


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------

def _fmt(value, spec: str, empty: str = "") -> str:
    return empty if value is None else format(value, spec)


def markdown(result: dict) -> str:
    """The table of ``result`` (one line per row, skipped rows with their note)."""
    s = result["setup"]
    h, w = s["image_size"]
    lines = [
        f"Fisheye {w} x {h} (equidistant, {s['fov_deg']:.0f} deg) from a 6 x F cube; headline "
        f"F = {s['headline_face_size']}, required_face_size F_req = {s['required_face_size']}; "
        f"{result['threads']} thread{'s' if result['threads'] > 1 else ''}, "
        f"{result['machine'].get('cpu_model') or ''}"
        f"{', ' + result['machine']['gpu'] if 'gpu' in result['machine'] else ''}; "
        f"commit {result['commit'][:12]}{' (dirty)' if result['dirty'] else ''}; "
        f"1-min load {_fmt(load[0] if (load := result['loadavg_start']) else None, '.2f', '?')}"
        f" -> {_fmt(load[0] if (load := result['loadavg_end']) else None, '.2f', '?')}.",
        "",
        "PSNR: analytic texture against its pixel-footprint average; seam / interior: largest "
        f"error of the smooth texture within {SEAM_TEXELS:g} texels of a cube edge / elsewhere; "
        "town: PSNR and share of right labels against the exact ray cast. "
        "* = on the Pareto front (time, PSNR) of its device.",
        "",
        "| row | device | F / F_req | ms / frame | IQR ms | frames / s | x remap | PSNR dB "
        "| seam / interior err | town dB | labels % | notes |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        st, acc = r["settings"], r["accuracy"] or {}
        ratio = st["face_size"] / s["required_face_size"]
        seam = acc.get("seam_max_err")
        err = "" if seam is None else f"{seam:.3f} / {acc['interior_max_err']:.3f}"
        labels = acc.get("label_accuracy")
        name = f"{r['name']}{' *' if r.get('pareto') else ''}"
        lines.append(
            f"| {name} | {st['device']} | {ratio:.2f} | {_fmt(r.get('ms_per_frame'), '.2f')} | "
            f"{_fmt(r.get('iqr_ms_per_frame'), '.2f')} | {_fmt(r.get('frames_per_s'), '.1f')} | "
            f"{_fmt(r.get('ratio_to_remap'), '.2f')} | {_fmt(acc.get('psnr_db'), '.1f')} | "
            f"{err} | {_fmt(acc.get('town_psnr_db'), '.1f')} | "
            f"{'' if labels is None else f'{100 * labels:.1f}'} | {'; '.join(r['notes'])} |")
    return "\n".join(lines) + "\n"


_MARKERS = {"ours": "o", "cv2.remap": "s", "py360convert": "^", "pytorch360convert": "v",
            "six grid_sample": "D"}
_COLOURS = {"nearest": "tab:gray", "bilinear": "tab:blue", "bicubic": "tab:green"}


def chart(result: dict, path: Path) -> None:
    """``path`` (PNG): ms per frame (log) against PSNR, one marker per row (peers distinct,
    GPU rows hollow), the Pareto front of each device drawn and its points labelled."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 7.5), layout="constrained")
    ax = fig.subplots()
    rows = [r for r in result["rows"] if not r["skipped"]]
    seen = set()
    for r in rows:
        st, fam = r["settings"], r["family"]
        colour = _COLOURS[st["interpolation"]] if fam == "ours" else "tab:red"
        label = f"ours, {st['interpolation']}" if fam == "ours" else fam
        hollow = st["device"] != "cpu"
        ax.scatter(r["ms_per_frame"], r["accuracy"]["psnr_db"], marker=_MARKERS[fam], s=40,
                   facecolors="none" if hollow else colour, edgecolors=colour,
                   label=None if label in seen else label, zorder=3)
        seen.add(label)
    for device, front in result["pareto"].items():
        pts = [(result["rows"][i]["ms_per_frame"], result["rows"][i]["accuracy"]["psnr_db"],
                result["rows"][i]["name"]) for i in front]
        ax.step([p[0] for p in pts], [p[1] for p in pts], where="post", color="black",
                linestyle="--" if device != "cpu" else "-", linewidth=1,
                label=f"Pareto front ({device})", zorder=2)
        for k, (x, y, name) in enumerate(pts):  # staggered: neighbours on the front overlap
            ax.annotate(name, (x, y), textcoords="offset points", xytext=(5, 4 - 9 * (k % 4)),
                        fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("ms per frame (median; log scale)")
    ax.set_ylabel("PSNR (dB) against the exact pixel-footprint average")
    s = result["setup"]
    ax.set_title(f"Cube -> {s['image_size'][1]} x {s['image_size'][0]} fisheye: speed vs "
                 f"accuracy ({result['threads']} thread{'s' if result['threads'] > 1 else ''}; "
                 "upper left is better)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    fig.legend(fontsize=8, loc="outside right upper")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=110)


def write_outputs(result: dict, out_dir: Path) -> dict[str, Path]:
    """``bench.json``, ``bench.png`` and ``bench.md`` in ``out_dir``, each atomically."""
    paths = {k: Path(out_dir) / f"bench.{k}" for k in ("json", "png", "md")}
    write_json_atomic(result, paths["json"])
    chart(result, paths["png"])
    atomic_write_text(paths["md"], markdown(result))
    return paths


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

def _devices(names: list[str]) -> list[torch.device]:
    out = []
    for name in names:
        if name == "auto":
            name = "cuda" if torch.cuda.is_available() else "cpu"
        if name == "cuda" and not torch.cuda.is_available():
            raise ValueError("--device cuda: CUDA is not available in this torch build or "
                             "machine (use --device auto to fall back to the CPU)")
        if torch.device(name) not in out:
            out.append(torch.device(name))
    return out


def add_arguments(parser: argparse.ArgumentParser, out_dir: Path = RESULTS) -> None:
    """The benchmark's flags (``--quick`` fills the ones left unset); ``out_dir`` is the default
    of ``--out-dir``, ``out_dir / "quick"`` with ``--quick`` (git-ignored: a smoke run never
    overwrites the committed results of a full run)."""
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 256 x 256 from 6 x 128, batch 2, 5 repeats (~1 min)")
    parser.add_argument("--size", type=positive_int, default=None,
                        help="image side in pixels (default 1024; 256 with --quick)")
    parser.add_argument("--face", type=positive_int, default=None,
                        help="headline face size (default size / 2)")
    parser.add_argument("--faces", type=positive_int, nargs="+", default=None,
                        help="face sizes of the interpolation sweep (default face / 2, face, "
                             "F_req, 2 F_req)")
    parser.add_argument("--batch", type=positive_int, default=None,
                        help="the larger batch (default 8; 2 with --quick)")
    parser.add_argument("--threads", type=positive_int, default=2,
                        help="torch and OpenCV threads (default 2)")
    parser.add_argument("--repeats", type=positive_int, default=None,
                        help="timed calls per row (default 10; 5 with --quick)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed calls per row first (default 2; 1 with --quick)")
    parser.add_argument("--device", nargs="+", choices=("cpu", "cuda", "auto"),
                        default=["cpu"], help="devices of the torch rows (default cpu; auto: "
                                              "cuda when available)")
    parser.add_argument("--reference-samples", type=positive_int, default=5,
                        help="sub-samples per pixel side of the texture reference (default 5)")
    parser.add_argument("--town-pixels", type=int, default=None,
                        help="pixels ray cast for the town (default 20000; 5000 with --quick; "
                             "0: no town)")
    parser.add_argument("--town-samples", type=positive_int, default=3,
                        help="sub-rays per pixel side of the town reference, odd (default 3)")
    parser.add_argument("--no-fused", action="store_true",
                        help="rebuilt grids without torch.compile (no compilation wait)")
    parser.add_argument("--only", nargs="+", default=None, metavar="TEXT",
                        help="keep the rows whose name contains one of these")
    parser.add_argument("--out-dir", type=Path, default=None,
                        help=f"folder of bench.json, bench.png, bench.md (default {out_dir}; "
                             f"{Path(out_dir) / 'quick'} with --quick)")
    parser.set_defaults(default_out_dir=Path(out_dir))
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _resolve(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the defaults that depend on ``--quick``, and check the rest."""
    quick = args.quick
    if args.out_dir is None:
        base = getattr(args, "default_out_dir", RESULTS)
        args.out_dir = base / "quick" if quick else base
    defaults = {"size": 256 if quick else 1024, "batch": 2 if quick else 8,
                "repeats": 5 if quick else 10, "warmup": 1 if quick else 2,
                "town_pixels": 5000 if quick else 20000}
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.size < 8:
        raise ValueError(f"--size: expected at least 8 pixels, got {args.size}")
    if args.warmup < 0:
        raise ValueError(f"--warmup: expected >= 0, got {args.warmup}")
    if args.town_pixels < 0:
        raise ValueError(f"--town-pixels: expected >= 0, got {args.town_pixels}")
    if args.town_samples % 2 == 0:
        raise ValueError(f"--town-samples: expected an odd number (the pixel centre is one of "
                         f"the sub-rays), got {args.town_samples}")
    return args


def main(argv: list[str] | None = None, *, out_dir: Path | None = None) -> int:
    """``python benchmarks/run.py [flags]``: run, write the outputs, print the table; exit
    status 0 (a bad flag: usage on stderr and ``SystemExit(2)``). ``out_dir``: the default of
    ``--out-dir``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser, *([] if out_dir is None else [out_dir]))
    args = parser.parse_args(argv)
    try:
        result = run(_resolve(args))
    except ValueError as err:
        parser.error(str(err))
    paths = write_outputs(result, args.out_dir)
    print(markdown(result))
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0
