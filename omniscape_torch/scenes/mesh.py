"""Triangle meshes of the town's primitives, and the Embree scene that traces them.

The town (`town`) describes its objects as primitives: axis-aligned boxes, vertical
cylinders with a top cap, spheres, and ground rectangles. This module turns them into one
triangle soup (`Mesh`) in which every triangle knows its *part*, the primitive it comes
from (the town keeps a table of the parts' class, colour and motion), its outward face normal,
and its vertices' normals (smooth on cylinders and spheres, flat elsewhere), and traces rays
through it with Embree (`MeshScene`, through the ``embreex`` bindings).

Tessellation: a cylinder is a prism of ``segments`` sides (vertices on the circle), a sphere a
subdivided icosahedron (vertices on the sphere; ``4 ** k * 20`` triangles), a box 12 triangles,
a ground rectangle 2. Triangles are wound counter-clockwise seen from outside (the face normal
``(p1 - p0) x (p2 - p0)`` points out).

Embree's closest hit is deterministic: a ray gives the same distance, triangle and barycentric
coordinates whatever the batch it is traced in and whatever the thread, so a cubemap traced in
tiles equals the same rays traced one by one.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

__all__ = ["Mesh", "MeshScene", "box_mesh", "concat", "cylinder_mesh", "icosphere",
           "rectangle_mesh", "sphere_mesh"]


@dataclass
class Mesh:
    """A triangle soup with per-triangle parts.

    Attributes:
        vertices: ``(V, 3)`` float32, metres.
        triangles: ``(T, 3)`` int32 vertex indices, counter-clockwise seen from outside.
        normals: ``(V, 3)`` float32 unit vertex normals (shading).
        face_normals: ``(T, 3)`` float32 unit outward normals of the triangles.
        part: ``(T,)`` int64, the part (primitive) each triangle belongs to.
        vertex_part: ``(V,)`` int64, the part of each vertex (vertices are not shared between
            parts), to move a part's vertices.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    face_normals: np.ndarray
    part: np.ndarray
    vertex_part: np.ndarray

    @property
    def num_triangles(self) -> int:
        return int(self.triangles.shape[0])


