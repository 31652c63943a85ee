"""Write an OmniScape-like dataset: a motorcycle ride through the built-in town, seen by a rig of
stereo fisheye and stereo catadioptric cameras, with range depth, labels, intrinsics (also as
OCamCalib's ``calib_results.txt``, as the OmniScape dataset ships them: `data.ocamcalib`,
fitted once per folder), extrinsics, vehicle dynamics, and the instance ids and 2D boxes of the
town's vehicles, pedestrians, poles and traffic signs (`data.objects`; ``omniscape-torch
generate``; the files: `data.format`, the per-run ones written by `data.run_files`, the
contact sheet by `data.contact_sheet`).

The rig
-------
Four cameras on the two front sides of the motorcycle (rig frame: OpenCV axes, x right, y down,
z forward, origin on the ground under the motorcycle's reference point, the point whose
location ``dynamics.json`` gives; metres):

================== ======================== ==========================================
camera             position (x, y, z)        model and attitude
================== ======================== ==========================================
fisheye_left       (-0.4, -0.8, 0.6)         ``presets.fisheye``: equidistant, 190 deg,
fisheye_right      (+0.4, -0.8, 0.6)         looking forward (cam -> rig = I)
catadioptric_left  (-0.4, -1.0, 0.4)         ``presets.catadioptric(looking="down")``:
catadioptric_right (+0.4, -1.0, 0.4)         unified, xi 0.9, 220 deg, axis down
================== ======================== ==========================================

So the stereo baselines are 0.8 m, the fisheyes 0.8 m above the ground, the catadioptric
cameras 1.0 m. Each frame, the motorcycle's attitude ``R_bike`` (rig -> world,
``ride.camera_rotation``: yaw, pitch, lean) places and turns every camera: camera centre
``c = location + R_bike @ position``, and its rays go to the world by ``R_bike @ R_cam``. Each
camera gets its own cubemap rendered at ``c`` with the cube axes along the world axes (x east,
y down, z north), only the texels its layer reads (``read_texels``, a kernel), at the face
size it needs (``sizing.required_face_size`` over every attitude, capped by ``max_face_size``;
or ``face_size`` for all), so that frame ``k`` depends on the configuration and ``k`` only, not
on the number of frames (a run of 12 frames extends a run of 8). The built-in town is flat,
so the ride is made with ``town_route(seed, town)`` (S-bends between the lanes of the main
street in town 1, right turns at the crossings of towns 2 and 3): pitch comes from the
suspension only. The images are encoded and written by threads while the next camera renders
(`FrameRenderer`). With ``antialias=k`` > 1 (the default up to 512 x 512 pixels:
`default_antialias`) each cube texel on an edge is the mean of ``k x k`` rays over its
footprint and each RGB pixel the mean of 2 x 2 rays over its own; labels and depth stay the
texel and pixel centres' point samples.

``NNNNNN`` is the frame number (zero-padded to 6 digits). Every file is written atomically
(temporary file + rename). A frame is finished when its ``.done`` marker and all its files
exist; a rerun with the same configuration skips finished frames (and leaves their files and
the unchanged per-run files untouched), so an interrupted run resumes where it stopped; a
rerun with more frames extends the dataset, and one with another configuration in the same
folder is refused (`data.resume`; a manifest written before ``antialias`` existed is one of
``antialias=1``). A rerun checks the files of the finished frames (`data.integrity`) and
renders again those with a damaged file. Frames are independent: ``workers``
processes take a frame (or a shard's frames) at a time and report each finished frame to the
progress bar (`processes.run_in_processes`; the frames: `render_chunk`, a plain function of
the configuration and the frame numbers); nothing uses a global random state (the weather of a
frame, when several are given, is drawn from ``numpy.random.default_rng([seed, frame])``), so
the files do not depend on the number of workers. Ctrl-C stops a run within 2 s with any
number of workers (they finish the frame in flight or drop it: its files are whole or not
there), raising `Interrupted` with the frames kept; the same call renders the rest.

Past one machine (`data.distributed`): ``ray`` runs chunks of frames as Ray tasks
(`render_task`), ``shard=(K, N)`` renders run ``K`` of ``N``'s share for schedulers
without Ray; both write the same files as one process. ``format="webdataset"`` also packs the
frames into WebDataset shards (`data.shards`), each by the task that rendered them.

``rig="woodscape"`` (``generate --rig woodscape``) renders WoodScape's four cameras on a car
instead, with their previous images, through the same frame loop, and writes WoodScape's
layout (`data.woodscape`: the cameras, the car's drive, the files).
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..scenes import ride as _ride
from ..scenes import routes as _routes
from ..cubemap.faces import FACES
from ..io import atomic_write_bytes, atomic_write_text, colorize, write_exr, write_image
from ..io.atomic import folder_lock, remove_stale_temporaries, remove_temporaries
from . import distributed, shards
from .processes import run_in_processes
from . import format as fmt
from . import woodscape
from .resume import config_changes  # noqa: F401 (re-exported)
from .resume import extend_shards, folder_frames, render_damaged_again
from .contact_sheet import SHEET_CELL, SHEET_COLUMNS, contact_sheet  # noqa: F401 (re-exported)
from .run_files import write_run_files
from .objects import (encode_objects, instance_image, instance_objects, pack_instances,
                      unpack_instances)
from ..io.images import require_pillow
from ..cameras.presets import catadioptric, fisheye
from ..cubemap.cone import camera_cone, cone_texels, grow_texels
from ..render.kernels.cone import read_texels
from ..render.layer import OmniProjection
from ..render.reproject import equirectangular_camera
from ..scenes.town import CARLA_PRESETS, LAYOUTS, WEATHERS, Town
from ..render.sizing import (MEMORY_PER_PIXEL, PROCESS_MEMORY, available_memory,
                             required_face_size)

__all__ = ["CAMERAS", "FORMATS", "RIGS", "RIG_POSITIONS", "DatasetConfig", "FrameRenderer",
           "Interrupted", "check_memory", "contact_sheet", "estimate_memory", "generate",
           "render_chunk", "render_frame", "render_frames", "render_task"]

#: The rig's cameras, in this order.
CAMERAS = ("fisheye_left", "fisheye_right", "catadioptric_left", "catadioptric_right")

#: Camera centres in the rig frame (x right, y down, z forward), metres.
RIG_POSITIONS = {
    "fisheye_left": (-0.4, -0.8, 0.6),
    "fisheye_right": (0.4, -0.8, 0.6),
    "catadioptric_left": (-0.4, -1.0, 0.4),
    "catadioptric_right": (0.4, -1.0, 0.4),
}

#: The rigs ``generate`` renders: OmniScape's motorcycle (this module's docstring; its layout
#: `data.format`) and WoodScape's car (`data.woodscape`: its cameras, drive and layout).
RIGS = ("omniscape", "woodscape")
#: Each rig's cameras and default image size ``(H, W)``.
_RIG_CAMERAS = {"omniscape": CAMERAS, "woodscape": woodscape.CAMERAS}
_RIG_IMAGE_SIZE = {"omniscape": (256, 256), "woodscape": woodscape.IMAGE_SIZE}

#: Centre of the panorama in the rig frame, metres.
PANORAMA_POSITION = (0.0, -0.9, 0.0)


#: Smallest face and image sizes accepted: below 8 texels a face has hardly an interior for
#: bilinear sampling and its resampled border, and an 8-pixel image is a smoke test already.
MIN_FACE_SIZE = MIN_IMAGE_SIZE = 8

#: Peak memory of one process rendering a frame, per texel of the largest cube one camera
#: renders, bytes: the cube's outputs (RGB, planar depth, range, labels, instance ids: 32
#: bytes, in buffers kept from camera to camera, and the labels with the instance ids packed
#: into one int64 map: 8), its rays (12, kept per face size), the layer's padded atlases,
#: and the Embree scene and ray batches (a few MB, not per texel). Measured peaks
#: (``VmHWM`` of a fresh process, ``render_frame``; 2 cores, the Embree town) above the
#: process's own 295-327 MB: 197 bytes per texel at 6 x 320^2 (one camera, 160^2 image),
#: 230 at the default (256^2 images), 181 at 512^2 and 116 at 1024^2 once the pixels' share
#: (``MEMORY_PER_PIXEL``) is taken off; with ``sizing.PROCESS_MEMORY`` (700 MB) the estimate
#: lies 1.6-2x above these peaks (tests/test_dataset.py checks a run against it); 12 bytes
#: added since for the instance ids (measured before them).
MEMORY_PER_TEXEL = 232


@dataclass
class DatasetConfig:
    """What ``generate`` writes (everything that changes the files; not ``workers``)."""

    frames: int = 8
    fps: float = 2.0
    image_size: tuple[int, int] | None = None     # (H, W); None: the rig's (256 or 966x1280)
    face_size: int | None = None                  # None: per camera, required_face_size
    max_face_size: int = 1024
    cameras: tuple[str, ...] | None = None        # None: all the rig's
    weather: tuple[str, ...] = CARLA_PRESETS    # one drawn per frame when several
    seed: int = 0
    save_cubemaps: bool = False
    save_panorama: bool = False
    town: int = 1                                 # the town's layout: scenes.town.LAYOUTS
    antialias: int | None = None                  # None: default_antialias(image_size)
    min_object_pixels: int = 1                    # objects files: objects of this many pixels
    rig: str = "omniscape"                        # RIGS: the vehicle, cameras and layout

    def __post_init__(self):
        if self.image_size is None:   # an unknown rig: validate names it
            self.image_size = _RIG_IMAGE_SIZE.get(self.rig, _RIG_IMAGE_SIZE["omniscape"])
        if self.cameras is None:
            self.cameras = _RIG_CAMERAS.get(self.rig, CAMERAS)
        self.image_size = tuple(int(s) for s in self.image_size)
        self.cameras = tuple(self.cameras)
        self.weather = tuple(self.weather)
        if self.antialias is None:   # recorded as the number it stands for (to_dict)
            self.antialias = default_antialias(self.image_size)
        self.validate()

    def validate(self) -> None:
        def positive_int(name, value, minimum=1, unit=""):
            if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
                raise ValueError(f"{name}: expected an integer of at least {minimum}{unit}, got "
                                 f"{value!r}")
        if self.rig not in RIGS:
            raise ValueError(f"rig: expected one of {RIGS}, got {self.rig!r}")
        positive_int("frames", self.frames)
        positive_int("antialias", self.antialias)
        positive_int("min_object_pixels", self.min_object_pixels)
        positive_int("max_face_size", self.max_face_size, MIN_FACE_SIZE, " texels")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {self.seed!r}")
        if isinstance(self.town, bool) or self.town not in LAYOUTS:
            raise ValueError(f"town: expected one of {sorted(LAYOUTS)} "
                             f"({', '.join(f'{k} {v}' for k, v in LAYOUTS.items())}), got "
                             f"{self.town!r}")
        if self.face_size is not None:
            positive_int("face_size", self.face_size, MIN_FACE_SIZE, " texels")
        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps: expected a positive number, got {self.fps!r}")
        if len(self.image_size) != 2 or min(self.image_size) < MIN_IMAGE_SIZE:
            raise ValueError(f"image_size: expected (H, W), both at least {MIN_IMAGE_SIZE} "
                             f"pixels, got {self.image_size!r}")
        if not self.cameras:
            raise ValueError("cameras: expected at least one camera")
        for name in self.cameras:
            if name not in _RIG_CAMERAS[self.rig]:
                raise ValueError(f"cameras: unknown camera {name!r} of the {self.rig} rig; "
                                 f"expected some of {', '.join(_RIG_CAMERAS[self.rig])}")
        if self.rig == "woodscape" and (self.save_cubemaps or self.save_panorama):
            raise ValueError("save_cubemaps, save_panorama: not with rig='woodscape' (its "
                             "layout is WoodScape's)")
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras: duplicates in {self.cameras}")
        if not self.weather:
            raise ValueError("weather: expected at least one weather")
        for name in self.weather:
            if name not in WEATHERS:
                raise ValueError(f"weather: unknown weather {name!r}; expected some of "
                                 f"{', '.join(WEATHERS)}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["image_size"] = list(self.image_size)
        d["cameras"] = list(self.cameras)
        d["weather"] = list(self.weather)
        return d


#: Images of at most this many pixels are anti-aliased by default (`default_antialias`).
ANTIALIAS_PIXELS = 512 * 512


def default_antialias(image_size: tuple[int, ...]) -> int:
    """``DatasetConfig.antialias`` when not given: 2 for images of at most
    `ANTIALIAS_PIXELS` pixels, else 1.

    ``antialias=k`` renders each cube texel on an edge (``scenes.town.edge_texels``) as the mean
    of ``k x k`` rays over its footprint (``Town.render_cubemap``), and each RGB pixel as the
    mean of 2 x 2 rays over its footprint (``OmniProjection(supersample=2)``); labels and depth
    stay point samples of the texel and pixel centres, exactly as with ``k = 1``. Measured
    (``benchmarks/bench_town.py``, 2 cores, the default CARLA weathers): at 256 x 256 and the
    default face sizes the RGB against 8 x 8 traced rays a pixel goes from 36.4 dB (fisheye) and
    37.9 dB (catadioptric) with ``k = 1`` to 40.2 and 42.2 dB with ``k = 2`` (41.3 and 43.1 with
    ``k = 3``), and a frame from 0.51 s to 0.95 s (CPU 0.84 to 1.55 s). At 1024 x 1024
    ``k = 2`` takes a frame from 3.7 s to 6.3 s (CPU 7.0 to 11.9 s), past the 4 s a frame of the
    four cameras is meant to take on 2 cores: 1 there (``--antialias 2`` asks for it anyway).
    """
    return 2 if math.prod(image_size) <= ANTIALIAS_PIXELS else 1


# --------------------------------------------------------------------------------------------
# The plan: ride, cameras, face sizes (cheap; computed identically in every process)
# --------------------------------------------------------------------------------------------

def _make_camera(name: str, image_size: tuple[int, int]):
    """Camera ``name`` at ``image_size`` and its rotation camera -> rig."""
    if name in woodscape.CAMERAS:
        camera, T = woodscape.rig_camera(name, image_size)
        return camera, woodscape.rig_pose(T)[0]
    if name.startswith("fisheye"):
        return fisheye(image_size), torch.eye(3)
    return catadioptric(image_size, looking="down")


#: Half the built-in town's length along its road (``Town.length / 2``, metres).
_TOWN_HALF_LENGTH = 80.0


def town_route(seed: int, town: int = 1) -> _ride.Route:
    """The ride through the built-in town's layout ``town`` (`scenes.routes.route`):
    in town 1 it starts in the right-hand lane at the south end, heading north, and weaves
    between the lanes (S-bends of two opposite arcs, radius 60 to 120 m), about 140 m; in
    town 2 it turns right at the crossroads, in town 3 it goes round a block."""
    return _routes.route(town, seed, _TOWN_HALF_LENGTH)


def _make_ride(config: DatasetConfig) -> dict:
    return _ride.simulate(town_route(config.seed, config.town), float(config.fps),
                          frames=config.frames, seed=config.seed)


def _frame_weather(config: DatasetConfig, frame: int) -> str:
    if len(config.weather) == 1:
        return config.weather[0]
    rng = np.random.default_rng([config.seed, frame])
    return config.weather[int(rng.integers(len(config.weather)))]


class _Plan:
    """Everything a process needs to render any frame."""

    def __init__(self, config: DatasetConfig):
        self.config = config
        # WoodScape's car: its previous images' states too (woodscape.drive)
        self.frames, self.previous = (
            woodscape.drive(town_route(config.seed, config.town), float(config.fps),
                            config.frames, config.seed)
            if config.rig == "woodscape" else (_make_ride(config), None))
        self._poses = {}   # previous -> (R_bike (N, 3, 3) rig -> world, location (N, 3))
        for previous, states in ((False, self.frames), (True, self.previous)):
            if states is not None:
                self._poses[previous] = (_ride.camera_rotation(states).double(),
                                         _ride.carla_to_world(states["location"]).double())
        self.R_bike, self.location = self._poses[False]
        self.cameras = {}
        self._faces: dict[tuple[str, int, bool], torch.Tensor] = {}
        self._texels: tuple[tuple[str, int, bool], torch.Tensor] | None = None
        sizes = _face_sizes(config)
        for name in config.cameras:
            extra = {}
            if config.rig == "woodscape":   # T_vehicle: camera -> vehicle (ISO 8855)
                camera, extra["T_vehicle"] = woodscape.rig_camera(name, config.image_size)
                r_cam, position = woodscape.rig_pose(extra["T_vehicle"])
            else:
                camera, r_cam = _make_camera(name, config.image_size)
                position = torch.tensor(RIG_POSITIONS[name], dtype=torch.float64)
            self.cameras[name] = dict(camera=camera, r_cam=r_cam.double(),
                                      face_size=int(sizes[name]), position=position, **extra)
        h = config.image_size[0]
        self.panorama_size = (h, 2 * h)
        self.panorama_face = _panorama_face(config.max_face_size, h)

    def weather(self, k: int) -> str:
        """The weather of frame ``k``."""
        return _frame_weather(self.config, k)

    def rotation(self, name: str, k: int, previous: bool = False) -> torch.Tensor:
        """Camera -> world (= cube) rotation of camera ``name`` at frame ``k`` (``previous``:
        at its previous image, rig woodscape), float64."""
        return self._poses[previous][0][k] @ self.cameras[name]["r_cam"]

    def centre(self, name: str, k: int, previous: bool = False) -> torch.Tensor:
        r_bike, location = self._poses[previous]
        return location[k] + r_bike[k] @ self.cameras[name]["position"]

    def faces(self, name: str, k: int, previous: bool = False) -> torch.Tensor:
        """``(6,)`` bool: the faces camera ``name`` reads at frame ``k``: those with a texel in
        its cone of view (`texels`; cached). A superset of ``sizing.visible_faces``'
        exact answer, which costs seconds per camera and frame at 1024 x 1024 (measured: the
        same faces on the default ride at 256 x 256; at 48 x 48 and on the turns of towns 2
        and 3, now and then one more face, of which a few texels are traced)."""
        if (name, k, previous) not in self._faces:
            self._faces[name, k, previous] = self.texels(name, k, previous).flatten(1).any(1)
        return self._faces[name, k, previous]

    def texels(self, name: str, k: int, previous: bool = False) -> torch.Tensor:
        """``(6, F, F)`` bool: the cube texels within camera ``name``'s cone of view at frame
        ``k`` (`cubemap.cone`: `camera_cone`, `cone_texels`), a superset of those its layer
        reads (the last one kept)."""
        if self._texels is None or self._texels[0] != (name, k, previous):
            c = self.cameras[name]
            if "cone" not in c:
                c["cone"] = camera_cone(c["camera"], c["face_size"])
            # the optical axis, in the world (cube) frame
            axis = self.rotation(name, k, previous)[:, 2]
            self._texels = ((name, k, previous), cone_texels(c["face_size"], axis, c["cone"]))
        return self._texels[1]

    def files(self, k: int) -> list[str]:
        """Relative paths of every file of frame ``k`` (the marker excluded)."""
        if self.config.rig == "woodscape":
            return woodscape.frame_files(self.config.cameras, k)
        out = []
        for name in self.config.cameras:
            out += [fmt.frame_file(name, m, k) for m in fmt.MODALITIES]
            if self.config.save_cubemaps:
                out += [fmt.cubemap_file(name, m, k, face) for face, need in
                        zip(FACES, self.faces(name, k).tolist()) if need
                        for m in fmt.CUBE_MODALITIES]
        if self.config.save_panorama:
            out += [fmt.panorama_file(m, k) for m in fmt.CUBE_MODALITIES]
        return out

    def finished(self, out: Path, k: int) -> bool:
        """Whether frame ``k`` is finished in ``out``: its marker and all its files."""
        return (out / fmt.marker(k)).is_file() and all((out / f).is_file()
                                                        for f in self.files(k))


# --------------------------------------------------------------------------------------------
# Rendering one frame (in a worker process or in the main one)
# --------------------------------------------------------------------------------------------

class FrameRenderer:
    """Renders frames of one configuration: the plan, the town and a layer per camera, built
    once and kept for every frame it renders (in the main process, or in one task of a
    worker).

    Per camera, the town traces only the texels the layer reads: its taps' under the frame's
    attitude (`render.kernels.cone.read_texels`, within the cone of `camera_cone`; the layer's
    output is the same bit for bit as from whole faces, tests/test_dataset.py), unless
    ``save_cubemaps`` asks for whole faces. The cubes are rendered into buffers kept from
    camera to camera and frame to frame, and each camera's images are converted, encoded and
    written by ``writers`` threads while the next camera renders (a frame's marker once all its
    files are written)."""

    def __init__(self, config: DatasetConfig, *, writers: int = 2) -> None:
        self.config = config
        self.plan = _Plan(config)
        self.town = Town(config.seed, layout=config.town)
        self.writers = int(writers)
        self._layers: dict[str, OmniProjection] = {}
        self._cubes: dict[int, dict[str, torch.Tensor]] = {}

    def _layer(self, key: str, camera, face_size: int) -> OmniProjection:
        if key not in self._layers:
            # fused_grid=False: the eager grid, no torch.compile start-up in every worker;
            # anti-aliased cubes: each RGB pixel the mean of 2 x 2 rays over its footprint
            # (labels and depth stay the pixel centre's: OmniProjection's supersample)
            self._layers[key] = OmniProjection(
                camera, face_size, fused_grid=False,
                supersample=2 if self.config.antialias > 1 else 1)
        return self._layers[key]

    def _cube_buffers(self, face_size: int) -> dict[str, torch.Tensor]:
        """Output tensors of ``Town.render_cubemap`` for this face size, kept and reused (the
        last two face sizes)."""
        if face_size not in self._cubes:
            if len(self._cubes) >= 2:
                self._cubes.pop(next(iter(self._cubes)))
            F = face_size
            self._cubes[F] = {"rgb": torch.empty(1, 6, 3, F, F),
                              "depth": torch.empty(1, 6, F, F),
                              "labels": torch.empty(1, 6, F, F, dtype=torch.int64),
                              "range": torch.empty(1, 6, F, F),
                              "instances": torch.empty(1, 6, F, F, dtype=torch.int32),
                              "packed": torch.empty(1, 6, F, F, dtype=torch.int64)}
        return self._cubes[face_size]

    def texels(self, name: str, k: int, previous: bool = False) -> torch.Tensor | None:
        """``(6, F, F)`` bool: the texels camera ``name``'s layer reads at frame ``k``
        (``render.kernels.cone.read_texels`` of its rays; within ``_Plan.texels``' cone), or
        None with ``save_cubemaps`` (whole faces). With ``antialias``, grown by a texel on each
        face: a texel's anti-aliasing compares it with its 8 neighbours on the face
        (``scenes.town.edge_texels``), so every texel read has them all rendered."""
        if self.config.save_cubemaps:
            return None
        c, rotation = self.plan.cameras[name], self.plan.rotation(name, k, previous).float()
        layer = self._layer(name, c["camera"], c["face_size"])
        rays_s, valid_s, rays_c, valid_c = layer.camera_rays()
        texels = read_texels(rays_s, valid_s, rotation, c["face_size"], layer.pad)
        if layer.supersample > 1:   # depth and labels: the pixel centres' rays
            texels |= read_texels(rays_c, valid_c, rotation, c["face_size"], layer.pad)
        return texels if self.config.antialias == 1 else grow_texels(texels)

    def cubemap(self, name: str, k: int, previous: bool = False) -> dict[str, torch.Tensor]:
        """Camera ``name``'s cubemap of frame ``k`` (``Town.render_cubemap``: the faces and
        texels it reads, in the frame's weather, with the configuration's ``antialias``), in
        this renderer's buffers: valid until the next cubemap of the same face size.
        ``previous``: at the frame's previous image (rig woodscape)."""
        config, plan = self.config, self.plan
        F = plan.cameras[name]["face_size"]
        states = plan.previous if previous else plan.frames
        return self.town.render_cubemap(
            plan.centre(name, k, previous).float(), None, F, faces=plan.faces(name, k, previous),
            texels=self.texels(name, k, previous), t=float(states["time"][k]),
            weather=_frame_weather(config, k), out=self._cube_buffers(F),
            antialias=config.antialias)

    def render(self, out: str | Path, k: int) -> int:
        """Render and write every file of frame ``k``, then its marker. Returns ``k``."""
        from concurrent.futures import ThreadPoolExecutor, wait

        out = Path(out)
        config, plan, town = self.config, self.plan, self.town
        t = float(plan.frames["time"][k])
        weather = _frame_weather(config, k)
        pending = []
        with ThreadPoolExecutor(max(1, self.writers)) as pool:
            try:
                with torch.no_grad():
                    for name in config.cameras:
                        c = plan.cameras[name]
                        F = c["face_size"]
                        faces = plan.faces(name, k)
                        cube = self.cubemap(name, k)
                        # labels and instance ids in one nearest pass
                        packed = pack_instances(cube["labels"], cube["instances"],
                                                self._cubes[F]["packed"])
                        res = self._layer(name, c["camera"], F).render(
                            rgb=cube["rgb"], depth=cube["depth"], labels=packed,
                            rotation=plan.rotation(name, k).float())
                        # res is this camera's own: its writers may run while the next renders
                        if config.rig == "woodscape":
                            pending += self._woodscape_camera(pool, out, name, k, res)
                        else:
                            pending += [pool.submit(job) for job in _camera_writes(
                                out, name, k, res, config.min_object_pixels)]
                        if config.save_cubemaps:
                            for i, (face, need) in enumerate(zip(FACES, faces.tolist())):
                                if need:
                                    pending.append(pool.submit(
                                        _write_modalities,
                                        functools.partial(_cube_path, out, name, k, face),
                                        cube["rgb"][0, i].clone(), cube["depth"][0, i].clone(),
                                        cube["labels"][0, i].clone()))
                    if config.save_panorama:
                        centre = plan.location[k] + plan.R_bike[k] @ torch.tensor(
                            PANORAMA_POSITION, dtype=torch.float64)
                        F = plan.panorama_face
                        cube = town.render_cubemap(centre.float(), None, F, t=t,
                                                   weather=weather, out=self._cube_buffers(F),
                                                   antialias=config.antialias)
                        h, w = plan.panorama_size
                        res = self._layer("panorama", equirectangular_camera(w, h), F).render(
                            rgb=cube["rgb"], depth=cube["depth"], labels=cube["labels"],
                            rotation=plan.R_bike[k].float())
                        pending.append(pool.submit(
                            _write_modalities, functools.partial(_panorama_path, out, k),
                            res["rgb"][0], res["depth"][0, 0], res["labels"][0]))
            finally:
                wait(pending)   # no write goes on after this returns or raises
            for job in pending:
                job.result()    # the first error of a writer
        atomic_write_text(out / fmt.marker(k), json.dumps({"frame": k, "weather": weather})
                          + "\n")
        return k

    def _woodscape_camera(self, pool, out: Path, name: str, k: int,
                          res: dict[str, torch.Tensor]) -> list:
        """Write camera ``name``'s files of frame ``k`` in WoodScape's layout (``res``: its
        render), then render its previous image and write it: the writers' jobs."""
        plan, c = self.plan, self.plan.cameras[name]
        jobs = [pool.submit(lambda: woodscape.write_camera(
            out, name, k, _to_uint8(res["rgb"][0]), res, c["camera"], c["T_vehicle"],
            plan.frames, self.config.min_object_pixels))]
        cube = self.cubemap(name, k, previous=True)
        before = self._layer(name, c["camera"], c["face_size"]).render(
            rgb=cube["rgb"], rotation=plan.rotation(name, k, previous=True).float())
        jobs.append(pool.submit(lambda: woodscape.write_previous(
            out, name, k, _to_uint8(before["rgb"][0]), plan.previous)))
        return jobs


