"""Rendering a cubemap into any camera: the layer, its samplers and the uses built on it."""


def __getattr__(name: str):
    """A submodule on first use (``ot.render.layer`` without importing it first: the
    package's top level loads lazily, so nothing else may have imported it)."""
    import importlib
    import importlib.util

    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}"):
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
