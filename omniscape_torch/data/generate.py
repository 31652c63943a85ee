"""Write an OmniScape-like dataset: a motorcycle ride through the built-in town, seen by a rig of
stereo fisheye and stereo catadioptric cameras, with range depth, labels, intrinsics (also as
OCamCalib's ``calib_results.txt``, as the OmniScape dataset ships them: :mod:`.ocamcalib`, fitted
once per run), extrinsics, vehicle dynamics, and the instance ids and 2D boxes of the town's
vehicles, pedestrians, poles and traffic signs (:mod:`.objects`; ``omniscape-torch
generate``; the files: :mod:`.format`).

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
y down, z north), only the texels it reads (those in its cone of view), at the face size it needs
(``sizing.required_face_size`` over every attitude, capped by ``max_face_size``; or
``face_size`` for all), so that frame ``k`` depends on the configuration and ``k`` only, not
on the number of frames (a run of 12 frames extends a run of 8). The built-in town is flat,
so the ride is made with ``town_route(seed, town)`` (S-bends between the lanes of the main
street in town 1, right turns at the crossings of towns 2 and 3): pitch comes from the
suspension only. The images are encoded and written by threads while the next camera renders
(:class:`FrameRenderer`). With ``antialias=k`` > 1 (the default up to 512 x 512 pixels:
:func:`default_antialias`) each cube texel on an edge is the mean of ``k x k`` rays over its
footprint and each RGB pixel the mean of 2 x 2 rays over its own; labels and depth stay the
texel and pixel centres' point samples.

``NNNNNN`` is the frame number (zero-padded to 6 digits). Every file is written atomically
(temporary file + rename). A frame is finished when its ``.done`` marker and all its files
exist; a rerun with the same configuration skips finished frames (and leaves their files and
the unchanged per-run files untouched), so an interrupted run resumes where it stopped. A rerun
with another configuration in the same folder is refused (a manifest written before
``antialias`` existed is one of ``antialias=1``). Frames are independent: ``workers``
processes render shares of the frames (:func:`render_frames`, a plain function of the
configuration and the frame numbers); nothing uses a global random state (the weather of a frame,
when several are given, is drawn from ``numpy.random.default_rng([seed, frame])``), so the
files do not depend on the number of workers.

Past one machine (:mod:`.distributed`): ``ray`` runs chunks of frames as Ray tasks
(:func:`render_task`), ``shard=(K, N)`` renders run ``K`` of ``N``'s share for schedulers
without Ray; both write the same files as one process. ``format="webdataset"`` also packs the
frames into WebDataset shards (:mod:`.shards`), each by the task that rendered them.
"""

from __future__ import annotations

import csv
import functools
import io as _io
import json
import math
import platform
import signal
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..scenes import ride as _ride
from ..scenes import routes as _routes
from ..cubemap.faces import FACES
from ..io import (CLASSES, IGNORE_INDEX, atomic_write_bytes, atomic_write_text, colorize,
                 read_image, write_exr, write_image)
from ..io.atomic import folder_lock, remove_stale_temporaries
from . import distributed, shards
from . import format as fmt
from . import ocamcalib
from .objects import (encode_objects, instance_image, instance_objects, pack_instances,
                      unpack_instances)
from ..io.labels import PALETTE
from ..io.images import encode_image, require_pillow
from ..cameras.presets import catadioptric, fisheye
from ..cubemap.faces import face_axes
from ..render.layer import OmniProjection
from ..render.reproject import equirectangular_camera
from ..scenes.town import CARLA_PRESETS, LAYOUTS, WEATHERS, Town
from ..render.sizing import (MEMORY_PER_PIXEL, PROCESS_MEMORY, available_memory,
                             required_face_size)

__all__ = ["CAMERAS", "FORMATS", "RIG_POSITIONS", "DatasetConfig", "FrameRenderer",
           "check_memory", "contact_sheet", "estimate_memory", "generate", "render_chunk",
           "render_frame", "render_frames", "render_task"]

#: The rig's cameras, in this order.
CAMERAS = ("fisheye_left", "fisheye_right", "catadioptric_left", "catadioptric_right")

#: Camera centres in the rig frame (x right, y down, z forward), metres.
RIG_POSITIONS = {
    "fisheye_left": (-0.4, -0.8, 0.6),
    "fisheye_right": (0.4, -0.8, 0.6),
    "catadioptric_left": (-0.4, -1.0, 0.4),
    "catadioptric_right": (0.4, -1.0, 0.4),
}

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
    image_size: tuple[int, int] = (256, 256)      # (H, W)
    face_size: int | None = None                  # None: per camera, required_face_size
    max_face_size: int = 1024
    cameras: tuple[str, ...] = CAMERAS
    weather: tuple[str, ...] = CARLA_PRESETS    # one drawn per frame when several
    seed: int = 0
    save_cubemaps: bool = False
    save_panorama: bool = False
    town: int = 1                                 # the town's layout: scenes.town.LAYOUTS
    antialias: int | None = None                  # None: default_antialias(image_size)

    def __post_init__(self):
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
        positive_int("frames", self.frames)
        positive_int("antialias", self.antialias)
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
            if name not in CAMERAS:
                raise ValueError(f"cameras: unknown camera {name!r}; expected some of "
                                 f"{', '.join(CAMERAS)}")
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


