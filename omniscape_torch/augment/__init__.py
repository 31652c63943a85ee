"""The augmentation modules (DESIGN.md): `from omniscape_torch.augment import RandomOmniCamera`,
or `ot.augment.RandomOmniCamera` after `import omniscape_torch as ot`.

Random omnidirectional cameras and vehicle attitudes, drawn per sample, rendered through the
layer's functions (`omniscape_torch.render`):

- `RandomOmniCamera` (`omni.py`): cubemap batch -> omni batch.
- `RandomReproject` (`perspective.py`): perspective (or any camera's) images -> fisheye batch.
- `draw.py`: the lenses and attitudes both draw, their generator and its seeding across epochs
  and `DataLoader` workers; `targets.py`: the detection targets and label maps of their dicts;
  `containers.py`: torchvision `tv_tensors` and unbatched samples at `forward`'s entry and exit;
  `adapters.py`: the albumentations adapter; `apply.py`: `ApplyToKey`.

Randomness comes only from a `torch.Generator`: the one passed to a call, else the module's own,
seeded from `seed` and, inside a `DataLoader` worker, from PyTorch's per-worker seed. Parameters
are drawn in float64 on the CPU, so a seed gives the same cameras on any device.

Attitude (rig convention of `omniscape_torch.cameras.presets`): `R = R_att @ R_mount` with
`R_att = yaw_pitch_roll_to_matrix(yaw, pitch, roll)` the vehicle's attitude relative to the
cube frame and `R_mount` the camera's mount on the vehicle (identity for a forward fisheye, the
"down" or "up" face's rotation for a catadioptric camera), `ray_cube = R @ ray_cam`.
"""

from .adapters import to_albumentations
from .apply import ApplyToKey
from .draw import FISHEYE_MODELS, MODES
from .omni import RandomOmniCamera
from .perspective import RandomReproject

__all__ = ["ApplyToKey", "FISHEYE_MODELS", "MODES", "RandomOmniCamera", "RandomReproject",
           "to_albumentations"]
