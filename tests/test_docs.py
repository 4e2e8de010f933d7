"""The docs site's own machinery: the pages generated at build time and the navigation.

``mkdocs build --strict`` (scripts/test.sh) fails on a broken link, a missing page or a
docstring mkdocstrings cannot read; these tests check, without building the site, that the
generated pages say what the code says (every CLI command, the schema) and that every page
of docs/ is reachable.
"""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


@pytest.fixture(scope="module")
def hook():
    spec = importlib.util.spec_from_file_location("docs_generate", DOCS / "_hooks" / "generate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _nav_pages(nav) -> list[str]:
    out = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        out += _nav_pages(value) if isinstance(value, list) else [value]
    return out


def _config() -> dict:
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text())


def test_every_page_is_in_the_nav():
    cfg = _config()
    assert cfg["docs_dir"] == "docs" and cfg.get("strict") is True
    nav = _nav_pages(cfg["nav"])
    pages = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md") if "_hooks" not in p.parts)
    assert sorted(nav) == pages, "mkdocs.yml's nav and the pages of docs/ differ"
    assert str(DOCS / "_hooks" / "generate.py").endswith(cfg["hooks"][0].split("/", 1)[1])


def test_cli_reference_has_every_command_and_option(hook):
    from gesturedb.cli.main import make_parser

    text = hook.cli_reference()
    cmds = hook.commands(make_parser())
    assert len(cmds) >= 20  # gesturedb, its 12 commands and their sub-commands
    for words, parser in cmds:
        title = " ".join(("gesturedb",) + words)
        assert re.search(rf"^#+ {re.escape(title)}$", text, re.M), f"no section for {title}"
        for action in parser._actions:
            for opt in action.option_strings:
                assert opt in text, f"{title}: {opt} missing from the CLI reference"
    # synth's --help is long: the width is fixed, so the page does not depend on the terminal
    assert max(len(ln) for ln in text.splitlines()) <= hook.HELP_COLUMNS + 20


def test_generated_blocks_are_where_the_pages_ask(hook):
    from gesturedb.db import schema

    cli, sch, res = ((DOCS / n).read_text() for n in ("cli.md", "schema.md", "results.md"))
    assert "<!-- generated: cli -->" in cli and "<!-- generated: schema -->" in sch
    assert "<!-- generated: include benchmarks/RESULTS.md -->" in res
    out = hook.expand(sch)
    assert schema.describe() in out and "<!--" not in out
    assert f"Schema version {schema.SCHEMA_VERSION}." in out
    inc = hook.expand(res)
    assert "## Search" in inc and "](docs/" not in inc
    with pytest.raises(ValueError, match="unknown generated block 'nope'"):
        hook.expand("<!-- generated: nope -->")


def test_results_name_a_command_for_every_benchmark():
    """benchmarks/RESULTS.md holds the latest figure of each benchmark, with its command."""
    text = (ROOT / "benchmarks" / "RESULTS.md").read_text()
    for bench in sorted((ROOT / "benchmarks").glob("bench_*.py")):
        assert f"benchmarks/{bench.name}" in text, f"benchmarks/RESULTS.md has no figure of {bench.name}"


def test_docs_name_no_stale_paths():
    """The package moved to src/gesturedb/ and its CLI to src/gesturedb/cli/."""
    stale = re.compile(r"(?<![\w/.\-])gesturedb/(?:cli|db|io|synth|eval|features|control|refiner)/")
    for p in [ROOT / "README.md"] + sorted(DOCS.rglob("*.md")):
        if p.name == "ARCHITECTURE.md":  # module paths there are relative to src/gesturedb/, as it says
            continue
        for ln, line in enumerate(p.read_text().splitlines(), start=1):
            m = stale.search(line)
            if m and "installed" not in line:
                pytest.fail(f"{p.relative_to(ROOT)} line {ln}: {m.group(0)} is now src/{m.group(0)}")