def _cube_path(out: Path, name: str, k: int, face: str, modality: str) -> Path:
    return out / fmt.cubemap_file(name, modality, k, face)


def _panorama_path(out: Path, k: int, modality: str) -> Path:
    return out / fmt.panorama_file(modality, k)


def _camera_writes(out: Path, name: str, k: int, res: dict[str, torch.Tensor],
                   min_object_pixels: int = 1) -> list[Callable[[], None]]:
    """The jobs writing camera ``name``'s files of frame ``k`` (``res``: the layer's outputs,
    labels packed with instance ids; objects of at least ``min_object_pixels`` pixels): three,
    so the writer threads share a camera's encoding (the RGB PNG is about a third of it)."""
    def path(modality: str) -> Path:
        return out / fmt.frame_file(name, modality, k)

    return [lambda: write_image(path("rgb"), _to_uint8(res["rgb"][0])),
            lambda: write_exr(path("depth"), res["depth"][0, 0].float()),
            lambda: _write_labels(path, res, min_object_pixels)]


def _write_labels(path: Callable[[str], Path], res: dict[str, torch.Tensor],
                  min_object_pixels: int) -> None:
    """A camera's label, colour-label, validity and instance images and its objects file."""
    labels, instances = unpack_instances(res["labels"][0])
    valid = res["valid"][0, 0]
    ids = labels.to(torch.uint8).numpy()   # 0..12 and 255 (IGNORE_INDEX)
    write_image(path("labels"), ids)
    write_image(path("labels_color"), colorize(ids))
    write_image(path("valid"), (valid.to(torch.uint8) * 255).numpy())
    write_image(path("instances"), instance_image(instances))
    atomic_write_text(path("objects"), encode_objects(
        instance_objects(instances, labels, min_pixels=min_object_pixels)))


