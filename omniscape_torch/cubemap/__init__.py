"""Cube maps: face order and orientation, padded cube, atlas and its sampling grid.

The only place in the package that knows the face order (`FACES`) and orientation.
Conventions (``DESIGN.md``): OpenCV frame (x right, y down, z forward); pixel ``(u, v)`` =
(column, row), integer coordinates at texel centres; cubemaps are ``(B, 6, C, F, F)``.

Pipeline for a layer::

    plan = border_plan(F, pad)                       # once per (F, pad)
    grid = rays_to_grid(R @ rays, F, pad)            # once per camera / attitude
    atlas = cubemap_to_atlas(cube, pad, plan=plan)   # per batch
    out = grid_sample(atlas, grid, align_corners=False)
"""

from .atlas import atlas_to_faces, cubemap_to_atlas, face_uv_to_grid, faces_to_atlas
from .grid import rays_to_grid, rotated_rays_to_grid
from .depth import depth_to_range, range_factor, range_to_depth
from .faces import (
    FACES,
    face_axes,
    face_intrinsics,
    face_pixel_to_ray,
    face_rays,
    face_rotations,
    ray_to_face,
)
from .padding import PAD_MODES, BorderPlan, border_plan, check_cubemap, pad_faces
from .rotation import ROTATION_ATOL, check_rotation

__all__ = [
    "FACES",
    "PAD_MODES",
    "ROTATION_ATOL",
    "BorderPlan",
    "atlas_to_faces",
    "border_plan",
    "check_cubemap",
    "check_rotation",
    "cubemap_to_atlas",
    "depth_to_range",
    "face_axes",
    "face_intrinsics",
    "face_pixel_to_ray",
    "face_rays",
    "face_rotations",
    "face_uv_to_grid",
    "faces_to_atlas",
    "pad_faces",
    "range_factor",
    "range_to_depth",
    "ray_to_face",
    "rays_to_grid",
    "rotated_rays_to_grid",
]
