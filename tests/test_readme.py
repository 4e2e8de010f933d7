"""Every code block of the README runs as written, and every command line in it is one the CLI accepts.

- ```python blocks run, in order, in one interpreter per block.
- ```bash blocks run with bash, in order, after the demo (scripts/demo.sh without its
  set-up line) made the outputs the README refers to (out/scott.h5, out/2_scott_0_2_2.bvh).
  A block preceded by ``<!-- not run by tests/test_readme.py: REASON -->`` is not run (the
  reason must be given); its ``gesturedb`` lines are still parsed by the real argument parser.
- Blocks without a language and indented blocks are synopses (``[--option]``, ``DB.h5``):
  every ``gesturedb COMMAND`` they show must exist and every ``--option`` must be one of
  that command's options.

Everything runs in a sandbox laid out like the repository's neighbourhood
(``SANDBOX/repo`` as the working folder, ``SANDBOX/shared/data`` the real data), so
``../shared/data`` means what the README says and nothing is written into the repository.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SKIP = re.compile(r"<!--\s*not run by tests/test_readme\.py:\s*(.*?)\s*-->")


def blocks():
    """(language, code, skip reason or None, first line number) of every fenced block."""
    lines = README.read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        m = re.match(r"^```(\w*)\s*$", lines[i])
        if not m:
            i += 1
            continue
        lang, start = m.group(1), i
        j = i + 1
        while not lines[j].startswith("```"):
            j += 1
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        skip = SKIP.search(prev)
        out.append((lang, "\n".join(lines[start + 1:j]) + "\n", skip.group(1) if skip else None, start + 1))
        i = j + 1
    return out


def indented_blocks():
    """Indented code blocks (4 spaces after a blank line) outside fences."""
    text = README.read_text()
    fenced = re.sub(r"```.*?```", "", text, flags=re.S)
    return re.findall(r"(?:^|\n\n)((?: {4}\S.*\n?)+)", fenced)


def gesturedb_lines(code: str) -> list[str]:
    """Command lines starting with ``gesturedb``, continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", code)
    out = []
    for line in joined.splitlines():
        line = line.split(" #", 1)[0].strip()
        if line.startswith("gesturedb "):
            out.append(line)
    return out


def _parser():
    from gesturedb.cli.main import make_parser

    return make_parser()


def _subparser(parser, words):
    """The argparse parser of ``gesturedb WORDS...`` (nested sub-commands followed as far as they go)."""
    import argparse

    p = parser
    for w in words:
        sub = next((a for a in p._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or w not in sub.choices:
            break
        p = sub.choices[w]
    return p


def _options(p) -> set[str]:
    """Option strings of a parser and of all its sub-commands."""
    import argparse

    out = set()
    for a in p._actions:
        out.update(a.option_strings)
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                out |= _options(sp)
    return out


def test_readme_blocks_are_found():
    langs = [b[0] for b in blocks()]
    assert "python" in langs and "bash" in langs
    for lang, _, skip, ln in blocks():
        assert skip is None or skip.strip(), f"README line {ln}: a skipped block must say why"


def test_command_lines_parse():
    """Every gesturedb line of a bash block is accepted by the real parser (run or not)."""
    parser = _parser()
    n = 0
    for lang, code, _, ln in blocks():
        if lang != "bash":
            continue
        for line in gesturedb_lines(code):
            argv = shlex.split(line)[1:]
            try:
                args = parser.parse_args(argv)
            except SystemExit:
                pytest.fail(f"README line {ln}: the CLI does not accept: {line}")
            assert callable(args.run)
            n += 1
    assert n >= 5


def test_synopsis_commands_and_options_exist():
    parser = _parser()
    code = "\n".join(c for lang, c, _, _ in blocks() if lang == "") + "\n" + "\n".join(indented_blocks())
    lines = gesturedb_lines(code)
    assert len(lines) >= 10
    for line in lines:
        words = line.split()[1:]
        sub = _subparser(parser, words[:1])
        assert sub is not parser, f"README synopsis: unknown command in: {line}"
        # a synopsis may list alternatives (`list | add WORD [--before S]`): options of any of its sub-commands
        known = _options(sub)
        for opt in re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", line.split("#", 1)[0]):
            assert opt in known, f"README synopsis: {opt} is not an option of `gesturedb {words[0]}`: {line}"


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
    env = _env()
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", body], cwd=repo, env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, f"scripts/demo.sh failed:\n{r.stdout}\n{r.stderr}"
    assert (repo / "out" / "scott.h5").exists() and (repo / "out" / "2_scott_0_2_2.bvh").exists()
    return repo


def _env():
    env = {k: v for k, v in os.environ.items() if k != "GESTUREDB_DATA"}
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env["PATH"]
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


@pytest.mark.slow
def test_readme_code_blocks_run_as_written(sandbox):
    ran = 0
    for lang, code, skip, ln in blocks():
        if skip or lang not in ("python", "bash"):
            continue
        cmd = [sys.executable, "-c", code] if lang == "python" else ["bash", "-euo", "pipefail", "-c", code]
        r = subprocess.run(cmd, cwd=sandbox, env=_env(), capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, f"README block at line {ln} ({lang}) failed:\n{code}\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}"
        ran += 1
    assert ran >= 3