def _finish(vertices, triangles, normals, part_of_vertex) -> Mesh:
    """A `Mesh` from per-primitive arrays, each triangle wound outward (its face normal
    ``(p1 - p0) x (p2 - p0)`` along its vertex normals)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    triangles = np.ascontiguousarray(triangles, dtype=np.int32).reshape(-1, 3)
    normals = np.ascontiguousarray(normals, dtype=np.float32).reshape(-1, 3)
    v = vertices.astype(np.float64)
    fn = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    vertex_part = np.asarray(part_of_vertex, dtype=np.int64).reshape(-1)
    # orient every triangle outward: along the sum of its vertices' normals
    flip = (fn * normals[triangles].sum(1)).sum(1) < 0
    triangles[flip] = triangles[flip][:, ::-1]
    fn[flip] *= -1
    return Mesh(vertices, triangles, normals, fn.astype(np.float32),
                vertex_part[triangles[:, 0]], vertex_part)


def _box_table() -> tuple[np.ndarray, np.ndarray]:
    """The 24 corners of a box's 6 faces (4 each, a quad around the face) as ``(24, 3)`` bool
    (True: ``hi``, False: ``lo``) and their ``(24, 3)`` flat outward normals."""
    corners, normals = [], []
    for axis in range(3):
        u, w = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, 1):
            for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = [0, 0, 0]
                c[axis], c[u], c[w] = side, a, b
                corners.append(c)
                normals.append([(1.0 if side else -1.0) if k == axis else 0.0 for k in range(3)])
    return np.array(corners, dtype=bool), np.array(normals, dtype=np.float32)


def _quads(first: np.ndarray) -> np.ndarray:
    """Two triangles ``(0, 1, 2), (0, 2, 3)`` per quad of 4 consecutive vertices."""
    q = first[:, None, None] + np.array([[0, 1, 2], [0, 2, 3]])[None]
    return q.reshape(-1, 3)


def box_mesh(lo: np.ndarray, hi: np.ndarray, parts: np.ndarray) -> Mesh:
    """``N`` axis-aligned boxes ``lo (N, 3)`` to ``hi (N, 3)``: 24 vertices (flat faces) and
    12 triangles each, part ``parts[i]``; but a box standing on the ground (``hi y = 0``, y
    down) has no bottom face (10 triangles): it would lie in the ground's plane, where a ray
    could meet either."""
    lo, hi = np.asarray(lo, np.float32).reshape(-1, 3), np.asarray(hi, np.float32).reshape(-1, 3)
    n = lo.shape[0]
    corners, normals = _box_table()
    v = np.where(corners[None], hi[:, None], lo[:, None])  # (N, 24, 3)
    first = np.arange(n)[:, None] * 24 + np.arange(0, 24, 4)[None]  # (N, 6) faces
    bottom = (normals[::4, 1] > 0)[None] & (hi[:, 1] >= 0)[:, None]
    tri = _quads(first[~bottom])
    nrm = np.broadcast_to(normals, (n, 24, 3))
    return _finish(v, tri, nrm, np.repeat(np.asarray(parts, np.int64), 24))


def rectangle_mesh(x0, x1, z0, z1, parts, y: float = 0.0) -> Mesh:
    """Horizontal rectangles ``x0 <= x <= x1, z0 <= z <= z1`` at height ``y`` (world y down),
    facing up (``-y``): 2 triangles each."""
    x0, x1, z0, z1 = (np.asarray(a, np.float64).reshape(-1) for a in (x0, x1, z0, z1))
    n = x0.shape[0]
    ys = np.full(n, y)
    # counter-clockwise seen from above (from -y): x east, z north, looking down the +y axis
    v = np.stack([np.stack([x0, ys, z0], -1), np.stack([x0, ys, z1], -1),
                  np.stack([x1, ys, z1], -1), np.stack([x1, ys, z0], -1)], 1)  # (N, 4, 3)
    tri = _quads(np.arange(n) * 4)
    nrm = np.broadcast_to(np.array([0.0, -1.0, 0.0], np.float32), (n, 4, 3))
    return _finish(v, tri, nrm, np.repeat(np.asarray(parts, np.int64), 4))


def cylinder_mesh(cyl: np.ndarray, parts: np.ndarray, segments: int = 32) -> Mesh:
    """Vertical cylinders ``cyl (N, 5)`` = (cx, cz, r, ytop, ybot) (``ytop < ybot``, y down):
    the side (``segments`` quads, radial vertex normals) and the top cap at ``ytop`` (a fan,
    flat, facing up). No bottom cap: they stand on the ground."""
    cyl = np.asarray(cyl, np.float64).reshape(-1, 5)
    n, s = cyl.shape[0], int(segments)
    ang = 2 * np.pi * np.arange(s + 1) / s
    ang[-1] = 0.0
    cx, cz, r, yt, yb = (cyl[:, i:i + 1] for i in range(5))
    ca, sa = np.cos(ang)[None], np.sin(ang)[None]
    px, pz = cx + r * ca, cz + r * sa                          # (N, s + 1)
    # side quads: (bottom k, top k, top k+1, bottom k+1), oriented by _finish
    k0, k1 = np.arange(s), np.arange(1, s + 1)
    ybot, ytop = np.broadcast_to(yb, (n, s)), np.broadcast_to(yt, (n, s))
    quad = np.stack([np.stack([px[:, k0], ybot, pz[:, k0]], -1),
                     np.stack([px[:, k0], ytop, pz[:, k0]], -1),
                     np.stack([px[:, k1], ytop, pz[:, k1]], -1),
                     np.stack([px[:, k1], ybot, pz[:, k1]], -1)], 2)  # (N, s, 4, 3)
    rad = np.stack([ca[0], np.zeros(s + 1), sa[0]], -1)            # (s + 1, 3)
    qn = np.stack([rad[k0], rad[k0], rad[k1], rad[k1]], 1)          # (s, 4, 3)
    side_v = quad.reshape(n, 4 * s, 3)
    side_n = np.broadcast_to(qn.reshape(1, 4 * s, 3), (n, 4 * s, 3))
    # cap: centre + ring at ytop, a fan
    cap_v = np.concatenate([np.stack([cx[:, 0], yt[:, 0], cz[:, 0]], -1)[:, None],
                            np.stack([px[:, :s], np.broadcast_to(yt, (n, s)), pz[:, :s]], -1)],
                           1)  # (N, s + 1, 3)
    cap_n = np.broadcast_to(np.array([0.0, -1.0, 0.0]), (n, s + 1, 3))
    per = 4 * s + s + 1
    base = np.arange(n)[:, None] * per
    side_t = _quads((base + np.arange(0, 4 * s, 4)[None]).reshape(-1)).reshape(n, -1, 3)
    c0 = base + 4 * s
    ring = np.arange(s)
    fan = np.stack([np.broadcast_to(c0, (n, s)), c0 + 1 + (ring + 1) % s, c0 + 1 + ring], -1)
    v = np.concatenate([side_v, cap_v], 1)
    nrm = np.concatenate([side_n, cap_n], 1)
    tri = np.concatenate([side_t, fan], 1)
    return _finish(v, tri, nrm, np.repeat(np.asarray(parts, np.int64), per))


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere: ``(vertices (V, 3) float64, triangles (T, 3))``, a subdivided icosahedron
    with ``20 * 4 ** subdivisions`` triangles, counter-clockwise seen from outside."""
    t = (1 + 5 ** 0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t),
         (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(int(subdivisions)):
        mid: dict[tuple[int, int], int] = {}

        def midpoint(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in mid:
                p = verts[a] + verts[b]
                verts.append(p / np.linalg.norm(p))
                mid[key] = len(verts) - 1
            return mid[key]
        nf = []
        for a, b, c in f:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = nf
    return np.array(verts), np.array(f, dtype=np.int64)


def sphere_mesh(sph: np.ndarray, parts: np.ndarray, subdivisions: int = 3) -> Mesh:
    """Spheres ``sph (N, 4)`` = (cx, cy, cz, r): icospheres, vertex normals radial."""
    sph = np.asarray(sph, np.float64).reshape(-1, 4)
    unit, tri = icosphere(subdivisions)
    n, nv = sph.shape[0], unit.shape[0]
    v = sph[:, None, :3] + sph[:, None, 3:] * unit[None]
    tri = (np.arange(n)[:, None, None] * nv + tri[None]).reshape(-1, 3)
    nrm = np.broadcast_to(unit, (n, nv, 3))
    return _finish(v, tri, nrm, np.repeat(np.asarray(parts, np.int64), nv))


def concat(meshes: list[Mesh]) -> Mesh:
    """One mesh of several (vertex indices offset; parts kept as given)."""
    offsets = np.cumsum([0] + [m.vertices.shape[0] for m in meshes[:-1]])
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.triangles + np.int32(o) for m, o in zip(meshes, offsets)]),
                np.concatenate([m.normals for m in meshes]),
                np.concatenate([m.face_normals for m in meshes]),
                np.concatenate([m.part for m in meshes]),
                np.concatenate([m.vertex_part for m in meshes]))


