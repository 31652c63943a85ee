"""Built-in procedural scenes: the embedded default data source.

``Town`` is a small procedural town ray-cast in torch from analytic primitives; it renders
cubemaps (RGB, planar depth, CARLA's 13 labels) at any pose, and any camera's rays directly
(the exact ground truth). See :mod:`omniscape_torch.scenes.town` for the world frame.
"""

from .town import CLASS_IDS, WEATHERS, Town, Weather

__all__ = ["CLASS_IDS", "Town", "WEATHERS", "Weather"]
