"""The code in docs/writing-a-driver.md and docs/writing-a-controller.md is the code that runs.

Every Python block of those pages carries a marker, an HTML comment on the line before it
(a blank line between them is allowed):

* ``<!-- file: PATH -->``: a part of the file PATH; the parts of a file, in page order, are
  the whole file (blank lines aside). The file itself runs in tests/test_examples.py.
* ``<!-- run -->``: a test module as a reader would write one. It is executed here with
  examples/ importable, and each of its ``test_*`` functions is called (a coroutine on its
  own event loop).
* ``<!-- fragment -->``: a piece of code shown to explain one call; it must parse.

A page whose code no longer matches its file, or whose tests fail, fails here.
"""

from __future__ import annotations

import ast
import asyncio
import re
import sys
import textwrap
import types

import pytest
from conftest import ROOT, require_module

PAGES = ["writing-a-driver.md", "writing-a-controller.md"]
FENCE = re.compile(r"^```python\n(.*?)^```$", re.M | re.S)
MARKER = re.compile(r"<!--\s*(file:\s*(?P<path>\S+)|run|fragment)\s*-->\s*$")


def blocks(page: str) -> list[tuple[str, str | None, str]]:
    """(kind, path or None, code) for every Python block of ``page``, in order."""
    text = (ROOT / "docs" / page).read_text()
    out = []
    for match in FENCE.finditer(text):
        before = [line for line in text[: match.start()].splitlines() if line.strip()]
        marker = MARKER.match(before[-1].strip()) if before else None
        if marker is None:
            line = text[: match.start()].count("\n") + 1
            raise AssertionError(f"docs/{page}, line {line}: a Python block without a marker (file:, run, fragment)")
        kind = "file" if marker.group("path") else marker.group(1)
        out.append((kind, marker.group("path"), match.group(1)))
    return out


def significant(code: str) -> list[str]:
    return [line.rstrip() for line in code.splitlines() if line.strip()]


@pytest.mark.parametrize("page", PAGES)
def test_every_block_is_marked_and_fragments_parse(page):
    found = blocks(page)
    assert any(kind == "file" for kind, _, _ in found) and any(kind == "run" for kind, _, _ in found)
    for kind, _, code in found:
        if kind == "fragment":
            ast.parse(textwrap.dedent(code))


@pytest.mark.parametrize("page", PAGES)
def test_the_page_quotes_its_files_whole_and_verbatim(page):
    parts: dict[str, list[str]] = {}
    for kind, path, code in blocks(page):
        if kind == "file":
            parts.setdefault(path, []).extend(significant(code))
    for path, lines in parts.items():
        on_disk = significant((ROOT / path).read_text())
        assert lines == on_disk, f"docs/{page} does not quote {path} as it is"


def run_tests(page: str) -> list[str]:
    """Execute the page's ``run`` blocks with examples/ importable; call every test in them."""
    ran = []
    sys.path.insert(0, str(ROOT / "examples"))
    try:
        for n, (kind, _, code) in enumerate(blocks(page)):
            if kind != "run":
                continue
            module = types.ModuleType(f"doc_{page.replace('-', '_')[:-3]}_{n}")
            sys.modules[module.__name__] = module  # pydantic models in it resolve their annotations
            try:
                exec(compile(code, f"docs/{page} (block {n})", "exec"), module.__dict__)
                for name, test in list(vars(module).items()):
                    if name.startswith("test_") and callable(test):
                        result = test()
                        if asyncio.iscoroutine(result):
                            asyncio.run(result)
                        ran.append(name)
            finally:
                del sys.modules[module.__name__]
    finally:
        sys.path.remove(str(ROOT / "examples"))
    return ran


def test_the_driver_page_tests_pass():
    ran = run_tests("writing-a-driver.md")
    assert len(ran) >= 3, ran


def test_the_controller_page_tests_pass():
    require_module("mujoco")
    ran = run_tests("writing-a-controller.md")
    assert len(ran) >= 2, ran
