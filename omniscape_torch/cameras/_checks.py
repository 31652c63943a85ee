"""The checks every function that takes a camera makes: the error for a value that is not one
(`not_a_camera`), and one camera, not a batch (`check_one_camera`)."""

from __future__ import annotations


def not_a_camera(name: str, value: object, expected: str = "an ot.Camera") -> TypeError:
    """The error for an argument `name` that is not a camera: a `TypeError` naming what was
    expected and the type given, with a hint for the `(camera, rotation)` pair that
    `ot.presets.catadioptric` returns (unlike `ot.presets.fisheye`, which returns the camera
    alone).

    Returns:
        The exception, for the caller to raise (so that its traceback ends at the check).
    """
    hint = ""
    if isinstance(value, tuple) and len(value) == 2 and _is_camera(value[0]):
        hint = ("; ot.presets.catadioptric returns (camera, rotation): pass the camera, and "
                "the rotation where the call takes one (camera, rotation = "
                "ot.presets.catadioptric(...))")
    return TypeError(f"{name}: expected {expected}, got {type(value).__name__}{hint}")


def _is_camera(value: object) -> bool:
    """An `ot.Camera` by its attributes (this module imports none, so that `camera.py`'s own
    imports may use it)."""
    return all(hasattr(value, a) for a in ("model", "params", "image_size", "batch_shape"))


def check_one_camera(value: object, name: str = "camera") -> None:
    """Refuse what is not one camera (an `ot.Camera` whose batch shape is `()`), naming `name`:
    `not_a_camera`'s `TypeError`, or a `ValueError` for a batch."""
    if not _is_camera(value):
        raise not_a_camera(name, value)
    if tuple(value.batch_shape) != ():
        raise ValueError(f"{name}: expected one camera, got a batch of shape "
                         f"{tuple(value.batch_shape)}")