def _write_modalities(path: Callable[[str], Path], rgb: torch.Tensor, depth: torch.Tensor,
                      labels: torch.Tensor) -> None:
    """A saved cube face or panorama: ``rgb (3, h, w)`` float, ``depth (h, w)``, ``labels``."""
    write_image(path("rgb"), _to_uint8(rgb))
    write_exr(path("depth"), depth.float())
    write_image(path("labels"), labels.to(torch.uint8).numpy())


def render_frames(config: DatasetConfig, out: str | Path, frames: list[int]) -> list[int]:
    """Render and write ``frames`` of ``config`` into ``out``: a plain function of its
    arguments (the files depend on the configuration and the frame numbers only), which any
    process or scheduler can call for any share of the frames. Returns the frames."""
    renderer = FrameRenderer(config)
    return [renderer.render(out, k) for k in frames]


def render_frame(config: DatasetConfig, out: str | Path, k: int) -> int:
    """``render_frames(config, out, [k])``. Returns ``k``."""
    return render_frames(config, out, [k])[0]


def _worker_setup(config: DatasetConfig, out: str, frames_per_shard: int | None) -> Callable:
    """A worker process's state (`processes.run_in_processes`): one thread for torch, a
    renderer built once; returns the function that renders a unit of frames."""
    torch.set_num_threads(1)
    return functools.partial(_render_unit, FrameRenderer(config), Path(out), frames_per_shard)


