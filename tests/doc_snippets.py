"""Code examples of the docs, to run in tests: the fenced Python blocks of docs/*.md and the
``::`` blocks of docstrings.

A Python block that cannot run in the tests (a fragment of a longer example, hours of training)
says so on the line before its fence, with the reason: ``<!-- not run: REASON -->`` (an HTML
comment, shown neither on the site nor on GitHub). Shell commands are ``bash`` blocks, which no test
runs.
"""

from __future__ import annotations

import inspect
import re
import textwrap
from pathlib import Path
from typing import NamedTuple

DOCS = Path(__file__).resolve().parents[1] / "docs"
BLOCK = re.compile(
    r"^(?:<!-- not run: (?P<reason>.*?) -->\n)?```python\n(?P<code>.*?)^```", re.DOTALL | re.MULTILINE
)


class DocBlock(NamedTuple):
    """One fenced ``python`` block of a page of the docs."""

    doc: str
    line: int
    """Line of the block's first line of code in the page (1-based)."""
    code: str
    not_run: str | None
    """Why the tests do not run it (``None``: they do)."""

    def compiled(self):
        """The block compiled, named ``docs/<doc>:<line>`` in tracebacks."""
        return compile("\n" * (self.line - 1) + self.code, f"docs/{self.doc}", "exec")


def python_blocks(doc: str) -> list[DocBlock]:
    """The fenced ``python`` blocks of ``docs/<doc>``, in page order."""
    text = (DOCS / doc).read_text(encoding="utf-8")
    return [
        DocBlock(doc, text.count("\n", 0, match.start("code")) + 1, match["code"], match["reason"])
        for match in BLOCK.finditer(text)
    ]


def python_block(doc: str, marker: str) -> str:
    """The one fenced ``python`` block of ``docs/<doc>`` that contains ``marker``."""
    found = [block.code for block in python_blocks(doc) if marker in block.code]
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
