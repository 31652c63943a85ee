"""A small procedural town of triangle meshes, traced by Embree and shaded in C (or torch).

World frame (metres): x east, y down (gravity is +y, like the OpenCV camera's y), z north. The
ground is the plane ``y = 0``; things above the ground have ``y < 0``. Streets share one
cross-section, ``across`` metres from their centre line: two driving lanes (``|across| < 3.5``,
centre line dashed, lane edges solid, zebra crossings every 60 m), a parking strip on each side
(``3.5 < |across| < 5.25``), sidewalks (``5.25 < |across| < 8.5``), and beyond them buildings,
walls, fences and open lots (ground labelled ``Other``). Layouts (`LAYOUTS`, ``layout=``):

1. main street: one street along z, centred on ``x = 0`` (the default);
2. crossroads: the main street and a cross street along x, centred on ``z = 0``;
3. blocks: two streets along z (``x = 0`` and ``x = 70``) and two along x (``z = -40`` and
   ``z = 40``), a block between them.

The town's objects line the streets over ``|z| < length / 2`` (and the cross streets' own
extents); the ground and the roads go on beyond, to ``far + length`` metres. A camera with
identity rotation at ``(0, -1.2, 0)`` stands on the main street's centre line at eye height and
looks north, along the road.

Geometry: the objects are primitives (axis-aligned boxes: buildings, walls, fences, vehicles,
sign plates, bins; vertical cylinders with a top cap: poles, tree trunks, pedestrians' bodies;
spheres: tree crowns, pedestrians' heads; ground rectangles: road, sidewalk, lots), turned into
one triangle mesh (`mesh`: 32-sided prisms, icospheres of 1280 triangles) in which every
triangle knows its primitive, so its class and colour. Primitives are seen from outside: a ray
that meets a triangle from behind (it started inside) goes on through it. Moving vehicles and
pedestrians go straight along z at constant speed and wrap around the town's length
(`Town.moving_objects`); the mesh at time ``t`` is traced by an Embree scene built for
``t`` (the last one is kept).

Outputs (`Town.render_rays`, `Town.render_cubemap`): RGB in ``[0, 1]``, the range
(Euclidean distance along the ray; for the sky: ``town.far``, default 1000 m) or the cubemap's
planar depth (along each face's axis; for the sky: ``town.far``, the far plane of a simulator's
depth camera), and CARLA's 13 class ids (sky is ``Unlabeled``; road markings are ``RoadLine``,
painted on the road by world coordinates). Colour is
``albedo(class, world point) * (ambient + sun * lambert * lit) + emission``, then distance fog,
where ``lit`` is 0 when a shadow ray towards the sun (traced by Embree as well) meets anything;
the weather preset (`WEATHERS`) changes light, colour, wetness and fog, never geometry or
labels.

Shading runs through `omniscape_torch.render.kernels.town`: its C++ ops
(``torch.ops.omniscape_torch.town_*``, ``render/csrc/town_shade.cpp``, built with the fast
sampler into one library) or their torch twins beside them, as the rendering methods'
``backend`` says (``"auto"``: the C++ ops where a compiler builds them; the same operations in
the same order: the same labels and depths, colours within a few float32 roundings, torch's
``sqrt`` not being correctly rounded on every CPU).

The module's parts: the weather presets (`omniscape_torch.scenes.weather`), the streets and the
placement of the objects (`omniscape_torch.scenes.layout`), the meshes and Embree
(`omniscape_torch.scenes.mesh`); here the `Town`, which builds its mesh, traces and renders.

Exactness: every ray is traced and shaded on its own (Embree's closest hit, which does not
depend on the batch; then ``+ - * /``, ``sqrt``, comparisons and integer hashing, no
transcendental functions and no reductions), so the result of a ray does not depend on the batch
it is in, the chunking or the threads: ``render_rays`` of the cube's own texel rays
(`Town.cubemap_rays`) equals ``render_cubemap`` bit for bit, and so do any two runs.
With ``antialias=k`` (`Town.render_cubemap`) a texel on an edge (`edge_texels`) is
the mean of ``k x k`` sub-texel rays, built and summed the same way whatever the batch; its
labels and depth stay the centre ray's. A ray's last bit can matter: a hit point on a surface
that lies on a texture cell's boundary (the ground, ``y = 0``, for the noise cells) falls on
either side by its rounding.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from torch import Tensor

from ..cameras._base import broadcast_shapes
from ..cubemap.faces import face_axes, face_pixel_to_ray, face_rays
from ..render.kernels import check_backend
from ..render.kernels import town as _kernels
from ..render.kernels.town import BOX as _BOX, CYLINDER as _CYLINDER, GROUND as _GROUND
from ..render.kernels.town import SPHERE as _SPHERE
from . import mesh as _mesh
from .layout import CLASS_IDS, LAYOUTS, Street, layout_streets, place_objects
from .weather import (CARLA_PRESETS, CARLA_WEATHERS, WEATHERS, Weather, _get_weather,
                      _kernel_weather, carla_weather)

__all__ = ["CARLA_PRESETS", "CARLA_WEATHERS", "CLASS_IDS", "LAYOUTS", "Street", "Town", "Weather",
           "WEATHERS", "carla_weather", "edge_texels"]

_C = CLASS_IDS

#: Tessellation: sides of a cylinder, subdivisions of an icosphere (1280 triangles).
CYLINDER_SEGMENTS = 32
SPHERE_SUBDIVISIONS = 3
#: A ray that meets a triangle from behind goes on from this far past it (metres), at most
#: ``MAX_PASSES`` times.
PASS_STEP, MAX_PASSES = 1e-4, 4
#: Rays traced and shaded per task (the tasks run on ``threads`` threads).
CHUNK = 65536
#: Anti-aliased cubemaps (``render_cubemap(antialias=k)``, `edge_texels`): two
#: neighbouring texels on a face straddle an edge, and both are supersampled, where their labels
#: differ, their ranges by more than ``AA_RANGE_STEP`` of the nearer, or a colour channel by more
#: than ``AA_RGB_STEP``. Measured (benchmarks/bench_town.py's cameras at 256 x 256, their
#: default faces, frames 0 and 2, k = 2, against 8 x 8 rays a pixel): supersampling every texel
#: gives 40.4 dB (fisheye) and 42.3 dB (catadioptric); a colour step of 8/255 supersamples
#: 44 % / 37 % of the texels for 0.1 dB less, 10/255 35 % / 28 % for 0.25 / 0.15 dB less
#: (k = 3: 41.3 / 43.1 dB against 41.7 / 43.4), 16/255 18 % / 13 % for 0.55 / 0.4 dB less; the
#: range step adds under 1 % of the texels (it finds occlusions of like colours).
AA_RANGE_STEP, AA_RGB_STEP = 0.05, 10.0 / 255


def edge_texels(labels: Tensor, rng: Tensor, rgb: Tensor, rendered: Tensor | None = None
                ) -> Tensor:
    """``(F, F)`` bool: the texels of one cube face that `Town.render_cubemap`'s
    ``antialias`` supersamples. Two neighbouring texels (each of the 8 neighbours), both
    ``rendered`` (default: all), straddle an edge where their ``labels (F, F)`` differ, their
    ``rng (F, F)`` differ by more than ``AA_RANGE_STEP`` of the nearer, or a channel of their
    ``rgb (3, F, F)`` by more than ``AA_RGB_STEP``; both are on the edge (it lies in one
    footprint or the other). Across a face's seam nothing is compared."""
    F = labels.shape[-1]
    edge = torch.zeros(F, F, dtype=torch.bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):   # each pair of neighbours once
        a = (slice(0, F - dy), slice(max(0, -dx), F - max(0, dx)))
        b = (slice(dy, F), slice(max(0, dx), F + min(0, dx)))
        step = ((labels[a] != labels[b])
                | ((rng[a] - rng[b]).abs() > AA_RANGE_STEP * torch.minimum(rng[a], rng[b]))
                | ((rgb[(slice(None),) + a] - rgb[(slice(None),) + b]).abs().amax(0)
                   > AA_RGB_STEP))
        if rendered is not None:
            step &= rendered[a] & rendered[b]
        edge[a] |= step
        edge[b] |= step
    return edge


