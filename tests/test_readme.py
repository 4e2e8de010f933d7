"""Every example of the README and the docs site runs as written, and every command line in
them is one the CLI accepts.

The Markdown files are README.md and docs/**/*.md (the pages ``mkdocs.yml`` builds):

- ```python blocks run, in order, in one interpreter per block.
- ```bash / ```console blocks run with bash, in order, after the demo (scripts/demo.sh
  without its set-up lines) made the outputs the pages refer to (out/scott.h5,
  out/2_scott_0_2_2.bvh). In a console block only the ``$ `` lines run.
- A block preceded by ``<!-- not run by tests/test_readme.py: REASON -->`` is not run (the
  reason must be given); its ``gesturedb`` lines are still parsed by the real argument
  parser, so a renamed flag fails here either way.
- Blocks without a language or marked ```text are synopses (``[--option]``, ``DB.h5``):
  every ``gesturedb COMMAND`` they show must exist and every ``--option`` must be one of
  that command's options.

Everything runs in a sandbox laid out like the repository's neighbourhood
(``SANDBOX/repo`` as the working folder, ``SANDBOX/shared/data`` the real data), so
``../shared/data`` means what the pages say and nothing is written into the repository.
The docs site itself is built with ``mkdocs build --strict`` by scripts/test.sh; the
generated pages (CLI, schema) are checked here too (tests/test_docs.py).
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
SKIP = re.compile(r"<!--\s*not run by tests/test_readme\.py:\s*(.*?)\s*-->", re.S)
FENCE = re.compile(r"^(\s*)```(\w*)\s*$")
SHELL = ("bash", "console", "sh", "shell")
SYNOPSIS = ("", "text")


def markdown_files() -> list[Path]:
    """README.md, then every page of the docs site (docs/_hooks is code, not a page)."""
    pages = sorted(p for p in DOCS.rglob("*.md") if "_hooks" not in p.parts)
    return [README] + pages


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


def blocks(path: Path) -> list[tuple[str, str, str | None, int]]:
    """(language, code, skip reason or None, first line number) of every fenced block of ``path``."""
    lines = path.read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, lang, start = m.group(1), m.group(2), i
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith("```"):
            j += 1
        assert j < len(lines), f"{_name(path)} line {start + 1}: a fenced block is not closed"
        code = "\n".join(ln[len(indent):] if ln.startswith(indent) else ln for ln in lines[start + 1:j]) + "\n"
        # the skip marker is the last non-blank text before the fence (it may span lines)
        before = "\n".join(lines[max(0, start - 6):start]).rstrip()
        skip = SKIP.search(before) if before.endswith("-->") else None
        out.append((lang, code, skip.group(1) if skip else None, start + 1))
        i = j + 1
    return out


def all_blocks():
    for path in markdown_files():
        for lang, code, skip, ln in blocks(path):
            yield path, lang, code, skip, ln


def gesturedb_lines(code: str, *, console: bool = False) -> list[str]:
    """Command lines starting with ``gesturedb``, continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", code)
    out = []
    for line in joined.splitlines():
        line = line.strip()
        if console:
            if not line.startswith("$ "):
                continue
            line = line[2:].strip()
        line = re.split(r"\s#", line, maxsplit=1)[0].strip()
        if line.startswith("gesturedb "):
            out.append(line)
    return out


def _parser():
    from gesturedb.cli.main import make_parser

    return make_parser()


