"""Every public name has an entry in the API reference (docs/api/*.md).

A page documents a module with a ``::: dotted.path`` block; mkdocstrings renders the members the
module makes public (its ``__all__``), or those named in the block's ``members:`` option. This
test reads the pages as text (no mkdocs, no import of the heavy packages' dependencies beyond
the package itself) and checks that each name of each ``__all__`` below is covered: the
top-level package's names by the API index page, each package's and module's by a block of its
own module (or of the package that re-exports it). A new public name without a reference entry
fails here; ``mkdocs build --strict`` then checks that the entry renders.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from pathlib import Path

import pytest

import omniscape_torch

ROOT = Path(__file__).resolve().parents[1]
API = ROOT / "docs" / "api"
#: modules left out of the reference on purpose: the command line is documented by its guides
SKIP = {"omniscape_torch.cli"}
BLOCK = re.compile(r"^::: *(?P<path>[\w.]+)\n(?P<options>(?:[ \t]+.*\n?)*)", re.M)


def _blocks() -> dict[str, list[str] | None]:
    """``{module path: members listed (None: the module's public members)}`` of every page."""
    blocks: dict[str, list[str] | None] = {}
    for page in sorted(API.glob("*.md")):
        for m in BLOCK.finditer(page.read_text(encoding="utf-8")):
            members = re.search(r"members: *\[(.*)\]", m["options"])
            listed = [n.strip() for n in members[1].split(",")] if members else None
            if re.search(r"members: *false", m["options"]):
                listed = []
            blocks[m["path"]] = listed
    return blocks


def _modules_with_all():
    for info in pkgutil.walk_packages(omniscape_torch.__path__, "omniscape_torch."):
        if info.name in SKIP or info.name.split(".")[-1].startswith("_"):
            continue
        module = importlib.import_module(info.name)
        if hasattr(module, "__all__"):
            yield info.name, module


def _covered(module_name: str, name: str, blocks) -> bool:
    """A block of the module shows the name, or a block of a package that re-exports it, or
    (for a module that re-exports another's names, as ``omniscape_torch.augment``) a block of
    a module whose ``__all__`` holds the same object under that name."""
    listed = blocks.get(module_name, False)
    if listed is None or (listed and name in listed):
        return True
    parts = module_name.split(".")
    for i in range(len(parts) - 1, 1, -1):
        package = ".".join(parts[:i])
        pkg = importlib.import_module(package)
        if name in getattr(pkg, "__all__", ()) and blocks.get(package, False) is None:
            return True
    value = getattr(importlib.import_module(module_name), name)
    for path, members in blocks.items():
        other = importlib.import_module(path)
        if (path != module_name and name in getattr(other, "__all__", ())
                and (members is None or name in members) and getattr(other, name) is value):
            return True
    return False


@pytest.mark.parametrize("module_name", [n for n, _ in _modules_with_all()])
def test_every_public_name_has_a_reference_entry(module_name):
    blocks = _blocks()
    module = importlib.import_module(module_name)
    missing = [n for n in module.__all__ if not _covered(module_name, n, blocks)]
    assert not missing, (f"{module_name}: {missing} have no entry in docs/api/*.md: add a "
                         f"'::: {module_name}' block (or the name to its members: list)")


def test_top_level_names_are_in_the_index():
    index = (API / "index.md").read_text(encoding="utf-8")
    missing = [n for n in omniscape_torch.__all__ if f"`ot.{n}`" not in index]
    assert not missing, f"docs/api/index.md lacks {missing}"


def test_every_block_names_a_module():
    for path in _blocks():
        importlib.import_module(path)


#: A reST role, as Sphinx writes cross-references: the Markdown site would show it as text.
ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|attr|data|exc|obj|const):`")


def test_no_docstring_holds_a_rest_role():
    """The site renders the docstrings as Markdown (mkdocstrings): `:func:`x`` would show as
    text, so the package writes code spans or `[name][dotted.path]` cross-references."""
    found = [f"{path.relative_to(ROOT)}:{number}"
             for path in sorted((ROOT / "omniscape_torch").rglob("*.py"))
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if ROLE.search(line)]
    assert not found, f"{len(found)} reST roles, the first at " + ", ".join(found[:5])


@pytest.mark.slow
def test_the_built_site_shows_no_role_and_resolves_every_reference(tmp_path):
    """`mkdocs build --strict` (an unresolved cross-reference or a missing name fails it), then
    no page of the API reference shows a reST role as text."""
    import os
    import subprocess
    import sys
    site = tmp_path / "site"
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet",
                           "--site-dir", str(site)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    pages = sorted((site / "api").rglob("*.html"))
    assert len(pages) >= 8
    text = re.compile(r"<[^>]+>")
    shown = [(page.name, m.group(0)) for page in pages
             for m in ROLE.finditer(text.sub("", page.read_text(encoding="utf-8")))]
    assert not shown, shown[:5]
