"""A griffe extension for the API reference: the docstrings are written for Sphinx (``:class:`X```,
``:func:`~a.b```, a paragraph ending in ``::`` before an example); this turns those roles into
Markdown code and the ``::`` into ``:``, so mkdocstrings renders them as text, not as markup."""

from __future__ import annotations

import re
from typing import Any

from griffe import Extension, Object

ROLE = re.compile(r":(?:class|func|meth|mod|data|attr|exc|obj):`(~?)([^`]+)`")
RAISES = re.compile(r"(:raises?\s+)~[\w.]*?(\w+):")


def rst_to_markdown(text: str) -> str:
    """``text`` with every Sphinx role as inline code (``~a.b.C`` as ``C``), ``:raises ~a.b.E:`` as
    ``:raises E:`` and ``::`` ends as ``:``."""
    text = ROLE.sub(lambda m: f"``{m.group(2).rsplit('.', 1)[-1] if m.group(1) else m.group(2)}``", text)
    text = RAISES.sub(r"\1\2:", text)  # ``:raises ~a.b.Error:``: the type's name
    return re.sub(r"(?<=\S)::$", ":", text, flags=re.MULTILINE)


class RstRoles(Extension):
    """Rewrites the docstring of every object griffe loads (see :func:`rst_to_markdown`)."""

    def on_instance(self, *, obj: Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value)