def _setting(key: str, value) -> str:
    """A configuration value as the command line writes it."""
    if value is None:
        return "the default"
    if isinstance(value, bool):
        return "on" if value else "off"
    if key == "image_size" and isinstance(value, (list, tuple)) and len(value) == 2:
        return str(value[0]) if value[0] == value[1] else f"{value[0]}x{value[1]}"
    if isinstance(value, (list, tuple)):
        return ",".join(map(str, value))
    return str(value)


def config_changes(old: object, new: dict) -> str:
    """``": --image-size: the folder has 512, this run 256; ..."``: each setting of ``new`` (a
    :meth:`DatasetConfig.to_dict`) that differs from a folder's ``old`` one, by its option
    name, with both values; ``""`` when ``old`` is not a configuration (unreadable)."""
    if not isinstance(old, dict):
        return ""
    changes = [f"--{key.replace('_', '-')}: the folder has "
               f"{_setting(key, old[key]) if key in old else 'none'}, this run "
               f"{_setting(key, new[key]) if key in new else 'none'}"
               for key in dict.fromkeys([*new, *old]) if old.get(key) != new.get(key)]
    return ": " + "; ".join(changes) if changes else ""


#: Images of at most this many pixels are anti-aliased by default (:func:`default_antialias`).
ANTIALIAS_PIXELS = 512 * 512