def _subparser(parser, words):
    """The argparse parser of ``gesturedb WORDS...`` (nested sub-commands followed as far as they go)."""
    p = parser
    for w in words:
        sub = next((a for a in p._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or w not in sub.choices:
            break
        p = sub.choices[w]
    return p


def _options(p) -> set[str]:
    """Option strings of a parser and of all its sub-commands."""
    out = set()
    for a in p._actions:
        out.update(a.option_strings)
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                out |= _options(sp)
    return out


def test_blocks_are_found_and_skips_say_why():
    readme_langs = [b[0] for b in blocks(README)]
    assert "python" in readme_langs and "bash" in readme_langs
    n_run = 0
    for path, lang, _, skip, ln in all_blocks():
        assert skip is None or skip.strip(), f"{_name(path)} line {ln}: a skipped block must say why"
        n_run += skip is None and lang in ("python",) + SHELL
    assert n_run >= 15


def test_readme_is_short():
    n = len(README.read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines: guides and reference belong in docs/ (at most 300)"


def test_no_dated_measurements_in_the_readme():
    """Measurements live in benchmarks/RESULTS.md and docs/evaluation.md, not in the README's prose."""
    text = README.read_text()
    dates = re.findall(r"\b20\d\d-\d\d-\d\d\b", text)
    assert not dates, f"README.md: dated measurements {dates} belong in benchmarks/RESULTS.md or docs/"


def test_command_lines_parse():
    """Every gesturedb line of a shell block is accepted by the real parser (run or not)."""
    parser = _parser()
    n = 0
    for path, lang, code, _, ln in all_blocks():
        if lang not in SHELL:
            continue
        for line in gesturedb_lines(code, console=lang == "console"):
            argv = shlex.split(line)[1:]
            try:
                args = parser.parse_args(argv)
            except SystemExit:
                pytest.fail(f"{_name(path)} line {ln}: the CLI does not accept: {line}")
            assert callable(args.run)
            n += 1
    assert n >= 25


def test_synopsis_commands_and_options_exist():
    parser = _parser()
    n = 0
    for path, lang, code, _, ln in all_blocks():
        if lang not in SYNOPSIS:
            continue
        for line in gesturedb_lines(code):
            words = line.split()[1:]
            sub = _subparser(parser, words[:1])
            assert sub is not parser, f"{_name(path)} line {ln}: unknown command in: {line}"
            # a synopsis may list alternatives (`list | add WORD [--before S]`): options of any of its sub-commands
            known = _options(sub)
            for opt in re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", line):
                assert opt in known, f"{_name(path)} line {ln}: {opt} is not an option of `gesturedb {words[0]}`: {line}"
            n += 1
    assert n >= 15


def test_readme_links_exist():
    """The README's relative links and pictures point at files of the repository (the docs
    site's own links are checked by mkdocs build --strict)."""
    text = README.read_text()
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    assert len(targets) >= 15
    for t in targets:
        if re.match(r"[a-z]+://", t):
            continue
        path = (ROOT / t.split("#", 1)[0]).resolve()
        assert path.exists(), f"README.md links to {t}, which does not exist"


# ---------------------------------------------------------------------------
# running the examples


@pytest.fixture(scope="module")
def sandbox(data_dir, tmp_path_factory):
    """SANDBOX/repo with ../shared/data, after the demo's commands (not its set-up) ran there."""
    box = tmp_path_factory.mktemp("readme")
    repo = box / "repo"
    (repo / "scripts").mkdir(parents=True)
    (box / "shared").mkdir()
    os.symlink(data_dir, box / "shared" / "data")
    demo = (ROOT / "scripts" / "demo.sh").read_text()
    # the demo without its set-up lines (the environment running these tests is the installed one)
    # and without its `cd` to the repository: it runs in the sandbox
    skip = ("bash scripts/setup.sh", ". scripts/venv.sh", 'cd "$(dirname "$0")/.."')
    body = "\n".join(ln for ln in demo.splitlines() if not ln.strip().startswith(skip))
    assert body.count("gesturedb ") >= 3
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", body], cwd=repo, env=_env(), capture_output=True,
                       text=True, timeout=900)
    assert r.returncode == 0, f"scripts/demo.sh failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    assert (repo / "out" / "scott.h5").exists() and (repo / "out" / "2_scott_0_2_2.bvh").exists()
    return repo


def _env():
    env = {k: v for k, v in os.environ.items() if k != "GESTUREDB_DATA"}
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env["PATH"]
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("MPLBACKEND", "Agg")
    return env


def _runnable(path: Path):
    return [(lang, code, ln) for lang, code, skip, ln in blocks(path)
            if skip is None and lang in ("python",) + SHELL]


def _command(lang: str, code: str) -> list[str]:
    if lang == "python":
        return [sys.executable, "-c", code]
    if lang == "console":
        code = "\n".join(ln.strip()[2:] for ln in code.splitlines() if ln.strip().startswith("$ "))
    return ["bash", "-euo", "pipefail", "-c", code]


@pytest.mark.slow
@pytest.mark.parametrize("page", [_name(p) for p in markdown_files() if _runnable(p)])
def test_examples_run_as_written(sandbox, page):
    """The page's runnable blocks, in order, in the sandbox the demo left (earlier pages' outputs may be there)."""
    for lang, code, ln in _runnable(ROOT / page):
        r = subprocess.run(_command(lang, code), cwd=sandbox, env=_env(), capture_output=True, text=True,
                           timeout=900)
        assert r.returncode == 0, (f"{page} block at line {ln} ({lang}) failed:\n{code}\n"
                                   f"{r.stdout[-2000:]}\n{r.stderr[-4000:]}")