class MeshScene:
    """An Embree scene of one triangle soup, committed at construction, for closest-hit and
    occlusion queries; safe to query from several threads at once (the queries release the
    GIL, so threads trace in parallel).

    Args:
        vertices: ``(V, 3)`` float32 world coordinates.
        triangles: ``(T, 3)`` int32 vertex indices.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError as err:  # pragma: no cover - a hard dependency
            raise ImportError("the built-in town needs Embree's Python bindings: "
                              "pip install embreex") from err
        self._scene = rtcore_scene.EmbreeScene()
        self._mesh = TriangleMesh(self._scene, np.ascontiguousarray(vertices, np.float32),
                                  np.ascontiguousarray(triangles, np.int32))
        self._lock = threading.Lock()
        # commit now (embreex commits on the first query, which must not race)
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 1, 0]], np.float32),
                        query="DISTANCE")

    def intersect(self, origins: np.ndarray, directions: np.ndarray,
                  tfar: float | np.ndarray = 1e37
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest hits of ``N`` rays ``origins + t directions``, ``0 <= t < tfar``.

        Args:
            origins: ``(N, 3)`` float32.
            directions: ``(N, 3)`` float32 (need not be unit: ``t`` is in their units).
            tfar: the rays' end, a scalar or ``(N,)``.

        Returns:
            ``t (N,)`` float32 (``inf`` where nothing is hit), ``triangle (N,)`` int64
            (-1 where nothing is hit), barycentric ``u, v (N,)`` float32 (the hit point is
            ``(1 - u - v) p0 + u p1 + v p2``).
        """
        n = origins.shape[0]
        # a copy: embreex writes the hits' distances into it
        dists = np.full(n, tfar, np.float32) if np.ndim(tfar) == 0 else np.array(tfar, np.float32)
        res = self._scene.run(np.ascontiguousarray(origins, np.float32),
                              np.ascontiguousarray(directions, np.float32),
                              dists=dists, output=True)
        prim = res["primID"].astype(np.int64)
        t = np.where(prim >= 0, res["tfar"], np.float32(np.inf)).astype(np.float32)
        return t, prim, res["u"], res["v"]

    def occluded(self, origins: np.ndarray, directions: np.ndarray,
                 tfar: float | np.ndarray = 1e37) -> np.ndarray:
        """``(N,)`` bool: whether anything lies on each ray ``origins + t directions``,
        ``0 <= t < tfar`` (a scalar or ``(N,)``)."""
        n = origins.shape[0]
        dists = np.full(n, tfar, np.float32) if np.ndim(tfar) == 0 else np.array(tfar, np.float32)
        res = self._scene.run(np.ascontiguousarray(origins, np.float32),
                              np.ascontiguousarray(directions, np.float32),
                              dists=dists, query="OCCLUDED")
        return res >= 0