def _render_unit(renderer: FrameRenderer, out: Path, frames_per_shard: int | None,
                 frames: list[int], report: Callable[[int], None]) -> None:
    render_chunk(renderer.config, out, frames, frames_per_shard, renderer=renderer,
                 on_frame=report)


def _frame_folders(plan: _Plan, out: Path) -> list[Path]:
    """The folders a frame's files (and its marker, and a shard) are written in."""
    config = plan.config
    if config.rig == "woodscape":
        return woodscape.frame_folders(out)
    folders = [out, out / fmt.DONE, out / fmt.SHARDS]
    for name in config.cameras:
        folders += [out / name / m for m in fmt.MODALITIES]
        if config.save_cubemaps:
            folders += [out / name / "cubemap" / m for m in fmt.CUBE_MODALITIES]
    if config.save_panorama:
        folders += [out / "panorama" / m for m in fmt.CUBE_MODALITIES]
    return folders


class Interrupted(KeyboardInterrupt):
    """``generate`` stopped by Ctrl-C (a `KeyboardInterrupt`), after its workers stopped:
    what the folder keeps. The same call renders the rest.

    Attributes:
        kept: the frames of the run (of its share, with ``shard``) finished in the folder.
        frames: the run's frames (of its share).
        out: the dataset folder.
    """

    def __init__(self, kept: int, frames: int, out: Path):
        super().__init__(f"interrupted: {kept} of {frames} frames kept in {out}")
        self.kept, self.frames, self.out = kept, frames, out


