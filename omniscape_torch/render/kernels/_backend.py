"""The one choice between a kernel's C++ op and its torch (or NumPy) reference twin.

Every public function of `omniscape_torch.render.kernels` takes `backend`, one of
`BACKENDS`, and asks `choose` once, after checking its arguments:

- `"cpp"`: the C++ op, built on first use (`build.load`); a `RuntimeError` that says why where
  it cannot be built, a `ValueError` for tensors off the CPU or that require gradients (the ops
  are CPU-only and forward-only).
- `"torch"`: the reference twin beside the op: differentiable, on any device. On a GPU this is
  the route every call takes.
- `"auto"` (the default everywhere): the C++ op where it can run (every tensor on the CPU, none
  requiring a gradient, the library built or buildable), else the twin. Where the library
  cannot be built, one `UserWarning` in the process says why (`build.ops`).

Nothing above this package decides between the two: a module passes its own `backend` (the
argument its user gave it) down to the kernels it calls.
"""

from __future__ import annotations

import torch

from . import build

__all__ = ["BACKENDS", "available", "check_backend", "choose", "compile_failures", "resolve",
           "unavailable_reason"]

#: The values of every kernel's `backend` argument.
BACKENDS = ("auto", "cpp", "torch")


def check_backend(backend: object, name: str = "backend") -> str:
    """`backend` if it is one of `BACKENDS`, else a `ValueError` naming `name`."""
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise ValueError(f"{name}: expected one of {BACKENDS}, got {backend!r}")
    return backend


def _runs_on_cpu(tensors: tuple) -> tuple[bool, bool]:
    """(every tensor on the CPU, none requiring a gradient) of the tensors among `tensors`."""
    grad = torch.is_grad_enabled()
    cpu, no_grad = True, True
    for t in tensors:
        if isinstance(t, torch.Tensor):
            cpu = cpu and t.device.type == "cpu"
            no_grad = no_grad and not (grad and t.requires_grad)
    return cpu, no_grad


def choose(backend: str, *tensors: object, what: str = "kernel"):
    """The C++ ops (`torch.ops.omniscape_torch`) for a call on `tensors`, or None for the
    reference twin (module docstring).

    Args:
        backend: one of `BACKENDS` (checked).
        *tensors: the call's tensors (other values are skipped): their devices and gradients
            decide `"auto"`, and are checked for `"cpp"`.
        what: the kernel's name, for the messages.

    Raises:
        ValueError: `backend="cpp"` with a tensor off the CPU or one that requires a gradient.
        RuntimeError: `backend="cpp"` where the C++ library cannot be built (why).
    """
    check_backend(backend)
    if backend == "torch":
        return None
    cpu, no_grad = _runs_on_cpu(tensors)
    if backend == "auto":
        return build.ops() if cpu and no_grad else None
    if not cpu:
        raise ValueError(f"{what}: backend='cpp' runs on the CPU only; the tensors are on "
                         "another device (use backend='auto' or 'torch')")
    if not no_grad:
        raise ValueError(f"{what}: backend='cpp' computes no gradients; an input requires one "
                         "(use backend='auto' or 'torch')")
    ops = build.ops()
    if ops is None:
        raise RuntimeError(f"{what}: backend='cpp', but the C++ kernels are unavailable here "
                           f"({build.unavailable_reason()})")
    return ops


def resolve(backend: str, *tensors: object, what: str = "kernel") -> str:
    """`"cpp"` or `"torch"`: `choose`'s route for a call on `tensors`, decided once for a caller
    that runs several kernels on them (the layer: one route for every modality of a call)."""
    return "cpp" if choose(backend, *tensors, what=what) is not None else "torch"


def available() -> bool:
    """Whether the C++ ops run in this process: built (on the first call, once per machine) and
    loaded. False, after one `UserWarning` that says why (`unavailable_reason`), where they
    cannot be built (no C++ compiler, no ninja)."""
    return build.ops() is not None


def unavailable_reason() -> str | None:
    """Why `available` is False (`"Error: message"`), else None."""
    return build.unavailable_reason()


def compile_failures() -> dict[tuple, str]:
    """`{("extension", "fastsample"): "Error: message"}` when the C++ library could not be built
    in this process (`available` is False); empty when it works (or was not needed yet)."""
    why = unavailable_reason()
    return {} if why is None else {("extension", "fastsample"): why}
