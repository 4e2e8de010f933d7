"""`gesturedb.synth.graph.viterbi` against brute-force enumeration of every path (spec: ../shared/spec/graph.md)."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from gesturedb.errors import ParameterError, SearchError
from gesturedb.synth.graph import viterbi


def _random_graph(rng, K, p_edge, *, integer):
    dense = rng.random((K, K)) < p_edge
    cost = rng.integers(0, 4, (K, K)).astype(np.float64) if integer else rng.random((K, K)) * 3
    indptr = np.concatenate([[0], np.cumsum(dense.sum(1))]).astype(np.int64)
    rows, cols = np.nonzero(dense)  # row-major: targets increasing within a row
    return indptr, cols.astype(np.int64), cost[rows, cols].astype(np.float64), dense, cost


def _brute(unary, dense, cost, w_data, w_trans):
    """Every path; the best by exact cost, ties broken as the DP breaks them.

    The DP keeps the smallest final node and, walking back, the smallest predecessor
    among exact ties: that is the optimal path whose reversed node sequence is smallest.
    """
    n, K = unary.shape
    best = None
    for path in itertools.product(range(K), repeat=n):
        if any(not dense[a, b] for a, b in zip(path[:-1], path[1:])):
            continue
        if not np.all(np.isfinite(unary[np.arange(n), path])):
            continue
        c = w_data * sum(unary[i, d] for i, d in enumerate(path)) + w_trans * sum(
            cost[a, b] for a, b in zip(path[:-1], path[1:]))
        key = (c, tuple(reversed(path)))
        if best is None or key < best:
            best = key
    return best


@pytest.mark.parametrize("integer", [True, False])
def test_viterbi_matches_brute_force(integer):
    rng = np.random.default_rng(1 if integer else 2)
    checked = infeasible = 0
    for _trial in range(300):
        K = int(rng.integers(1, 5))
        n = int(rng.integers(1, 5))
        indptr, indices, ec, dense, cost = _random_graph(rng, K, rng.uniform(0.2, 0.9), integer=integer)
        unary = (rng.integers(0, 3, (n, K)).astype(np.float64) if integer else rng.random((n, K)) * 2)
        unary[rng.random((n, K)) < 0.25] = np.inf  # clips some nodes may not play
        w_data, w_trans = (1.0, 2.0) if integer else (float(rng.random()), float(rng.random()))
        best = _brute(unary, dense, cost, w_data, w_trans)
        if best is None:
            infeasible += 1
            with pytest.raises(SearchError, match="target clip"):
                viterbi(unary, indptr, indices, ec, w_data=w_data, w_trans=w_trans)
            continue
        path, c = viterbi(unary, indptr, indices, ec, w_data=w_data, w_trans=w_trans)
        assert path.dtype == np.int64 and path.shape == (n,)
        if integer:  # exact arithmetic: the tie rule decides the path
            assert c == best[0]
            assert tuple(reversed(path.tolist())) == best[1]
        else:
            assert c == pytest.approx(best[0], rel=1e-12, abs=1e-12)
            assert tuple(reversed(path.tolist())) == best[1]
        checked += 1
    assert checked > 100 and infeasible > 5


def test_ties_prefer_smallest_nodes():
    # complete graph on 3 nodes, all costs equal: every path ties; smallest final, smallest predecessors
    K, n = 3, 4
    indptr = np.arange(0, K * K + 1, K, dtype=np.int64)
    indices = np.tile(np.arange(K, dtype=np.int64), K)
    ec = np.ones(K * K)
    unary = np.zeros((n, K))
    unary[:, 0] = np.inf  # node 0 forbidden everywhere: node 1 must win every tie
    path, c = viterbi(unary, indptr, indices, ec)
    assert path.tolist() == [1, 1, 1, 1] and c == 3.0


def test_unreachable_clip_is_named():
    indptr = np.array([0, 1, 1], dtype=np.int64)  # 0 -> 0 only; node 1 has no out-edge
    indices = np.array([0], dtype=np.int64)
    ec = np.array([0.5])
    unary = np.array([[np.inf, 0.0], [0.0, 0.0], [np.inf, np.inf]])
    with pytest.raises(SearchError, match="clip 1: no edge"):
        viterbi(unary, indptr, indices, ec)
    unary = np.array([[0.0, 0.0], [0.0, 0.0], [np.inf, np.inf]])
    with pytest.raises(SearchError, match="clip 2: no allowed node"):
        viterbi(unary, indptr, indices, ec)


def test_single_clip_is_best_node():
    unary = np.array([[3.0, 1.0, 1.0, 2.0]])
    path, c = viterbi(unary, np.zeros(5, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
    assert path.tolist() == [1] and c == 1.0


def test_bad_inputs_are_named():
    indptr = np.array([0, 1], dtype=np.int64)
    indices = np.array([0], dtype=np.int64)
    ec = np.array([1.0])
    with pytest.raises(ParameterError, match="unary: expected float64"):
        viterbi(np.zeros((2, 1), dtype=np.float32), indptr, indices, ec)
    with pytest.raises(ParameterError, match="indptr: expected shape"):
        viterbi(np.zeros((2, 2)), indptr, indices, ec)
    with pytest.raises(ParameterError, match="edge_cost: expected finite"):
        viterbi(np.zeros((2, 1)), indptr, indices, np.array([np.inf]))
    with pytest.raises(ParameterError, match="w_trans"):
        viterbi(np.zeros((2, 1)), indptr, indices, ec, w_trans=-1)
    with pytest.raises(ParameterError, match="strictly increasing"):
        viterbi(np.zeros((2, 1)), np.array([0, 2], dtype=np.int64), np.array([0, 0], dtype=np.int64), np.ones(2))
    with pytest.raises(ParameterError, match="unary: expected finite values or"):
        viterbi(np.full((2, 1), np.nan), indptr, indices, ec)
