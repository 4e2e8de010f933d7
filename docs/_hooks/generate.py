"""MkDocs hook: pages generated at build time from the code, so they cannot go stale.

A page asks for generated text with an HTML comment on a line of its own:

``<!-- generated: cli -->``
    every ``gesturedb`` command's ``--help``, from the real argparse parsers
    (:func:`gesturedb.cli.main.make_parser`), nested sub-commands included;
``<!-- generated: schema -->``
    the HDF5 schema, :func:`gesturedb.db.schema.describe` (what ``gesturedb info --schema`` prints);
``<!-- generated: include PATH -->``
    a Markdown file of the repository (PATH relative to the repository root), e.g.
    ``benchmarks/RESULTS.md``; its links into ``docs/`` are rewritten for the site.

Listed under ``hooks:`` in ``mkdocs.yml``; ``tests/test_docs.py`` calls these functions too.
"""
from __future__ import annotations

import argparse
import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MARKER = re.compile(r"^<!--\s*generated:\s*(\w+)\s*(.*?)\s*-->\s*$", re.M)
#: help text is formatted for this many columns whatever the terminal running the build
HELP_COLUMNS = 100


def _subcommands(parser: argparse.ArgumentParser) -> dict:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def commands(parser: argparse.ArgumentParser | None = None, words: tuple = ()) -> list:
    """``(words, parser)`` of every command, depth first: ``((), gesturedb)``, ``(("build",), ...)``, ..."""
    if parser is None:
        from gesturedb.cli.main import make_parser

        parser = make_parser()
    out = [(words, parser)]
    for name, sub in _subcommands(parser).items():
        out += commands(sub, words + (name,))
    return out


def cli_reference() -> str:
    """Markdown: a section per command with its ``--help`` as argparse prints it."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(HELP_COLUMNS)  # argparse reads the width from here
    try:
        parts = []
        for words, parser in commands():
            title = " ".join(("gesturedb",) + words)
            level = "#" * min(2 + max(len(words) - 1, 0), 4)
            parts += [f"{level} {title}", "", "```text", parser.format_help().rstrip(), "```", ""]
        return "\n".join(parts)
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def schema_reference() -> str:
    from gesturedb.db import schema

    return schema.describe()


def include(path: str) -> str:
    """A repository file's Markdown without its title, its links into docs/ made relative to the site."""
    text = (ROOT / path).read_text()
    text = re.sub(r"\A\s*# [^\n]*\n", "", text)  # the including page has the title
    return re.sub(r"\]\((?:\.\./)?docs/", "](", text)


def expand(markdown: str) -> str:
    """``markdown`` with every ``<!-- generated: ... -->`` marker replaced by its text."""
    def one(m):
        kind, arg = m.group(1), m.group(2)
        if kind == "cli":
            return cli_reference()
        if kind == "schema":
            return schema_reference()
        if kind == "include":
            return include(arg)
        raise ValueError(f"unknown generated block {kind!r} (expected cli, schema or include PATH)")

    return MARKER.sub(one, markdown)


def on_page_markdown(markdown, page, config, files):  # noqa: ARG001 - the MkDocs hook signature
    return expand(markdown)
