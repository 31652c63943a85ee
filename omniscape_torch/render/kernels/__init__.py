"""The kernel boundary: the only place where Python meets the package's C++ ops.

One public function per computation, each beside its torch (or NumPy) reference twin: it
checks its arguments once, then runs the C++ op or the twin, chosen by its `backend` argument
(`"auto"`, `"cpp"` or `"torch"`; `_backend.choose` is the one place that decides). Modules above
this package (the layer, the augmentation, detection, the town) pass their `backend` down and
never ask whether the C++ ops exist.

- `build`: the one C++ library (`render/csrc/`), built on first use, its ops' fake
  implementations for `torch.compile`.
- `cube`: sampling a cube through a grid, a lookup table or rays (the C++ ops and their twin,
  `grid_sample` on the padded atlas).
- `image`: sampling an image along rays, with or without the antialiasing prefilter, with
  labels (`reproject_image`); the rays of whole cameras from their radius tables.
- `camera`: pixel centres -> rays -> atlas grid of whole cameras (`camera_grid`,
  `camera_rays`, `radial_table`: the C++ tables or compiled torch).
- `cone`: the cube texels a layer's bilinear taps touch (`omniscape_torch.cubemap.cone`).
- `framing`: the focal at which a perspective source fills a share of a fisheye.
- `draw`: the augmentation's draw of cameras and attitudes (one stream layout) and its C++ twin.
- `town`: the built-in town's shading (`omniscape_torch.scenes.Town`): back faces, shading
  with shadow rays, storing a cube face's rays.

On a GPU (or any device but the CPU) every function takes its torch route: the C++ ops are
CPU-only and forward-only.
"""

from . import build, camera, cone, cube, draw, framing, image, town
from ._backend import (BACKENDS, available, check_backend, choose, compile_failures, resolve,
                       unavailable_reason)

__all__ = ["BACKENDS", "available", "build", "camera", "check_backend", "choose", "cone",
           "compile_failures", "cube", "draw", "framing", "image", "resolve", "town",
           "unavailable_reason"]