def default_antialias(image_size: tuple[int, ...]) -> int:
    """``DatasetConfig.antialias`` when not given: 2 for images of at most
    :data:`ANTIALIAS_PIXELS` pixels, else 1.

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
    if name.startswith("fisheye"):
        return fisheye(image_size), torch.eye(3)
    return catadioptric(image_size, looking="down")


#: Half the built-in town's length along its road (``Town.length / 2``, metres).
_TOWN_HALF_LENGTH = 80.0


def town_route(seed: int, town: int = 1) -> _ride.Route:
    """The ride through the built-in town's layout ``town`` (:func:`..scenes.routes.route`):
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
        self.frames = _make_ride(config)
        self.R_bike = _ride.camera_rotation(self.frames).double()          # (N, 3, 3)
        self.location = _ride.carla_to_world(self.frames["location"]).double()  # (N, 3)
        self.cameras = {}
        self._faces: dict[tuple[str, int], torch.Tensor] = {}
        self._texels: tuple[tuple[str, int], torch.Tensor] | None = None
        sizes = _face_sizes(config)
        for name in config.cameras:
            camera, r_cam = _make_camera(name, config.image_size)
            r_cam = r_cam.double()
            self.cameras[name] = dict(camera=camera, r_cam=r_cam, face_size=int(sizes[name]),
                                      position=torch.tensor(RIG_POSITIONS[name],
                                                            dtype=torch.float64))
        h = config.image_size[0]
        self.panorama_size = (h, 2 * h)
        self.panorama_face = _panorama_face(config.max_face_size, h)

    def rotation(self, name: str, k: int) -> torch.Tensor:
        """Camera -> world (= cube) rotation of camera ``name`` at frame ``k``, float64."""
        return self.R_bike[k] @ self.cameras[name]["r_cam"]

    def centre(self, name: str, k: int) -> torch.Tensor:
        return self.location[k] + self.R_bike[k] @ self.cameras[name]["position"]

    def faces(self, name: str, k: int) -> torch.Tensor:
        """``(6,)`` bool: the faces camera ``name`` reads at frame ``k``: those with a texel in
        its cone of view (:meth:`texels`; cached). A superset of ``sizing.visible_faces``'
        exact answer, which costs seconds per camera and frame at 1024 x 1024 (measured: the
        same faces on the default ride at 256 x 256; at 48 x 48 and on the turns of towns 2
        and 3, now and then one more face, of which a few texels are traced)."""
        if (name, k) not in self._faces:
            self._faces[name, k] = self.texels(name, k).flatten(1).any(1)
        return self._faces[name, k]

    def texels(self, name: str, k: int) -> torch.Tensor:
        """``(6, F, F)`` bool: the cube texels within camera ``name``'s cone of view at frame
        ``k`` (:func:`camera_cone`, :func:`cone_texels`), a superset of those its layer reads
        (the last one kept)."""
        if self._texels is None or self._texels[0] != (name, k):
            c = self.cameras[name]
            if "cone" not in c:
                c["cone"] = camera_cone(c["camera"], c["face_size"])
            axis = self.rotation(name, k)[:, 2]   # the optical axis, in the world (cube) frame
            self._texels = ((name, k), cone_texels(c["face_size"], axis, c["cone"]))
        return self._texels[1]

    def files(self, k: int) -> list[str]:
        """Relative paths of every file of frame ``k`` (the marker excluded)."""
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

    Per camera, the town traces only the texels the layer reads: those within the camera's
    cone of view (:func:`camera_cone`, :func:`cone_texels`; the layer's output is the same bit
    for bit as from whole faces, tests/test_dataset.py), unless ``save_cubemaps`` asks for
    whole faces. The cubes are rendered into buffers kept
    from camera to camera and frame to frame, and each camera's images are converted,
    encoded and written by ``writers`` threads while the next camera renders (a frame's
    marker once all its files are written)."""

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

    def texels(self, name: str, k: int) -> torch.Tensor | None:
        """``(6, F, F)`` bool: the texels camera ``name`` reads at frame ``k`` (a superset:
        ``_Plan.texels``), or None with ``save_cubemaps`` (whole faces). With ``antialias``,
        grown by a texel on each face: a texel's anti-aliasing compares it with its 8
        neighbours on the face (``scenes.town.edge_texels``), so every texel read has them all
        rendered, as with whole faces."""
        if self.config.save_cubemaps:
            return None
        texels = self.plan.texels(name, k)
        return texels if self.config.antialias == 1 else _grow(texels)

    def cubemap(self, name: str, k: int) -> dict[str, torch.Tensor]:
        """Camera ``name``'s cubemap of frame ``k`` (``Town.render_cubemap``: the faces and
        texels it reads, in the frame's weather, with the configuration's ``antialias``), in
        this renderer's buffers: valid until the next cubemap of the same face size."""
        config, plan = self.config, self.plan
        F = plan.cameras[name]["face_size"]
        return self.town.render_cubemap(
            plan.centre(name, k).float(), None, F, faces=plan.faces(name, k),
            texels=self.texels(name, k), t=float(plan.frames["time"][k]),
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
                        pending.append(pool.submit(_write_camera, out, name, k, res))
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


def camera_cone(camera, face_size: int) -> float:
    """The half-angle (radians) of a cone around a camera's optical axis that holds every cube
    texel its layer reads at ``face_size``: the camera's widest angle (``Camera.max_angle``,
    its model's domain within its ``fov``, an upper bound of its valid pixels'), plus one and a
    half times the largest angle between neighbouring pixels along the image's centre row and
    column (a pixel's footprint, which ``sizing.visible_faces`` counts too, with room for the
    diagonal and the tangential direction) and two and a half texels at a face's centre
    (``2 / F`` radians each, the largest: the bilinear taps, within a texel of the ray, and the
    atlas border, resampled from the next face's texels within a texel and a half of the
    seam)."""
    h, w = camera.image_size
    cu, cv = (w - 1) / 2, (h - 1) / 2
    u = torch.arange(w, dtype=torch.float64)
    v = torch.arange(h, dtype=torch.float64)
    step = 0.0
    params = camera.params.detach().reshape(-1, camera.params.shape[-1])[0].double()
    for pixels in (torch.stack([u, torch.full_like(u, cv)], -1),
                   torch.stack([torch.full_like(v, cu), v], -1)):
        rays, valid = camera.model.unproject(pixels, params)
        rays = rays / rays.norm(dim=-1, keepdim=True)
        both = valid[1:] & valid[:-1]
        if both.any():
            cos = (rays[1:] * rays[:-1]).sum(-1)[both].clamp(-1, 1)
            step = max(step, float(torch.acos(cos).max()))
    widest = float(camera.max_angle().detach().reshape(-1)[0])
    return widest + 1.5 * step + 2.5 * (2.0 / face_size)


def cone_texels(face_size: int, axis: torch.Tensor, half_angle: float) -> torch.Tensor:
    """``(6, F, F)`` bool: the cube texels (cube axes = world) whose ray lies within
    ``half_angle`` radians of the unit vector ``axis (3,)`` (float32: its rounding is far
    below the margins of :func:`camera_cone`)."""
    F = face_size
    if half_angle >= math.pi:
        return torch.ones(6, F, F, dtype=torch.bool)
    f, c = F / 2, (F - 1) / 2
    x = (torch.arange(F, dtype=torch.float32) - c) / f           # texel u (columns), v (rows)
    norm = torch.sqrt(1 + x.view(1, F) ** 2 + x.view(F, 1) ** 2) * math.cos(half_angle)
    axes = face_axes(torch.float64)                                # (6, [a, b, r], 3)
    proj = (axes @ axis.to(torch.float64).reshape(3)).float()     # (6, 3): a.A, b.A, r.A
    out = torch.empty(6, F, F, dtype=torch.bool)
    for k in range(6):   # a face at a time: no (6, F, F) float temporaries
        dot = proj[k, 2] * x.view(1, F) + proj[k, 1] * x.view(F, 1) + proj[k, 0]
        torch.ge(dot, norm, out=out[k])
    return out


def _grow(texels: torch.Tensor) -> torch.Tensor:
    """``texels (6, F, F)`` bool and their 8 neighbours on each face (a 3 x 3 dilation)."""
    grown = torch.nn.functional.max_pool2d(texels[:, None].float(), 3, stride=1, padding=1)
    return grown[:, 0] > 0


def _cube_path(out: Path, name: str, k: int, face: str, modality: str) -> Path:
    return out / fmt.cubemap_file(name, modality, k, face)


def _panorama_path(out: Path, k: int, modality: str) -> Path:
    return out / fmt.panorama_file(modality, k)


def _write_camera(out: Path, name: str, k: int, res: dict[str, torch.Tensor]) -> None:
    """Write one camera's images of frame ``k`` (``res``: the layer's outputs, its labels
    packed with the instance ids: ``objects.pack_instances``)."""
    labels, instances = unpack_instances(res["labels"][0])
    valid = res["valid"][0, 0]

    def path(modality: str) -> Path:
        return out / fmt.frame_file(name, modality, k)

    write_image(path("rgb"), _to_uint8(res["rgb"][0]))
    write_exr(path("depth"), res["depth"][0, 0].float())
    ids = labels.to(torch.uint8).numpy()   # 0..12 and 255 (IGNORE_INDEX)
    write_image(path("labels"), ids)
    write_image(path("labels_color"), colorize(ids))
    write_image(path("valid"), (valid.to(torch.uint8) * 255).numpy())
    write_image(path("instances"), instance_image(instances))
    atomic_write_text(path("objects"), encode_objects(instance_objects(instances, labels)))


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


def _init_worker() -> None:
    # Ctrl-C reaches the whole process group: the main process stops the run and says so
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)


