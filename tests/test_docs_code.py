"""Every ```python block of README.md and docs/**/*.md runs as written.

Each page is one test: its python blocks run in order in one namespace, from the repository
root (so ``../shared/data/...`` resolves), as a reader pasting them one after the other would.
Blocks that are not Python to run (shell commands, output listings, file layouts) use ``bash``
or ``text`` fences. A page listed in ``SLOW`` is marked ``slow``.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
#: pages (relative paths) whose blocks take more than a few seconds: marked ``slow``
SLOW = {"docs/calibration.md"}   # fit, image_circle, convert, select_model: about 10 s

FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^\n`]*)$")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(first line number, code)`` of each fenced block whose info string starts with
    ``python`` (``python`` or ``py``), dedented by its fence's indentation."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, info = m["indent"], m["fence"], m["info"].strip().split()
        body, j = [], i + 1
        while j < len(lines):
            close = FENCE.match(lines[j])
            if (close and close["fence"][0] == fence[0] and len(close["fence"]) >= len(fence)
                    and not close["info"].strip()):
                break
            body.append(lines[j][len(indent):] if lines[j].startswith(indent) else lines[j])
            j += 1
        if info and info[0] in ("python", "py"):
            blocks.append((i + 2, textwrap.dedent("\n".join(body))))
        i = j + 1
    return blocks


def _params():
    for page in PAGES:
        rel = page.relative_to(ROOT).as_posix()
        if python_blocks(page.read_text(encoding="utf-8")):
            marks = [pytest.mark.slow] if rel in SLOW else []
            yield pytest.param(page, id=rel, marks=marks)


@pytest.mark.parametrize("page", list(_params()))
def test_page_code_runs(page: Path, monkeypatch):
    monkeypatch.chdir(ROOT)
    namespace = {"__name__": "__docs__"}
    for line, code in python_blocks(page.read_text(encoding="utf-8")):
        compiled = compile("\n" * (line - 1) + code, str(page), "exec")
        exec(compiled, namespace)


def test_fences_are_found():
    text = "a\n```python\nx = 1\n```\n  ```bash\n  ls\n  ```\n  ```python\n  y = 2\n  ```\n"
    assert python_blocks(text) == [(3, "x = 1"), (9, "y = 2")]
