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


def __getattr__(name: str):
    """A submodule on first use (``ot.scenes.ride`` without importing it first: the
    package's top level loads lazily, so nothing else may have imported it)."""
    import importlib
    import importlib.util

    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}"):
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