def _to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` float in [0, 1] -> ``(H, W, 3)`` uint8."""
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()


# --------------------------------------------------------------------------------------------
# generate
# --------------------------------------------------------------------------------------------

#: ``generate``'s output formats: the folder (`format`), and the folder with WebDataset
#: shards (`shards`).
FORMATS = ("folder", "webdataset")


def generate(out: str | Path, config: DatasetConfig | None = None, *, workers: int = 1,
             ray: str | bool | None = None, shard: tuple[int, int] | None = None,
             format: str = "folder", frames_per_shard: int | None = None,
             progress: bool | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Write (or complete, or extend to more frames) the dataset of ``config`` in ``out``.

    Args:
        out: the dataset folder (created). With ``ray`` or ``shard`` across machines, a
            folder every machine sees at the same path (shared storage).
        config: a `DatasetConfig` (default: all defaults).
        workers: processes rendering frames in parallel on this machine (1: in this process),
            each taking the next frame (or shard) not taken yet.
        ray: chunks of frames as Ray tasks (`distributed.run_on_ray`): the address of a
            cluster (``"HOST:PORT"``, ``"auto"``), or True for ``$RAY_ADDRESS``, else the
            cluster of ``ray start`` on this machine, else a local cluster started for the run
            (`distributed.ray_cluster`); None (default): no Ray. Not with ``workers``.
        shard: ``(K, N)``: only run ``K`` of ``N``'s share, frames ``K, K + N, ...`` (with
            ``format="webdataset"``, the frames of shards ``K, K + N, ...``); ``N`` such runs,
            anywhere and at once, write the dataset one run writes. Each locks its own share.
        format: ``"folder"`` (default), or ``"webdataset"``: also pack the frames into
            WebDataset shards of ``frames_per_shard`` frames (`data.shards`), each by the
            task that rendered them.
        frames_per_shard: default, that of the shards in ``out``, else
            ``shards.FRAMES_PER_SHARD``; only with ``format="webdataset"``.
        progress: show a tqdm bar on stderr (default: when stderr is a terminal).
        log: called with one-line messages (default: nothing).

    Returns:
        ``{"rendered": [frame numbers], "skipped": [frame numbers], "face_sizes": {camera: F}}``
        (``skipped``: finished before the run).

    Raises:
        ValueError: bad configuration or argument, or ``out`` holds a dataset of another
            configuration or of more frames (or shards of another ``frames_per_shard``).
        ImportError: ``ray`` without Ray installed, or no Pillow to write the images with
            (or OpenCV, with ``rig="woodscape"``: its polygons), at once.
        MemoryError: the run would not fit in memory (`check_memory`; with ``ray``, in
            any node of the cluster; before any work).
        omniscape_torch.data.distributed.TaskErrors: with ``ray``, frames that failed for good,
            each with its error; the others are written, and the same call renders the rest.
        omniscape_torch.io.atomic.FolderBusyError: another run is writing ``out`` (or the same
            share of it).
        OSError: ``out`` cannot be written (the message names the path).
        Interrupted: Ctrl-C (a `KeyboardInterrupt`), once the workers have stopped (within
            2 s): how many frames the folder keeps; the same call renders the rest.
    """
    config = DatasetConfig() if config is None else config
    config.validate()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers: expected a positive integer, got {workers!r}")
    require_pillow()   # the images are PNGs written with Pillow: say so before any work
    use_ray = ray is not None and ray is not False
    if use_ray:
        if workers != 1:   # a usage error first, whether or not Ray is installed
            raise ValueError(f"workers: with ray, the cluster's CPUs render the frames; give "
                             f"one or the other, got workers={workers}")
        distributed.import_ray()
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {FORMATS}, got {format!r}")
    if config.rig == "woodscape":
        if format != "folder":
            raise ValueError(f"format: WoodScape's layout is a folder, got {format!r}")
        woodscape.require_opencv()   # its polygons: say so before any work
    if frames_per_shard is not None:
        shards.check_frames_per_shard(frames_per_shard)
        if format != "webdataset":
            raise ValueError("frames_per_shard: only with format='webdataset'")
    shard = distributed.check_shard(shard)
    log = log or (lambda msg: None)
    out = Path(out)
    if not use_ray:
        check_memory(config, workers)
    # runs of other shares of the frames may write the folder at the same time
    lock = out if shard is None else out / f".shard-{shard[0]}-of-{shard[1]}"
    try:
        with folder_lock(lock):   # its file removed when the run ends, however it ends
            return _generate(out, config, workers, progress, log, ray=ray if use_ray else None,
                             shard=shard, frames_per_shard=(
                                 shards.resolve_frames_per_shard(out, frames_per_shard)
                                 if format == "webdataset" else None))
    finally:
        if shard is not None:   # the share's lock folder, if empty (another run may hold it)
            with contextlib.suppress(OSError):
                lock.rmdir()


def _generate(out: Path, config: DatasetConfig, workers: int, progress: bool | None,
              log: Callable[[str], None], *, ray: str | bool | None = None,
              shard: tuple[int, int] | None = None,
              frames_per_shard: int | None = None) -> dict:
    """``generate`` inside the folder's lock (``frames_per_shard``: WebDataset shards)."""
    old_frames = folder_frames(out, config)
    # A run killed mid-write leaves its temporaries (the finished files are whole: written by
    # rename); they carry their process id, and only those of ended processes are removed.
    # Not by a share of a run: the others may run on other machines, whose processes this one
    # cannot see.
    stale = remove_stale_temporaries(out) if shard is None else []
    if stale:
        log(f"removed {len(stale)} temporary file(s) of an interrupted run")
    if old_frames is not None and old_frames < config.frames:
        log(f"extending the dataset in {out} from {old_frames} to {config.frames} frames (its "
            f"frames are kept: frame k depends on the settings and k only)")
        extend_shards(out, config)
    renderer = FrameRenderer(config)
    plan = renderer.plan
    (woodscape.write_run_files if config.rig == "woodscape" else write_run_files)(plan, out, log)
    s = frames_per_shard
    if s is None:
        units = [[k] for k in range(config.frames)]
    else:
        shards.write_index(out, config.frames, config.cameras, s)
        units = shards.shard_groups(config.frames, s)
    units = distributed.shard_part(units, shard)

    render_damaged_again(plan, out, [k for u in units for k in u], log)

    def finished(k: int) -> bool:
        return plan.finished(out, k) and (s is None or (out / fmt.shard_file(k // s)).is_file())

    todo_units = [u for u in units if not all(finished(k) for k in u)]
    frames = [k for u in units for k in u]
    todo = [k for u in todo_units for k in u]
    skipped = [k for k in frames if plan.finished(out, k)]
    sizes = {n: c["face_size"] for n, c in plan.cameras.items()}
    log(f"{len([k for k in todo if k not in skipped])} frame(s) to render, {len(skipped)} "
        f"finished" + ("" if shard is None else f" (share {shard[0]} of {shard[1]})")
        + "; face sizes " + ", ".join(f"{n} {sz}" for n, sz in sizes.items()))
    if progress is None:
        progress = sys.stderr.isatty()
    rendered: list[int] = []
    failures: dict[int, str] = {}
    if ray is not None and todo:
        done, failures = distributed.run_on_ray(
            render_task, (config, str(out.resolve()), s), todo, address=ray,
            chunks=None if s is None else todo_units, memory=estimate_memory(config, 1),
            progress=progress, total=len(frames), initial=len(frames) - len(todo),
            desc="generate", unit="frame", log=log)
        rendered = sorted(done)
        failures = {k: m for k, m in failures.items() if not finished(k)}
    elif todo:
        from tqdm import tqdm
        bar = tqdm(total=len(frames), initial=len(frames) - len(todo), disable=not progress,
                   file=sys.stderr, unit="frame", desc="generate")

        def on_frame(k: int) -> None:   # the bar moves per frame, with any number of workers
            rendered.append(k)
            bar.update(1)

        try:
            if workers == 1 or len(todo_units) <= 1:
                for unit in todo_units:
                    render_chunk(config, out, unit, s, renderer=renderer, on_frame=on_frame)
            else:   # the workers take a unit (a frame, or a shard's frames) at a time
                folders = _frame_folders(plan, out)
                run_in_processes(_worker_setup, (config, str(out), s), todo_units, workers,
                                 on_frame, cleanup=lambda pids: remove_temporaries(folders, pids))
        except KeyboardInterrupt:
            raise Interrupted(sum(plan.finished(out, k) for k in frames), len(frames),
                              out) from None
        finally:
            bar.close()
    sheet = out / fmt.CONTACT_SHEET
    if rendered or not sheet.is_file():
        shown = _sheet_frames(config, [k for k in range(config.frames) if plan.finished(out, k)]
                              if shard is None else None)
        if shown is not None and all(plan.finished(out, k)
                                     for k in (shown[0], *shown[1].values())):
            data = (woodscape.contact_sheet(out, config.cameras, shown[0])
                    if config.rig == "woodscape" else contact_sheet(out, config.cameras, *shown))
            if not sheet.is_file() or sheet.read_bytes() != data:
                atomic_write_bytes(sheet, data)
    if failures:
        raise distributed.TaskErrors("frame", failures, sorted(rendered))
    return {"rendered": sorted(rendered), "skipped": skipped, "face_sizes": sizes}


def render_chunk(config: DatasetConfig, out: str | Path, frames: list[int],
                 frames_per_shard: int | None = None, *,
                 renderer: FrameRenderer | None = None,
                 on_frame: Callable[[int], None] | None = None) -> list[int]:
    """Render the unfinished frames among ``frames`` of ``config`` into ``out`` and, with
    ``frames_per_shard``, pack each WebDataset shard of theirs whose frames are all finished
    and which is not there yet: a plain function of its arguments, which any process or
    scheduler can call for any share of the frames, as often as it likes (a repeated call
    finishes what an earlier one left). Stops at the first error. Returns the frames rendered.

    ``renderer``: a `FrameRenderer` of ``config`` to reuse (default: a new one).
    ``on_frame``: called with each frame's number once it is finished (a progress bar).
    """
    out = Path(out)
    renderer = FrameRenderer(config) if renderer is None else renderer
    rendered = []
    for k in frames:
        if not renderer.plan.finished(out, k):
            rendered.append(renderer.render(out, k))
            if on_frame is not None:
                on_frame(k)
    if frames_per_shard is not None:
        _pack_shards(renderer.plan, out, frames, frames_per_shard)
    return rendered


def render_task(config: DatasetConfig, out: str, frames_per_shard: int | None,
                frames: list[int]) -> tuple[dict[int, str], dict[int, str]]:
    """A Ray task of ``generate`` (`distributed.run_on_ray`): `render_chunk`,
    frame by frame, an error stopping only its frame. Returns ``({frame: "rendered"}, {frame:
    error message})``."""
    renderer = FrameRenderer(config)
    done: dict[int, str] = {}
    failures: dict[int, str] = {}
    for k in frames:
        try:
            for r in render_chunk(config, out, [k], renderer=renderer):
                done[r] = "rendered"
        except Exception as err:   # noqa: BLE001 - reported by frame, the others go on
            failures[k] = distributed.describe_error(err)
    if frames_per_shard is not None:
        try:
            _pack_shards(renderer.plan, Path(out), frames, frames_per_shard)
        except Exception as err:   # noqa: BLE001 - the shard's frames are not finished
            for k in frames:
                failures.setdefault(k, distributed.describe_error(err))
    return done, failures


def _pack_shards(plan: _Plan, out: Path, frames: list[int], frames_per_shard: int) -> None:
    """Write the WebDataset shards among those of ``frames`` whose frames are all finished and
    which are not written yet."""
    groups = shards.shard_groups(plan.config.frames, frames_per_shard)
    for index in sorted({k // frames_per_shard for k in frames}):
        group = groups[index]
        if not (out / fmt.shard_file(index)).is_file() and \
                all(plan.finished(out, k) for k in group):
            shards.write_shard(out, index, group, plan.config.cameras)


def _sheet_frames(config: DatasetConfig, done: list[int] | None
                  ) -> tuple[int, dict[str, int]] | None:
    """The frames the contact sheet shows: the middle one, and the first of each weather,
    among the finished frames ``done``; or, for a share of a run (``done`` None), among all
    the run's frames, so that whichever share finishes last writes the sheet a whole run
    writes. None when no frame is finished."""
    frames = list(range(config.frames)) if done is None else done
    if not frames:
        return None
    weathers: dict[str, int] = {}
    for k in frames:
        weathers.setdefault(_frame_weather(config, k), k)
    return frames[len(frames) // 2], weathers


# --------------------------------------------------------------------------------------------
# Memory: estimated before any work
# --------------------------------------------------------------------------------------------

#: Face sizes are computed on the image scaled down to at most this many pixels, then scaled
#: back (the rig's cameras scale with their image, and so does the face size they need, to
#: within a texel or two; an exact computation at 1024 x 1024 takes seconds).
SIZING_PIXELS = 2 ** 16


def _face_sizes(config: DatasetConfig, image_size: tuple[int, int] | None = None,
                memo: dict | None = None) -> dict[str, int]:
    """The face size of each camera for ``image_size`` (default the configuration's):
    ``face_size``, or ``required_face_size`` over every attitude (not the ride's: frame ``k``
    must not depend on the number of frames), capped by ``max_face_size``. ``memo``: a dict
    that keeps the sizes computed on scaled images across calls (a search over sizes)."""
    h, w = config.image_size if image_size is None else image_size
    if config.face_size is not None:
        return {name: config.face_size for name in config.cameras}
    scale = min(1.0, math.sqrt(SIZING_PIXELS / (h * w)))
    small = (max(MIN_IMAGE_SIZE, round(h * scale)), max(MIN_IMAGE_SIZE, round(w * scale)))
    memo = {} if memo is None else memo
    out = {}
    for name in config.cameras:
        key = (name.split("_")[0], small)   # per kind of camera: fisheye, catadioptric
        if key not in memo:
            memo[key] = required_face_size(_make_camera(name, small)[0], "any")
        need = memo[key]
        if small != (h, w):
            need = math.ceil(need * max(h / small[0], w / small[1]))
        out[name] = min(need, config.max_face_size)
    return out


def _largest_render(config: DatasetConfig, sizes: dict[str, int],
                    image_size: tuple[int, int] | None = None) -> tuple[int, int]:
    """Texels of the largest cube and pixels of the largest image one process renders."""
    h, w = config.image_size if image_size is None else image_size
    texels, pixels = 6 * max(sizes.values()) ** 2, h * w
    if config.save_panorama:
        texels = max(texels, 6 * _panorama_face(config.max_face_size, h) ** 2)
        pixels = max(pixels, 2 * h * h)
    return texels, pixels


def _panorama_face(max_face_size: int, height: int) -> int:
    """Face size of the panorama's cube: a texel per panorama pixel at the equator."""
    return max(MIN_FACE_SIZE, min(max_face_size, height // 2 * 2))


def estimate_memory(config: DatasetConfig, workers: int = 1, *,
                    image_size: tuple[int, int] | None = None, memo: dict | None = None) -> int:
    """Bytes ``generate(config, workers=workers)`` needs at its peak (for ``image_size``, by
    default the configuration's): per rendering process `PROCESS_MEMORY` plus the largest
    cube's texels and the largest image's pixels at their rates (`MEMORY_PER_TEXEL`,
    `MEMORY_PER_PIXEL`; cameras render one after the other), times the processes, plus
    the main process when workers render; with ``antialias`` > 1, 4 more times the pixels' rate
    (the layer's 2 x 2 rays a pixel: measured 683 bytes a pixel more at 512 x 512, a peak of
    958 MB against 779). ``memo``: as for ``_face_sizes``."""
    sizes = _face_sizes(config, image_size, memo)
    texels, pixels = _largest_render(config, sizes, image_size)
    per_pixel = MEMORY_PER_PIXEL * (5 if config.antialias > 1 else 1)
    per_process = PROCESS_MEMORY + MEMORY_PER_TEXEL * texels + per_pixel * pixels
    processes = min(workers, config.frames)
    return int(per_process * processes + (PROCESS_MEMORY if processes > 1 else 0))


def check_memory(config: DatasetConfig, workers: int = 1, available: int | None = None) -> None:
    """Refuse, before any work, a run that cannot fit in memory.

    Raises:
        MemoryError: `estimate_memory` exceeds ``available`` (default
            `available_memory`); the message gives both and the largest image size (and
            worker count) that fits.
    """
    need = estimate_memory(config, workers)
    available = available_memory() if available is None else available
    if need <= available:
        return
    h, w = config.image_size
    fits, memo = None, {}
    lo, hi = MIN_IMAGE_SIZE, max(h, w)          # the largest scale of (H, W) that fits
    while lo <= hi:
        mid = (lo + hi) // 2
        size = (round(h * mid / max(h, w)), round(w * mid / max(h, w)))
        if min(size) >= MIN_IMAGE_SIZE and estimate_memory(
                config, workers, image_size=size, memo=memo) <= available:
            fits, lo = size, mid + 1
        else:
            hi = mid - 1
    gb = 1e9
    hint = (f"the largest image size that fits is {fits[0]}x{fits[1]}" if fits else
            "no image size fits with these face sizes: lower the face size")
    if workers > 1:
        hint += ", or use fewer workers"
    texels, pixels = _largest_render(config, _face_sizes(config))
    raise MemoryError(
        f"this run needs about {need / gb:.1f} GB of memory ({min(workers, config.frames)} "
        f"process(es), each a cube of {texels / 1e6:.1f} M texels and an image of "
        f"{pixels / 1e6:.1f} M pixels), but {available / gb:.1f} GB are available; {hint}")
