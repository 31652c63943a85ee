"""Built-in procedural scenes: the embedded default data source.

``Town`` is a small procedural town of triangle meshes traced by Embree (`.mesh`) and
shaded in C++ (the ops ``torch.ops.omniscape_torch.town_*``, built with the fast sampler, and
their torch twins: `omniscape_torch.render.kernels.town`); it renders cubemaps (RGB,
planar depth, CARLA's 13 labels) at any pose, only the faces and texels asked for, and any
camera's rays directly (the exact ground truth), under CARLA's 14 weather presets and a few of
its own (`.weather`), in three street layouts (`LAYOUTS`, `.layout`), each with its ride
(`.routes`). See `omniscape_torch.scenes.town` for the world frame.
"""

from .town import CARLA_WEATHERS, CLASS_IDS, LAYOUTS, WEATHERS, Street, Town, Weather

__all__ = ["CARLA_WEATHERS", "CLASS_IDS", "LAYOUTS", "Street", "Town", "WEATHERS", "Weather"]
