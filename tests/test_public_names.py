"""Every public name the documents give resolves: the dotted names ``ot.xxx`` and
``omniscape_torch.xxx`` in the code of README.md, ARCHITECTURE.md, docs/**/*.md and the
design page (DESIGN.md, beside the project), and the ``from omniscape_torch... import ...``
lines of their code blocks. A name written ``omniscape_torch.a.b`` in full must be importable
that way (``import omniscape_torch.a``), not only reachable as an attribute."""

from __future__ import annotations

import importlib
import re
import types
from pathlib import Path

import pytest

import omniscape_torch as ot

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT.parent / "shared" / "DESIGN.md"

#: The names DESIGN.md's "Public names" section gives, for a checkout without the page beside
#: it (CI): outside code calls these.
DESIGN_NAMES = ("ot.cameras.MODELS", "ot.cameras.get_model", "ot.Camera", "ot.OmniProjection",
                "ot.cubemap.FACES", "ot.augment", "omniscape_torch.augment",
                "omniscape_torch.augment.RandomOmniCamera",
                "omniscape_torch.augment.RandomReproject")

_NAME = re.compile(r"(?<![\w.])(?:ot|omniscape_torch)(?:\.[A-Za-z_]\w*)+")
_FROM = re.compile(r"^[ \t]*from[ \t]+(omniscape_torch(?:\.\w+)*)[ \t]+import[ \t]+"
                   r"(?:\(([^)]*)\)|([\w \t,]+))", re.M)


def _documents() -> list[Path]:
    docs = [ROOT / "README.md", ROOT / "ARCHITECTURE.md", *sorted(ROOT.glob("docs/**/*.md"))]
    return [p for p in docs + [DESIGN] if p.is_file()]


def _code(text: str) -> tuple[list[str], list[str]]:
    """(fenced code blocks, inline code spans) of a Markdown text."""
    blocks = re.findall(r"```.*?```", text, flags=re.S)
    rest = re.sub(r"```.*?```", "", text, flags=re.S)
    return blocks, re.findall(r"`([^`\n]+)`", rest)


def documented_names() -> dict[str, str]:
    """``{dotted name: the document that gives it}``."""
    found = {name: "DESIGN.md (list)" for name in DESIGN_NAMES}
    for path in _documents():
        blocks, spans = _code(path.read_text(encoding="utf-8"))
        for code in blocks + spans:
            for name in _NAME.findall(code):
                found.setdefault(name, path.name)
        for block in blocks:
            for module, grouped, names in _FROM.findall(block):
                for name in filter(None, (n.strip() for n in (grouped or names)
                                          .replace("\n", ",").split(","))):
                    found.setdefault(f"{module}.{name.split()[0]}", path.name)
    return found


def resolve(name: str):
    """The object a documented dotted name names (AttributeError/ImportError if none)."""
    parts = name.split(".")
    if parts[0] == "ot":   # an attribute path from `import omniscape_torch as ot`
        obj = ot
        for part in parts[1:]:
            obj = getattr(obj, part)
        return obj
    # written in full: each module on the way importable under the name written
    obj = importlib.import_module(parts[0])
    for k, part in enumerate(parts[1:], 2):
        dotted = ".".join(parts[:k])
        if isinstance(obj, types.ModuleType) and hasattr(obj, "__path__"):   # a package
            try:
                obj = importlib.import_module(dotted)
                continue
            except ModuleNotFoundError as err:
                if err.name != dotted:
                    raise
        obj = getattr(obj, part)
        if isinstance(obj, types.ModuleType):
            raise ImportError(f"{dotted}: an attribute ({obj.__name__}), not a module that "
                              f"imports under this name")
    return obj


def test_the_documents_give_names():
    names = documented_names()
    assert len(names) >= len(DESIGN_NAMES) + 10, sorted(names)   # the parser found them


@pytest.mark.parametrize("name", sorted(documented_names()))
def test_documented_name_resolves(name):
    assert resolve(name) is not None


def test_augment_is_a_module_with_the_same_classes():
    from omniscape_torch.augment import RandomOmniCamera, RandomReproject

    import omniscape_torch.augment as augment
    assert ot.augment is augment
    assert RandomOmniCamera is ot.augment.RandomOmniCamera
    assert RandomReproject is ot.augment.RandomReproject
    for name in augment.__all__:
        assert getattr(ot.augment, name) is not None


def test_resolve_refuses_a_name_that_is_only_an_attribute(monkeypatch):
    """The check is meaningful: ``omniscape_torch.datasets`` is an attribute (``ot.datasets``)
    but no module of that dotted name; and a missing name fails."""
    assert resolve("ot.datasets.OmniDataset") is ot.OmniDataset
    with pytest.raises(ImportError):
        resolve("omniscape_torch.datasets")
    with pytest.raises(AttributeError):
        resolve("ot.cameras.no_such_name")
    with pytest.raises(AttributeError):
        resolve("omniscape_torch.scenes.Town.no_such_method")
    assert resolve("omniscape_torch.scenes.Town.render_cubemap") is not None
