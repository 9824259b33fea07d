"""A MkDocs hook: the page holding ``<!-- cli-help -->`` gets the ``--help`` text of ``sb3-hgrn`` and
of each of its subcommands, from the parser the command itself uses (:func:`sb3_hgrn.cli.build_parser`),
so the reference cannot drift from the code."""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator
from typing import Any

MARKER = "<!-- cli-help -->"


def parsers(parser: argparse.ArgumentParser, path: str) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """``(command, parser)`` of ``parser`` and of all its subcommands, depth first."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from parsers(child, f"{path} {name}")


def help_markdown() -> str:
    """One section per command, its help text in a code block."""
    from sb3_hgrn.cli import build_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal width: fix it for a stable page
    return "\n".join(
        f"## `{command}`\n\n```text\n{parser.format_help().rstrip()}\n```\n"
        for command, parser in parsers(build_parser(), "sb3-hgrn")
    )


def on_page_markdown(markdown: str, **kwargs: Any) -> str:
    """Put the help text where the page has :data:`MARKER`."""
    return markdown.replace(MARKER, help_markdown()) if MARKER in markdown else markdown
