"""Felzenszwalb merging in Boruvka rounds, on graphs small enough to reason about."""

from __future__ import annotations

import numpy as np

from shared.perception.segmenters.graph import Edges, absorb_small, felzenszwalb


def _chain(weights):
    n = len(weights) + 1
    a = np.arange(n - 1)
    return n, Edges.sorted(a, a + 1, np.asarray(weights, float))


def test_a_strong_edge_splits_a_chain():
    n, edges = _chain([0.01] * 9 + [1.0] + [0.02] * 9)
    part = felzenszwalb(n, edges, k=0.1)
    assert len(part.size) == 2
    assert (part.label[:10] == part.label[0]).all() and (part.label[10:] == part.label[10]).all()
    assert part.label[0] != part.label[10]
    assert part.size.sum() == n


def test_larger_k_merges_more():
    n, edges = _chain([0.01] * 9 + [1.0] + [0.02] * 9)
    assert len(felzenszwalb(n, edges, k=100.0).size) == 1


def test_absorb_small_joins_only_the_small_component():
    # Three groups: 8 nodes | 2 nodes | 8 nodes, the small one closer to the right group.
    n, edges = _chain([0.01] * 7 + [1.0] + [0.01] + [0.5] + [0.01] * 7)
    part = felzenszwalb(n, edges, k=0.05)
    assert sorted(part.size.tolist()) == [2, 8, 8]
    merged = absorb_small(part, edges, min_size=3)
    assert sorted(merged.size.tolist()) == [8, 10]
    assert merged.label[8] == merged.label[17] != merged.label[0]


def test_grid_with_two_halves():
    h, w = 12, 16
    node = np.arange(h * w).reshape(h, w)
    colour = np.zeros((h, w))
    colour[:, 8:] = 1.0
    a = np.concatenate([node[:, :-1].ravel(), node[:-1, :].ravel()])
    b = np.concatenate([node[:, 1:].ravel(), node[1:, :].ravel()])
    flat = colour.ravel()
    rng = np.random.default_rng(0)
    weights = np.abs(flat[a] - flat[b]) + rng.uniform(0, 0.02, len(a))
    part = felzenszwalb(h * w, Edges.sorted(a, b, weights), k=2.0)
    labels = part.label.reshape(h, w)
    assert len(np.unique(labels[:, :8])) == 1 and len(np.unique(labels[:, 8:])) == 1
    assert labels[0, 0] != labels[0, -1]
