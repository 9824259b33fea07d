"""Code examples of the docs, to run in tests: the fenced Python blocks of docs/*.md and the
``::`` blocks of docstrings."""

from __future__ import annotations

import inspect
import re
import textwrap
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"


def python_block(doc: str, marker: str) -> str:
    """The one fenced ``python`` block of ``docs/<doc>`` that contains ``marker``."""
    blocks = re.findall(r"^```python\n(.*?)^```", (DOCS / doc).read_text(), flags=re.DOTALL | re.MULTILINE)
    found = [block for block in blocks if marker in block]
    if len(found) != 1:
        raise LookupError(f"docs/{doc} has {len(found)} python blocks containing {marker!r}, expected 1.")
    return found[0]


def docstring_example(docstring: str) -> str:
    """The indented block after the first line of ``docstring`` that ends with ``::``, dedented."""
    match = re.search(r"::\n\n((?:[ \t]+\S.*\n|\n)+)", inspect.cleandoc(docstring) + "\n")
    if match is None:
        raise LookupError("The docstring has no '::' example block.")
    return textwrap.dedent(match.group(1))


def run_snippet(code: str) -> dict:
    """Run ``code`` in a fresh namespace and return that namespace."""
    namespace: dict = {"__name__": "doc_snippet"}
    exec(compile(code, "<doc snippet>", "exec"), namespace)
    return namespace