class Town:
    """A procedural town, deterministic by ``seed`` (a ``torch.Generator``; no global RNG).

    Args:
        seed: the random layout (buildings, gaps, parked cars, trees, colours, movers).
        layout: the street plan, a key of `LAYOUTS` (1: main street, 2: crossroads,
            3: blocks).
        length: extent of the town along z (metres), centred on ``z = 0``.
        far: range (and planar depth) reported for the sky, metres; nothing farther is seen.
        threads: threads that trace and shade (default: ``torch.get_num_threads()``); the
            result does not depend on it.

    Rendering (`render_rays`, `render_cubemap`) takes ``backend="auto" | "cpp" | "torch"``: the
    shading's C++ ops or their torch twins (`omniscape_torch.render.kernels.town`).

    Attributes hold the primitives as float32 tensors: ``boxes_lo/boxes_hi (Nb, 3)``,
    ``cyl (Nc, 5)`` = (cx, cz, r, ytop, ybot), ``sph (Ns, 4)`` = (cx, cy, cz, r), each with
    ``*_label`` (int64 class ids), ``*_colour (N, 3)`` albedo and ``*_mover`` (index into the
    movers, -1 for static) and ``*_instance`` (int64 instance id, 0 for none).
    ``movers`` is ``(M, 3)`` = (z0, speed m/s, kind 0 vehicle / 1 pedestrian). ``streets``
    the layout's `Street` list; ``mesh`` the triangles at ``t = 0``
    (`mesh.Mesh`).

    Instances: every vehicle (body and cabin), pedestrian (body and head), pole (a street
    lamp's, a traffic sign's) and traffic sign plate is an object with its own instance id,
    ``1..I`` in the order the town places them (the same ids at every time and from every
    viewpoint, so stable across a ride's frames); the ground, buildings, walls, fences, trees
    and bins have none (0). ``instance_label (I + 1,)`` int64 is the class of each id (0 for
    id 0).
    """

    def __init__(self, seed: int = 0, *, layout: int = 1, length: float = 160.0,
                 far: float = 1000.0, threads: int | None = None):
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
        if isinstance(layout, bool) or layout not in LAYOUTS:
            raise ValueError(f"layout: expected one of {sorted(LAYOUTS)}, got {layout!r}")
        if not (isinstance(length, (int, float)) and 20 <= length <= 2000):
            raise ValueError(f"length: expected 20 to 2000 metres, got {length!r}")
        if not (isinstance(far, (int, float)) and far > 0 and math.isfinite(far)):
            raise ValueError(f"far: expected a positive number of metres, got {far!r}")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                    or threads < 1):
            raise ValueError(f"threads: expected a positive integer or None, got {threads!r}")
        self.seed = int(seed)
        self.layout = int(layout)
        self.length = float(length)
        self.far = float(far)
        self.threads = threads
        self.streets = layout_streets(self.layout, self.length)
        g = torch.Generator().manual_seed(self.seed)
        # the objects' tables (boxes_*, cyl_*, sph_*, movers, instance_label, lamps, ground)
        for name, value in place_objects(self.streets, self.length, self.far, g).items():
            setattr(self, name, value)
        self._build_mesh()
        self._lock = threading.Lock()
        self._scene_cache: tuple[float, _mesh.MeshScene] | None = None
        self._rays_cache: dict[int, Tensor] = {}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_lock"], state["_scene_cache"], state["_rays_cache"] = None, None, {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    # ---------------------------------------------------------------- mesh
    def _build_mesh(self) -> None:
        """The triangle mesh at ``t = 0`` and the parts' tables: parts are the ground cells,
        then the boxes, the cylinders and the spheres, in their tables' order."""
        cells = self.ground
        ng, nb, nc, ns = len(cells), len(self.boxes_lo), len(self.cyl), len(self.sph)
        first = np.cumsum([0, ng, nb, nc])
        gx0, gx1, gz0, gz1 = (np.array([c[k] for c in cells]) for k in range(4))
        self.mesh = _mesh.concat([
            _mesh.rectangle_mesh(gx0, gx1, gz0, gz1, np.arange(ng)),
            _mesh.box_mesh(self.boxes_lo.numpy(), self.boxes_hi.numpy(),
                           first[1] + np.arange(nb)),
            _mesh.cylinder_mesh(self.cyl.numpy(), first[2] + np.arange(nc), CYLINDER_SEGMENTS),
            _mesh.sphere_mesh(self.sph.numpy(), first[3] + np.arange(ns), SPHERE_SUBDIVISIONS),
        ])
        i64 = torch.int64
        kind = torch.tensor([_GROUND] * ng + [_BOX] * nb + [_CYLINDER] * nc + [_SPHERE] * ns,
                            dtype=i64)
        label = torch.cat([torch.tensor([c[4] for c in cells], dtype=i64), self.boxes_label,
                           self.cyl_label, self.sph_label])
        colour = torch.cat([torch.zeros(ng, 3), self.boxes_colour, self.cyl_colour,
                            self.sph_colour])
        mover = torch.cat([torch.full((ng,), -1, dtype=i64), self.boxes_mover, self.cyl_mover,
                           self.sph_mover])
        paint = torch.tensor([{"": 0, "z": 1, "x": 2}[c[5]] for c in cells]
                             + [0] * (nb + nc + ns), dtype=torch.float32)
        paint_offset = torch.tensor([c[6] for c in cells] + [0.0] * (nb + nc + ns),
                                    dtype=torch.float32)
        centre = torch.zeros(ng + nb + nc + ns, 3)
        centre[first[1]:first[2]] = (self.boxes_lo + self.boxes_hi) / 2
        index = torch.cat([torch.arange(n, dtype=i64) for n in (ng, nb, nc, ns)])
        smooth = (kind == _CYLINDER) | (kind == _SPHERE)
        m = self.mesh
        part = torch.from_numpy(m.part)
        # one row per attribute, one column per triangle: a hit's attributes are one gather
        self._tri_attr = torch.cat([
            torch.from_numpy(m.face_normals).T,                    # 0-2 outward face normal
            label[part].to(torch.float32)[None],                   # 3 class id
            kind[part].to(torch.float32)[None],                    # 4 part kind
            colour[part].T,                                        # 5-7 albedo
            paint[part][None], paint_offset[part][None],           # 8-9 road paint
            centre[part, :2].T,                                    # 10-11 box centre x, y
            index[part].to(torch.float32)[None],                   # 12 index in its kind
            smooth[part].to(torch.float32)[None],                  # 13 smooth normals
        ]).contiguous()
        self._vertex_mover = mover[torch.from_numpy(m.vertex_part)]
        # a hit's instance id, one gather by triangle; a miss (triangle -1) reads the last, 0
        instance = torch.cat([torch.zeros(ng, dtype=i64), self.boxes_instance, self.cyl_instance,
                              self.sph_instance])
        self._tri_instance = np.append(instance[part].numpy(), 0).astype(np.int32)
        # what the shading reads: attributes (K, T), corners (T, 3) int32, vertex normals, lamps
        self._tables = _kernels.TownTables(self._tri_attr, torch.from_numpy(m.triangles),
                                           torch.from_numpy(m.normals),
                                           self.lamps.reshape(-1, 3).contiguous())

    @property
    def classes_present(self) -> set[int]:
        """Class ids that the town contains (the ground gives Road, RoadLine, Sidewalk and
        Other; the sky Unlabeled)."""
        ids = {_C["Unlabeled"], _C["Road"], _C["RoadLine"], _C["Sidewalk"], _C["Other"]}
        for t in (self.boxes_label, self.cyl_label, self.sph_label):
            ids |= set(t.tolist())
        return ids

    # ---------------------------------------------------------------- motion
    def moving_objects(self, t: float = 0.0) -> dict[str, Tensor]:
        """Positions at time ``t`` (seconds) of the movers: ``z (M,)`` float64 (straight-line
        motion along z, wrapped into ``[-length/2, length/2)``), ``speed (M,)`` m/s along z and
        ``kind (M,)`` (0 vehicle, 1 pedestrian)."""
        z0, v, kind = self.movers.unbind(-1)
        L = self.length
        z = torch.remainder(z0 + v * float(t) + L / 2, L) - L / 2
        return {"z": z, "speed": v, "kind": kind.to(torch.int64)}

    def _shifts(self, t: float) -> Tensor:
        """``(M + 1,)`` float32 shift along z of each mover at ``t`` (the last: 0, static)."""
        dz = (self.moving_objects(t)["z"] - self.movers[:, 0]).to(torch.float32)
        return torch.cat([dz, torch.zeros(1)])

    def geometry(self, t: float = 0.0) -> dict[str, Tensor]:
        """Primitive parameters at time ``t``: the movers shifted along z."""
        dz = self._shifts(t)
        lo, hi = self.boxes_lo.clone(), self.boxes_hi.clone()
        lo[:, 2] += dz[self.boxes_mover]
        hi[:, 2] += dz[self.boxes_mover]
        cyl = self.cyl.clone()
        cyl[:, 1] += dz[self.cyl_mover]
        sph = self.sph.clone()
        sph[:, 2] += dz[self.sph_mover]
        return {"lo": lo, "hi": hi, "cyl": cyl, "sph": sph}

    def vertices(self, t: float = 0.0) -> Tensor:
        """``(V, 3)`` float32 mesh vertices at time ``t`` (the movers' shifted along z)."""
        v = torch.from_numpy(self.mesh.vertices).clone()
        v[:, 2] += self._shifts(t)[self._vertex_mover]
        return v

    def scene(self, t: float = 0.0) -> _mesh.MeshScene:
        """The Embree scene of the mesh at time ``t`` (built once per ``t``; the last kept)."""
        t = float(t)
        with self._lock:
            if self._scene_cache is None or self._scene_cache[0] != t:
                self._scene_cache = (t, _mesh.MeshScene(self.vertices(t).numpy(),
                                                        self.mesh.triangles))
            return self._scene_cache[1]

    # ---------------------------------------------------------------- tracing
    def _trace(self, scene: _mesh.MeshScene, o: np.ndarray, d: np.ndarray, backend: str):
        """Closest front-facing hits of rays ``o (N, 3) or (1, 3)``, ``d (N, 3)`` (numpy
        float32) within ``far``: ``t (N,)`` (inf: none), triangle ``(N,)`` (-1: none),
        barycentric ``u, v (N,)``. A ray that meets a triangle from behind (it started inside a
        primitive) goes on from ``PASS_STEP`` past it, up to ``MAX_PASSES`` times (then it sees
        nothing)."""

        def backfaces(d: np.ndarray, tri: np.ndarray) -> np.ndarray:
            return _kernels.backfaces(torch.from_numpy(np.ascontiguousarray(d)),
                                      torch.from_numpy(tri), self._tri_attr,
                                      backend=backend).numpy()

        n = d.shape[0]
        o = np.broadcast_to(o, (n, 3))
        t, tri, u, v = scene.intersect(o, d, self.far)
        todo = None   # every ray (not gathered)
        for rest in range(MAX_PASSES, -1, -1):
            if todo is None:
                todo = np.flatnonzero(backfaces(d, tri))
            else:
                todo = todo[backfaces(d[todo], tri[todo])]
            if todo.size == 0:
                break
            if rest == 0:
                t[todo], tri[todo] = np.inf, -1
                break
            skip = t[todo] + np.float32(PASS_STEP)
            t2, tri2, u2, v2 = scene.intersect(o[todo] + skip[:, None] * d[todo], d[todo],
                                               np.float32(self.far) - skip)
            t[todo] = np.where(tri2 >= 0, skip + t2, np.float32(np.inf))
            tri[todo], u[todo], v[todo] = tri2, u2, v2
        return t, tri, u, v

    def _shade(self, o: np.ndarray, d: np.ndarray, t: np.ndarray, tri: np.ndarray,
               u: np.ndarray, v: np.ndarray, weather: Tensor, scene: _mesh.MeshScene,
               backend: str) -> dict[str, Tensor]:
        """Labels, range, normal and colour of rays ``o (N, 3) or (1, 3)``, ``d (N, 3)`` (numpy
        float32) from their closest hits (`_trace`), with shadow rays towards the sun
        through ``scene``: `omniscape_torch.render.kernels.town.shade` of the town's tables
        under ``weather`` (`_kernel_weather`)."""
        o, d, t, tri, u, v = (torch.from_numpy(np.ascontiguousarray(x))
                              for x in (o, d, t, tri, u, v))
        return _kernels.shade(o, d, t, tri, u, v, self._tables, weather, scene.occluded,
                              backend=backend)

    def _trace_shade(self, o: Tensor, d: Tensor, scene: _mesh.MeshScene, weather: Tensor,
                     backend: str) -> dict[str, Tensor]:
        """`_trace` then `_shade` of one batch (``o (N, 3) or (1, 3)``), and the
        hits' instance ids."""
        o, d = o.numpy(), d.numpy()
        hits = self._trace(scene, o, d, backend)
        out = self._shade(o, d, *hits, weather, scene, backend)
        out["instances"] = torch.from_numpy(self._tri_instance[hits[1]].astype(np.int64))
        return out

    def _run(self, tasks: list, job) -> None:
        """``job(task)`` for every task, on ``threads`` worker threads (Embree's queries release
        the GIL, and so do torch's kernels). Worker threads even for one: on the caller's thread
        torch may split each small kernel over OpenMP threads, which a busy machine makes up to
        40 times slower (measured on 2 cores at a load of 5)."""
        threads = self.threads or torch.get_num_threads()
        with ThreadPoolExecutor(max(1, min(threads, len(tasks)))) as pool:
            for _ in pool.map(job, tasks):
                pass

    # ---------------------------------------------------------------- public API
    def render_rays(self, origins: Tensor, directions: Tensor, *, t: float = 0.0,
                    weather: str | Weather = "clear_noon", chunk: int = CHUNK,
                    backend: str = "auto") -> dict[str, Tensor]:
        """Trace arbitrary rays: the exact ground truth.

        Args:
            origins: ``(..., 3)`` or ``(3,)`` ray origins, world frame, metres.
            directions: ``(..., 3)`` unit directions, world frame (not renormalised); the
                leading dimensions of the two broadcast.
            t: time (s) for the moving objects.
            weather: a `WEATHERS` name or a `Weather`.
            chunk: rays per task (results do not depend on it).
            backend: ``"auto"`` (default), ``"cpp"`` or ``"torch"``: the town's shading
                through its C++ ops or their torch twins
                (`omniscape_torch.render.kernels.town`; ``"auto"``: the C++ ops where they
                are built). The two give the same labels, ranges and depths, colours within a
                few float32 roundings.

        Returns:
            dict with ``rgb (..., 3)`` float32 in [0, 1], ``range (...)`` metres along the ray
            (``self.far`` for the sky), ``labels (...)`` int64 in 0..12, ``normal (..., 3)``
            (world frame, facing the ray; ``-direction`` for the sky), ``hit (...)`` bool,
            ``instances (...)`` int64: the instance id of the object hit (0: none; the
            class of id ``i`` is ``instance_label[i]``).
        """
        w = _kernel_weather(_get_weather(weather), self.far)
        check_backend(backend)
        if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
            raise ValueError(f"chunk: expected a positive integer, got {chunk!r}")
        d = torch.as_tensor(directions).to(torch.float32)
        o = torch.as_tensor(origins).to(torch.float32)
        if d.shape[-1:] != (3,):
            raise ValueError(f"directions: expected (..., 3), got {tuple(d.shape)}")
        if o.shape[-1:] != (3,):
            raise ValueError(f"origins: expected (..., 3) or (3,), got {tuple(o.shape)}")
        try:
            shape = broadcast_shapes(o.shape[:-1], d.shape[:-1])
        except RuntimeError:
            raise ValueError(f"origins {tuple(o.shape)} and directions {tuple(d.shape)}: "
                             "their leading dimensions do not broadcast") from None
        d = d.expand(*shape, 3).reshape(-1, 3).contiguous()
        if o.dim() > 1:
            o = o.expand(*shape, 3).reshape(-1, 3).contiguous()
        else:
            o = o.reshape(1, 3)
        n = d.shape[0]
        scene = self.scene(t)
        out = {"rgb": torch.empty(n, 3), "range": torch.empty(n),
               "labels": torch.empty(n, dtype=torch.int64), "normal": torch.empty(n, 3),
               "hit": torch.empty(n, dtype=torch.bool),
               "instances": torch.empty(n, dtype=torch.int64)}

        def job(s: int) -> None:
            e = min(s + chunk, n)
            res = self._trace_shade(o[s:e] if o.shape[0] > 1 else o, d[s:e], scene, w, backend)
            for k, v in res.items():
                out[k][s:e] = v

        self._run(list(range(0, n, chunk)), job)
        return {k: v.reshape(tuple(shape) + tuple(v.shape[1:])) for k, v in out.items()}

    @staticmethod
    def cubemap_rays(face_size: int, rotation: Tensor | None = None) -> Tensor:
        """``(6, F, F, 3)`` unit world-frame rays of the cube's texels, the rays that
        `render_cubemap` traces (``rotation`` maps cube frame to world)."""
        r = face_rays(face_size, normalize=True, dtype=torch.float32)
        if rotation is not None:
            r = r @ torch.as_tensor(rotation).to(torch.float32).T
        return r

    def _cube_rays(self, face_size: int, rotation: Tensor | None) -> Tensor:
        """`cubemap_rays`, kept for the last two face sizes when ``rotation`` is None."""
        if rotation is not None:
            return self.cubemap_rays(face_size, rotation)
        with self._lock:
            rays = self._rays_cache.get(face_size)
            if rays is None:
                rays = self.cubemap_rays(face_size)
                if len(self._rays_cache) >= 2:
                    self._rays_cache.pop(next(iter(self._rays_cache)))
                self._rays_cache[face_size] = rays
            return rays

    def render_cubemap(self, position, rotation: Tensor | None = None, face_size: int = 256, *,
                       faces: Tensor | None = None, texels: Tensor | None = None,
                       t: float = 0.0, weather: str | Weather = "clear_noon",
                       chunk: int = CHUNK, out: dict[str, Tensor] | None = None,
                       antialias: int = 1, backend: str = "auto") -> dict[str, Tensor]:
        """Render a cubemap at ``position`` (world, metres).

        Args:
            position: ``(3,)`` cube centre in the world frame.
            rotation: ``(3, 3)`` cube frame -> world (default identity: the front face looks
                north along the road, down is gravity).
            face_size: ``F``.
            faces: optional ``(6,)`` bool mask of the faces to render; the others are left at
                rgb 0, depth 0, label 255 (``IGNORE_INDEX``) and instance 0.
            texels: optional ``(6, F, F)`` bool mask of the texels to render (within
                ``faces``), the others left as the faces not rendered.
            t: time (s) for the moving objects.
            weather: a `WEATHERS` name or a `Weather`.
            chunk: texels per task (results do not depend on it).
            out: contiguous tensors to write the outputs into (some or all of the keys below,
                each of its shape and dtype), reused from call to call instead of new memory;
                the others are allocated.
            antialias: ``k``: the RGB of a texel on an edge is the mean of ``k x k`` rays
                stratified over its footprint on the face (sub-texel ``(u, v)`` at
                ``(i + 0.5) / k - 0.5`` of a texel from its centre, then normalised), where a
                texel's centre ray is a point sample of a hard edge or texture cell (1: the
                centre ray alone, the default). Adaptive (`_antialias`): only the texels
                that differ from a rendered neighbour on their face (label, range, colour:
                ``AA_RANGE_STEP``, ``AA_RGB_STEP``) are supersampled. Depth, range and labels
                stay those of the centre ray, whatever ``k``.
            backend: ``"auto"`` (default), ``"cpp"`` or ``"torch"``, as in `render_rays`.

        Returns:
            dict with ``rgb (1, 6, 3, F, F)`` float32, ``depth (1, 6, F, F)`` planar depth in
            metres (along each face's axis; ``self.far`` for the sky), ``labels (1, 6, F, F)``
            int64, ``range (1, 6, F, F)`` (``self.far`` for the sky) and
            ``instances (1, 6, F, F)`` int32, the centre ray's instance id (0: none).
        """
        w = _kernel_weather(_get_weather(weather), self.far)
        check_backend(backend)
        if isinstance(face_size, bool) or not isinstance(face_size, int) or face_size < 1:
            raise ValueError(f"face_size: expected a positive integer, got {face_size!r}")
        if isinstance(antialias, bool) or not isinstance(antialias, int) or antialias < 1:
            raise ValueError(f"antialias: expected a positive integer, got {antialias!r}")
        F = face_size
        origin = torch.as_tensor(position).to(torch.float32).reshape(1, 3)
        rot = None if rotation is None else torch.as_tensor(rotation).to(torch.float32)
        axes = face_axes(torch.float32)[:, 0]  # (6, 3) each face's axis a, cube frame
        if rot is not None:
            axes = axes @ rot.T
        rays = self._cube_rays(F, rot).reshape(6, F * F, 3)
        if faces is None:
            sel = torch.ones(6, dtype=torch.bool)
        else:
            sel = torch.as_tensor(faces).to(torch.bool).reshape(6)
        if texels is not None:
            texels = torch.as_tensor(texels).to(torch.bool)
            if texels.shape != (6, F, F):
                raise ValueError(f"texels: expected a (6, {F}, {F}) mask, got "
                                 f"{tuple(texels.shape)}")
        out = {} if out is None else out
        buffers = {}
        for key, shape, dtype, fill in (("rgb", (1, 6, 3, F, F), torch.float32, 0),
                                        ("depth", (1, 6, F, F), torch.float32, 0),
                                        ("labels", (1, 6, F, F), torch.int64, 255),
                                        ("range", (1, 6, F, F), torch.float32, 0),
                                        ("instances", (1, 6, F, F), torch.int32, 0)):
            buf = out.get(key)
            if buf is None:
                buffers[key] = torch.full(shape, fill, dtype=dtype)
                continue
            if (tuple(buf.shape) != shape or buf.dtype != dtype or not buf.is_contiguous()
                    or buf.device.type != "cpu"):
                raise ValueError(f"out[{key!r}]: expected a contiguous CPU {dtype} tensor of "
                                 f"shape {shape}, got {buf.dtype} {tuple(buf.shape)}")
            buffers[key] = buf.fill_(fill)
        rgb = buffers["rgb"].view(1, 6, 3, F * F)
        dep, rng, lab = (buffers[k].view(1, 6, F * F) for k in ("depth", "range", "labels"))
        tasks = []
        for f in torch.nonzero(sel).flatten().tolist():
            if texels is None:
                tasks += [(f, slice(s, min(s + chunk, F * F))) for s in range(0, F * F, chunk)]
            else:
                idx = np.flatnonzero(texels[f].reshape(-1).numpy())
                tasks += [(f, idx[s:s + chunk]) for s in range(0, idx.size, chunk)]
        scene = self.scene(t)
        rays_np, origin_np = rays.numpy(), origin.numpy()
        inst_np = buffers["instances"].view(6, F * F).numpy()

        def job(task) -> None:
            f, q = task
            d = rays_np[f, q]
            hits = self._trace(scene, origin_np, d, backend)
            inst_np[f, q] = self._tri_instance[hits[1]]
            shaded = self._shade(origin_np, d, *hits, w, scene, backend)
            index, start = (None, q.start) if isinstance(q, slice) else (torch.from_numpy(q), 0)
            _kernels.store(torch.from_numpy(np.ascontiguousarray(d)), index, start, shaded,
                           axes[f], self.far, rgb[0, f], dep[0, f], rng[0, f], lab[0, f],
                           backend=backend)

        self._run(tasks, job)
        if antialias > 1:
            self._antialias(antialias, sel, texels, buffers, origin_np, rot, scene, w, chunk,
                            backend)
        return buffers

    def _antialias(self, k: int, sel: Tensor, texels: Tensor | None,
                   buffers: dict[str, Tensor], origin: np.ndarray, rot: Tensor | None,
                   scene: _mesh.MeshScene, weather: Tensor, chunk: int, backend: str
                   ) -> None:
        """`render_cubemap`'s ``antialias=k``, on the cube of centre rays in
        ``buffers``: the RGB of every texel on an edge becomes the mean of ``k x k`` sub-texel
        rays (for odd ``k`` the middle one is the centre ray, already traced).

        The texels on an edge: `edge_texels` of each face, among its rendered texels
        (``texels``). A texel whose neighbours all look like it keeps its centre ray's colour:
        the sky, the insides of surfaces and of texture cells."""
        F = buffers["rgb"].shape[-1]
        faces = torch.nonzero(sel).flatten().tolist()
        edges: dict[int, np.ndarray] = {}

        def detect(f: int) -> None:
            done = None if texels is None else texels[f]
            edges[f] = np.flatnonzero(edge_texels(
                buffers["labels"][0, f], buffers["range"][0, f], buffers["rgb"][0, f],
                done).reshape(-1).numpy())

        self._run(faces, detect)
        # the sub-texel offsets (du, dv) from a texel's centre, in texels (the centre left out)
        off = (torch.arange(k, dtype=torch.float32) + 0.5) / k - 0.5
        dv, du = (x.reshape(-1) for x in torch.meshgrid(off, off, indexing="ij"))
        keep = (du != 0) | (dv != 0)
        du, dv = du[keep], dv[keep]
        m = du.numel()
        per_task = max(1, chunk // m)
        tasks = [(f, edges[f][s:s + per_task]) for f in faces
                 for s in range(0, edges[f].size, per_task)]
        rgb_np = buffers["rgb"].view(1, 6, 3, F * F).numpy()

        def job(task) -> None:
            f, q = task
            # the sub-texels' unit rays (cubemap.faces), rotated into the world as element-wise
            # sums: the same bits whatever the batch (the town's textures tell a ray's last bit
            # apart: the ground's noise cells split at y = 0, where a hit point's rounding falls)
            i, j = torch.from_numpy(q // F).float(), torch.from_numpy(q % F).float()
            uv = torch.stack([j[:, None] + du, i[:, None] + dv], -1)   # (n, m, 2)
            d = face_pixel_to_ray(f, uv, F, normalize=True).reshape(-1, 3)
            if rot is not None:
                d = d[:, :1] * rot[:, 0] + d[:, 1:2] * rot[:, 1] + d[:, 2:] * rot[:, 2]
            d = np.ascontiguousarray(d.numpy())
            hits = self._trace(scene, origin, d, backend)
            sub = self._shade(origin, d, *hits, weather, scene, backend)["rgb"]
            sub = sub.numpy().reshape(q.size, m, 3)
            total = sub[:, 0].copy()
            for n in range(1, m):   # summed in order: the same whatever the batch
                total += sub[:, n]
            if m < k * k:   # odd k: the centre ray is one of the k x k
                total += rgb_np[0, f][:, q].T
            rgb_np[0, f][:, q] = (total / np.float32(k * k)).T

        self._run(tasks, job)
