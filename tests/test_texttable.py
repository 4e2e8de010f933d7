"""Text tables that fit a terminal (gesturedb.eval.texttable): `gesturedb eval` prints tables of at most
100 columns, cut into parts that repeat the row labels; the JSON and HTML keep the whole table."""
from __future__ import annotations

import re

import pytest

from gesturedb.eval.texttable import TEXT_WIDTH, text_table


def _parts(text):
    return [p.splitlines() for p in text.split("\n\n")]


@pytest.mark.parametrize("n_cols,label", [(1, 6), (5, 11), (14, 11), (14, 40), (30, 3)])
def test_parts_fit_and_keep_every_cell_beside_its_label(n_cols, label):
    head = ["name".ljust(label)] + [f"metric {i} unit" for i in range(n_cols)]
    body = [[f"row{r}"] + [f"{r * 1000 + i * 1.25:.3f}" for i in range(n_cols)] for r in range(3)]
    text = text_table(head, body)
    parts = _parts(text)
    seen = {}
    for lines in parts:
        assert all(len(ln) <= TEXT_WIDTH and ln == ln.rstrip() for ln in lines), lines
        assert re.fullmatch(r"-+( +-+)*", lines[1])  # the rule under the head
        heads = re.split(r"  +", lines[0].strip())
        assert heads[0] == "name"
        for r, ln in enumerate(lines[2:]):
            cells = ln.split()
            assert cells[0] == f"row{r}"  # the label column is repeated in every part
            for h, c in zip(heads[1:], re.split(r"  +", ln[len(lines[0]) - len(lines[0].lstrip()):].strip())[1:]):
                seen.setdefault(h, []).append(c)
    # every column exactly once, in order, with its own cells
    assert list(seen) == head[1:]
    for i, h in enumerate(head[1:]):
        assert seen[h] == [body[r][i + 1] for r in range(3)]
    # as few parts as fit, shared evenly
    sizes = [len(re.split(r"  +", p[0].strip())) - 1 for p in parts]
    assert max(sizes) - min(sizes) <= 1 or len(parts) == 1
    if len(text.splitlines()[0]) <= TEXT_WIDTH and len(parts) == 1:
        assert sizes == [n_cols]


def test_a_narrow_table_is_one_table_and_alignment():
    t = text_table(["system", "jerk", "H"], [["reference", "12.5", "0.100"], ["k-NN", "3.0", "0.2"]])
    assert t == ("system     jerk      H\n"
                 "---------  ----  -----\n"
                 "reference  12.5  0.100\n"
                 "k-NN        3.0    0.2")
    t = text_table(["control", "status"], [["wrist high", "PASS"], ["slow", "FAIL"]], align="left")
    assert t.splitlines()[2:] == ["wrist high  PASS", "slow        FAIL"]
    # a column wider than the width is a part of its own, never dropped
    wide = text_table(["l", "x" * 120, "y"], [["a", "1", "2"]])
    assert [len(p) for p in _parts(wide)] == [3, 3] and "y" in _parts(wide)[1][0]
    with pytest.raises(ValueError, match="align"):
        text_table(["a"], [["b"]], align="centre")


def test_eval_motion_text_fits_a_terminal(scott_db, scott_dir, monkeypatch):
    from gesturedb.eval import evaluate as E
    from gesturedb.eval import texttable

    ev = E.evaluate_inputs(scott_db, [scott_dir / "inputs" / "2_scott_0_4_4.wav"],
                           systems=["random", "ranksum_pose"], starts=2)
    tables = []

    def recording(head, body, **kw):
        tables.append((head, texttable.text_table(head, body, **kw)))
        return tables[-1][1]

    monkeypatch.setattr(E, "text_table", recording)
    text = ev.to_text()
    assert len(tables) >= 5  # metrics, strokes, world, conventions, starts
    widest = max(len(ln) for _, t in tables for ln in t.splitlines())
    assert widest <= TEXT_WIDTH
    # the whole tables were wider: they come in parts, each column once
    full = [len("  ".join(head)) for head, _ in tables]
    assert max(full) > TEXT_WIDTH
    for head, t in tables:
        assert t in text
        for h in head[1:]:
            assert sum(ln.count(h) for p in _parts(t) for ln in p[:1]) >= 1
    # the JSON keeps every column of every table in one row per system
    row = ev.to_dict()["inputs"][0]["metrics"]["ranksum_pose"]
    for key, header, _ in E.METRIC_COLUMNS + E.WORLD_COLUMNS:
        if header in text:
            assert key in row