def _to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` float in [0, 1] -> ``(H, W, 3)`` uint8."""
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()


# --------------------------------------------------------------------------------------------
# Per-run files
# --------------------------------------------------------------------------------------------

def _write_if_changed(path: Path, text: str) -> None:
    """Atomic write, skipped when the file already holds ``text`` (a rerun keeps its mtime)."""
    try:
        if path.read_text(encoding="utf-8") == text:
            return
    except (FileNotFoundError, UnicodeDecodeError):
        pass
    atomic_write_text(path, text)


def _dumps(obj) -> str:
    return json.dumps(obj, indent=2) + "\n"


def _matrix(t: torch.Tensor) -> list:
    return [[float(x) for x in row] for row in t.tolist()]


def _pose(rotation: torch.Tensor, centre: torch.Tensor) -> list:
    t = torch.eye(4, dtype=torch.float64)
    t[:3, :3], t[:3, 3] = rotation, centre
    return _matrix(t)


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version
    try:
        ours = version("omniscape_torch")
    except PackageNotFoundError:  # pragma: no cover - run from a checkout never installed
        ours = "unknown"
    out = {"omniscape_torch": ours, "torch": torch.__version__, "numpy": np.__version__,
           "python": platform.python_version()}
    for name, module in (("pillow", "PIL"), ("opencv", "cv2")):   # cv2: optional
        try:
            out[name] = __import__(module).__version__
        except ImportError:  # pragma: no cover
            pass
    return out


def _dynamics_csv(recs: list[dict]) -> str:
    columns = ["frame", "timestamp"]
    for key in ("location", "velocity", "acceleration", "angular_velocity"):
        columns += [f"{key}_{a}" for a in "xyz"]
    columns += ["rotation_pitch", "rotation_yaw", "rotation_roll", "speed"]
    buf = _io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for r in recs:
        row = [r["frame"], repr(r["timestamp"])]
        for key in ("location", "velocity", "acceleration", "angular_velocity"):
            row += [repr(r[key][a]) for a in "xyz"]
        row += [repr(r["rotation"][a]) for a in ("pitch", "yaw", "roll")]
        row.append(repr(r["speed"]))
        writer.writerow(row)
    return buf.getvalue()


def _read_json(path: Path):
    """The JSON in ``path``, or None when it is missing or unreadable (a file to rewrite)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _write_camera_files(name: str, camera, base: Path, fits: dict,
                        log: Callable[[str], None]) -> None:
    """``camera.json`` and ``calib_results.txt`` of one camera. The polynomial model is fitted
    once per distinct camera of the run (``fits``: Camera JSON -> fit, shared by the stereo
    pairs) and not at all when the folder already holds the file and its record for this
    camera (a rerun); the file is written before the record that names it."""
    data = camera.to_dict()
    old = _read_json(base / fmt.CAMERA)
    written = ({k: v for k, v in old.items() if k != "ocamcalib"}
               if isinstance(old, dict) else None)
    record = ocamcalib.cached_record(old.get("ocamcalib") if isinstance(old, dict) else None,
                                     base / fmt.OCAMCALIB, data, written)
    if record is None:
        key = json.dumps(data, sort_keys=True)
        if key not in fits:
            fits[key] = ocamcalib.fit_polynomial(camera)
        fit = fits[key]
        record = ocamcalib.write_calib_results(fit, base / fmt.OCAMCALIB)
        log(f"{name}: {fmt.OCAMCALIB}, polynomial of degree {fit.degree}, held-out error "
            f"max {fit.max_px:.3f} px, RMS {fit.rms_px:.3f} px"
            + ("" if fit.within_tolerance else
               f" (above the {ocamcalib.TOLERANCE_PX} px aimed at: the best of degrees "
               f"{list(ocamcalib.DEGREES)})"))
    _write_if_changed(base / fmt.CAMERA, _dumps({**data, "ocamcalib": record}))


def _write_run_files(plan: _Plan, out: Path,
                     log: Callable[[str], None] = lambda msg: None) -> None:
    config = plan.config
    recs = _ride.records(plan.frames)
    _write_if_changed(out / fmt.DYNAMICS, _dumps(recs))
    _write_if_changed(out / fmt.DYNAMICS_CSV, _dynamics_csv(recs))
    cameras = {}
    fits: dict = {}
    for name, c in plan.cameras.items():
        base = out / name
        base.mkdir(parents=True, exist_ok=True)
        _write_camera_files(name, c["camera"], base, fits, log)
        t_rig = _pose(c["r_cam"], c["position"])
        poses = []
        for k in range(config.frames):
            poses.append({"frame": k,
                          "T_world_camera": _pose(plan.rotation(name, k), plan.centre(name, k)),
                          "faces": [f for f, v in zip(FACES, plan.faces(name, k).tolist())
                                    if v]})
        extr = {"frames": {"rig": "x right, y down, z forward (OpenCV), origin on the ground "
                                  "under the motorcycle's reference point, metres",
                           "world": "x east, y down, z north, metres (town frame; CARLA "
                                    "location (x, y, z) = world (z, x, -y))",
                           "camera": "OpenCV, x right, y down, z forward"},
                "T_rig_camera": t_rig, "face_size": c["face_size"], "poses": poses}
        _write_if_changed(base / "extrinsics.json", _dumps(extr))
        cameras[name] = {"model": c["camera"].model.name,
                         "image_size": list(config.image_size),
                         "face_size": c["face_size"],
                         "position_rig": list(RIG_POSITIONS[name]),
                         "rotation_rig_camera": _matrix(c["r_cam"])}
    manifest = {"format": fmt.FORMAT, "format_version": fmt.FORMAT_VERSION,
                "config": config.to_dict(), "versions": _versions(),
                "frames": config.frames, "cameras": cameras,
                "classes": list(CLASSES), "ignore_index": IGNORE_INDEX,
                "palette": PALETTE.tolist(),
                "weather_per_frame": [_frame_weather(config, k) for k in range(config.frames)],
                "layout": fmt.layout(config.save_cubemaps, config.save_panorama),
                "conventions": {"depth": "range (Euclidean, along the ray), metres",
                                "angles": "degrees in dynamics.json (CARLA)",
                                "pixels": "(u, v) = (column, row), (0, 0) the centre of the "
                                          "top-left pixel",
                                "boxes": "objects/*.json: XYXY corners, pixel columns u0..u1 "
                                         "and rows v0..v1 -> [u0, v0, u1 + 1, v1 + 1]",
                                "instances": "16-bit ids, 0 none; the same object keeps its "
                                             "id in every frame and camera"}}
    _write_if_changed(out / fmt.MANIFEST, _dumps(manifest))


# --------------------------------------------------------------------------------------------
# generate
# --------------------------------------------------------------------------------------------

#: ``generate``'s output formats: the folder (:mod:`.format`), and the folder with WebDataset
#: shards (:mod:`.shards`).
FORMATS = ("folder", "webdataset")


def generate(out: str | Path, config: DatasetConfig | None = None, *, workers: int = 1,
             ray: str | bool | None = None, shard: tuple[int, int] | None = None,
             format: str = "folder", frames_per_shard: int | None = None,
             progress: bool | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Write (or complete) the dataset of ``config`` in ``out``.

    Args:
        out: the dataset folder (created). With ``ray`` or ``shard`` across machines, a
            folder every machine sees at the same path (shared storage).
        config: a :class:`DatasetConfig` (default: all defaults).
        workers: processes rendering frames in parallel on this machine (1: in this process).
        ray: chunks of frames as Ray tasks (:func:`.distributed.run_on_ray`): the address of a
            cluster (``"HOST:PORT"``, ``"auto"``), or True for ``$RAY_ADDRESS``, else the
            cluster of ``ray start`` on this machine, else a local cluster started for the run
            (:func:`.distributed.ray_cluster`); None (default): no Ray. Not with ``workers``.
        shard: ``(K, N)``: only run ``K`` of ``N``'s share, frames ``K, K + N, ...`` (with
            ``format="webdataset"``, the frames of shards ``K, K + N, ...``); ``N`` such runs,
            anywhere and at once, write the dataset one run writes. Each locks its own share.
        format: ``"folder"`` (default), or ``"webdataset"``: also pack the frames into
            WebDataset shards of ``frames_per_shard`` frames (:mod:`.shards`), each by the
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
            configuration (or shards of another ``frames_per_shard``).
        ImportError: ``ray`` without Ray installed, or no Pillow to write the images with
            (at once).
        MemoryError: the run would not fit in memory (:func:`check_memory`; with ``ray``, in
            any node of the cluster; before any work).
        omniscape_torch.data.distributed.TaskErrors: with ``ray``, frames that failed for good,
            each with its error; the others are written, and the same call renders the rest.
        omniscape_torch.io.atomic.FolderBusyError: another run is writing ``out`` (or the same
            share of it).
        OSError: ``out`` cannot be written (the message names the path).
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
    with folder_lock(lock):
        return _generate(out, config, workers, progress, log, ray=ray if use_ray else None,
                         shard=shard, frames_per_shard=(
                             shards.resolve_frames_per_shard(out, frames_per_shard)
                             if format == "webdataset" else None))


def _generate(out: Path, config: DatasetConfig, workers: int, progress: bool | None,
              log: Callable[[str], None], *, ray: str | bool | None = None,
              shard: tuple[int, int] | None = None,
              frames_per_shard: int | None = None) -> dict:
    """``generate`` inside the folder's lock (``frames_per_shard``: WebDataset shards)."""
    manifest = out / fmt.MANIFEST
    if manifest.is_file():
        try:
            old = json.loads(manifest.read_text(encoding="utf-8")).get("config")
        except (ValueError, AttributeError):
            old = None
        if isinstance(old, dict):   # written before antialias existed: one ray a texel
            old.setdefault("antialias", 1)
        if old != config.to_dict():
            raise ValueError(f"{out} holds a dataset of another configuration ({manifest}"
                             f"{config_changes(old, config.to_dict())}); rerun with the "
                             f"folder's settings to complete it, or use another --out folder "
                             f"or remove it")
    # A run killed mid-write leaves its temporaries (the finished files are whole: written by
    # rename); they carry their process id, and only those of ended processes are removed.
    # Not by a share of a run: the others may run on other machines, whose processes this one
    # cannot see.
    stale = remove_stale_temporaries(out) if shard is None else []
    if stale:
        log(f"removed {len(stale)} temporary file(s) of an interrupted run")
    renderer = FrameRenderer(config)
    plan = renderer.plan
    _write_run_files(plan, out, log)
    s = frames_per_shard
    if s is None:
        units = [[k] for k in range(config.frames)]
    else:
        shards.write_index(out, config.frames, config.cameras, s)
        units = shards.shard_groups(config.frames, s)
    units = distributed.shard_part(units, shard)

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
        try:
            if s is not None:
                chunks = todo_units
            else:   # a few chunks of frames per worker: each task builds its renderer once
                size = -(-len(todo) // (2 * workers))
                chunks = [todo[i:i + size] for i in range(0, len(todo), size)]
            if workers == 1 or len(chunks) <= 1:
                for chunk in chunks:
                    rendered += render_chunk(config, out, chunk, s, renderer=renderer)
                    bar.update(len(chunk))
            else:
                with ProcessPoolExecutor(min(workers, len(chunks)),
                                         mp_context=get_context("spawn"),
                                         initializer=_init_worker) as pool:
                    futures = {pool.submit(render_chunk, config, str(out), chunk, s): chunk
                               for chunk in chunks}
                    try:
                        for fut in as_completed(futures):
                            rendered += fut.result()
                            bar.update(len(futures[fut]))
                    except BaseException:
                        for fut in futures:
                            fut.cancel()
                        raise
        finally:
            bar.close()
    sheet = out / fmt.CONTACT_SHEET
    if rendered or not sheet.is_file():
        shown = _sheet_frames(config, [k for k in range(config.frames) if plan.finished(out, k)]
                              if shard is None else None)
        if shown is not None and all(plan.finished(out, k)
                                     for k in (shown[0], *shown[1].values())):
            data = contact_sheet(out, config.cameras, *shown)
            if not sheet.is_file() or sheet.read_bytes() != data:
                atomic_write_bytes(sheet, data)
    if failures:
        raise distributed.TaskErrors("frame", failures, sorted(rendered))
    return {"rendered": sorted(rendered), "skipped": skipped, "face_sizes": sizes}


def render_chunk(config: DatasetConfig, out: str | Path, frames: list[int],
                 frames_per_shard: int | None = None, *,
                 renderer: FrameRenderer | None = None) -> list[int]:
    """Render the unfinished frames among ``frames`` of ``config`` into ``out`` and, with
    ``frames_per_shard``, pack each WebDataset shard of theirs whose frames are all finished
    and which is not there yet: a plain function of its arguments, which any process or
    scheduler can call for any share of the frames, as often as it likes (a repeated call
    finishes what an earlier one left). Stops at the first error. Returns the frames rendered.

    ``renderer``: a :class:`FrameRenderer` of ``config`` to reuse (default: a new one).
    """
    out = Path(out)
    renderer = FrameRenderer(config) if renderer is None else renderer
    rendered = [renderer.render(out, k) for k in frames if not renderer.plan.finished(out, k)]
    if frames_per_shard is not None:
        _pack_shards(renderer.plan, out, frames, frames_per_shard)
    return rendered


def render_task(config: DatasetConfig, out: str, frames_per_shard: int | None,
                frames: list[int]) -> tuple[dict[int, str], dict[int, str]]:
    """A Ray task of ``generate`` (:func:`.distributed.run_on_ray`): :func:`render_chunk`,
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


#: The size of one of the contact sheet's cells (pixels), and its columns.
SHEET_CELL = 200
SHEET_COLUMNS = ("rgb", "depth", "labels_color", "valid")


#: OpenCV's ``COLORMAP_TURBO`` (Google's Turbo), 256 RGB colours as hex: the depth column's
#: colour map, without OpenCV.
_TURBO = np.frombuffer(bytes.fromhex(
    "30123b32154333184a341b51351e5836215f37246638276d392a733a2d793b2f803c32863d358b3e38913f3b"
    "973f3e9c4040a24143a74146ac4249b1424bb5434eba4451bf4454c34456c74559cb455ccf455ed34661d646"
    "64da4666dd4669e0466be3476ee64771e94773eb4776ee4778f0477bf2467df44680f64682f84685fa4687fb"
    "458afc458cfd448ffe4391fe4294ff4196ff4099ff3e9bfe3d9efe3ba0fd3aa3fc38a5fb37a8fa35abf833ad"
    "f731aff52fb2f42eb4f22cb7f02ab9ee28bceb27bee925c0e723c3e422c5e220c7df1fc9dd1ecbda1ccdd81b"
    "d0d51ad2d21ad4d019d5cd18d7ca18d9c818dbc518ddc218dec018e0bd19e2bb19e3b91ae4b61ce6b41de7b2"
    "1fe9af20eaac22ebaa25eca727eea42aefa12cf09e2ff19b32f29835f39438f4913cf58e3ff68a43f78746f8"
    "844af8804ef97d52fa7a55fa7659fb735dfc6f61fc6c65fd6969fd666dfe6271fe5f75fe5c79fe597dff5680"
    "ff5384ff5188ff4e8bff4b8fff4992ff4796fe4499fe429cfe409ffd3fa1fd3da4fc3ca7fc3aa9fb39acfb38"
    "affa37b1f936b4f836b7f735b9f635bcf534bef434c1f334c3f134c6f034c8ef34cbed34cdec34d0ea34d2e9"
    "35d4e735d7e535d9e436dbe236dde037dfdf37e1dd37e3db38e5d938e7d739e9d539ebd339ecd13aeecf3aef"
    "cd3af1cb3af2c93af4c73af5c53af6c33af7c13af8be39f9bc39faba39fbb838fbb637fcb336fcb136fdae35"
    "fdac34fea933fea732fea431fea130fe9e2ffe9b2dfe992cfe962bfe932afe9029fd8d27fd8a26fc8725fc84"
    "23fb8122fb7e21fa7b1ff9781ef9751df8721cf76f1af66c19f56918f46617f36315f26014f15d13f05b12ef"
    "5811ed5510ec530feb500eea4e0de84b0ce7490ce5470be4450ae2430ae14109df3f08dd3d08dc3b07da3907"
    "d83706d63506d43305d23105d02f05ce2d04cc2b04ca2a04c82803c52603c32503c12302be2102bc2002b91e"
    "02b71d02b41b01b21a01af1801ac1701a91601a71401a41301a112019e10019b0f01980e01950d01920b018e"
    "0a018b09028808028507028106027e05027a0403"), np.uint8).reshape(256, 3)


def _resize_weights(src: int, dst: int) -> np.ndarray:
    """``(dst, src)`` weights of an area resampling from ``src`` to ``dst < src`` samples: the
    overlap of each source pixel with each output pixel's footprint (OpenCV's INTER_AREA)."""
    scale = src / dst
    lo = np.arange(dst)[:, None] * scale
    s = np.arange(src)[None, :]
    return np.clip(np.minimum(lo + scale, s + 1) - np.maximum(lo, s), 0, None) / scale


def _resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``image (H, W, C)`` uint8 resampled to ``height x width``: by area going down, nearest
    going up (OpenCV's INTER_AREA and INTER_NEAREST, in numpy)."""
    h, w = image.shape[:2]
    if height < h or width < w:
        out = np.tensordot(_resize_weights(h, height), image.astype(np.float64), axes=(1, 0))
        out = np.tensordot(out, _resize_weights(w, width), axes=(1, 1))   # (height, C, width)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8).transpose(0, 2, 1)
    rows = np.minimum(np.floor(np.arange(height) * (1.0 / (height / h))).astype(int), h - 1)
    cols = np.minimum(np.floor(np.arange(width) * (1.0 / (width / w))).astype(int), w - 1)
    return image[rows][:, cols]


def _sheet_cell(image: np.ndarray, title: str) -> np.ndarray:
    """``image (H, W, 3)`` uint8 RGB fitted into a ``SHEET_CELL`` square (aspect kept, black
    margins), ``title`` written in its top-left corner (Pillow's default font)."""
    from PIL import Image, ImageDraw, ImageFont

    h, w = image.shape[:2]
    scale = SHEET_CELL / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = _resize(image, size[1], size[0]) if scale != 1 else image
    cell = np.zeros((SHEET_CELL, SHEET_CELL, 3), np.uint8)
    y0, x0 = (SHEET_CELL - size[1]) // 2, (SHEET_CELL - size[0]) // 2
    cell[y0:y0 + size[1], x0:x0 + size[0]] = small
    font = ImageFont.load_default()
    _, _, right, bottom = ImageDraw.Draw(Image.new("L", (1, 1))).textbbox((4, 3), title,
                                                                          font=font)
    cell[:bottom + 3, :right + 4] //= 3          # a dark band under the title
    canvas = Image.fromarray(cell)
    ImageDraw.Draw(canvas).text((4, 3), title, fill=(255, 255, 255), font=font)
    return np.asarray(canvas).copy()


def contact_sheet(root: str | Path, cameras, frame: int,
                  weathers: dict[str, int] | None = None) -> bytes:
    """PNG bytes of frame ``frame`` of the dataset in ``root``: one row per camera of
    ``cameras``, columns ``SHEET_COLUMNS`` (depth on a log colour map, black where not valid),
    then, when ``weathers`` (weather name -> a finished frame in it) holds more than one, rows
    of the first camera's RGB in each of them (``len(SHEET_COLUMNS)`` a row): the dataset's
    variety at a glance. ``SHEET_CELL`` pixels square per cell, each titled."""
    from ..io import read_exr

    root = Path(root)

    def image(name: str, modality: str, k: int) -> np.ndarray:
        return read_image(root / fmt.frame_file(name, modality, k)).numpy()

    rows = []
    for name in cameras:
        valid = image(name, "valid", frame) > 0
        depth = read_exr(root / fmt.frame_file(name, "depth", frame)).numpy()
        log_depth = np.log10(np.maximum(depth, 1e-3))
        lo, hi = (float(log_depth[valid].min()), float(log_depth[valid].max())) \
            if valid.any() else (0.0, 1.0)
        scaled = np.clip((log_depth - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
        turbo = _TURBO[scaled]
        cells = {"rgb": image(name, "rgb", frame),
                 "depth": np.where(valid[..., None], turbo, 0).astype(np.uint8),
                 "labels_color": image(name, "labels_color", frame),
                 "valid": np.repeat(valid[..., None].astype(np.uint8) * 255, 3, -1)}
        titles = {"rgb": f"{name} {fmt.frame_name(frame)}", "depth": "depth (log)",
                  "labels_color": "labels", "valid": "valid"}
        rows.append(np.hstack([_sheet_cell(cells[m], titles[m]) for m in SHEET_COLUMNS]))
    if weathers is not None and len(weathers) > 1:
        cells = [_sheet_cell(image(cameras[0], "rgb", k), weather)
                 for weather, k in weathers.items()]
        per_row = len(SHEET_COLUMNS)
        cells += [np.zeros_like(cells[0])] * (-len(cells) % per_row)
        rows += [np.hstack(cells[i:i + per_row]) for i in range(0, len(cells), per_row)]
    return encode_image(np.vstack(rows))


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
    default the configuration's): per rendering process :data:`PROCESS_MEMORY` plus the largest
    cube's texels and the largest image's pixels at their rates (:data:`MEMORY_PER_TEXEL`,
    :data:`MEMORY_PER_PIXEL`; cameras render one after the other), times the processes, plus
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
        MemoryError: :func:`estimate_memory` exceeds ``available`` (default
            :func:`available_memory`); the message gives both and the largest image size (and
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
