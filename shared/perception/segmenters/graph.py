"""Felzenszwalb-Huttenlocher graph segmentation with whole-array numpy steps.

Kruskal's order (the original algorithm) needs a Python loop over every edge, far too slow for
a 160x120 graph at frame rate. Here merging runs in Boruvka rounds: each component looks at its
cheapest edge to another component at once and merges across it when the Felzenszwalb
predicate holds,

    w <= min(Int(A) + k / |A|, Int(B) + k / |B|),

with Int the largest edge weight merged inside a component so far. Plain Boruvka loses
Kruskal's global order, and that matters: in the first round every pixel is alone and its
tolerance ``k`` is at its largest, so chains of cheapest edges would run down the colour ramp
of a blurred silhouette and fuse the two sides. The rounds therefore run level by level over
geometrically growing weight limits (ratio ``LEVEL_RATIO``), a coarse Kruskal order: edges of
one level only compete once everything cheaper has had its chance to grow the regions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

MAX_ROUNDS = 200
"""Safety bound per level: each round at least halves the components that can still merge."""
LEVEL_RATIO = 1.25
"""Growth of the weight limit from one level to the next (finer is closer to Kruskal, slower)."""
MIN_LEVEL_FRAC = 1e-4
"""The first level takes every edge up to this share of the heaviest one."""


@dataclass
class Partition:
    """Components of a graph's nodes and what the predicate needs to know about them."""

    label: Annotated[np.ndarray, "(V,) int64 component of each node, 0 .. C-1"]
    size: Annotated[np.ndarray, "(C,) int64 nodes per component"]
    internal: Annotated[np.ndarray, "(C,) float64 largest edge weight merged inside"]

    @staticmethod
    def singletons(n_nodes: int) -> Partition:
        return Partition(np.arange(n_nodes), np.ones(n_nodes, np.int64), np.zeros(n_nodes))


@dataclass
class Edges:
    """Undirected weighted edges, sorted by weight (cheapest first)."""

    a: Annotated[np.ndarray, "(E,) int64 node"]
    b: Annotated[np.ndarray, "(E,) int64 node"]
    w: Annotated[np.ndarray, "(E,) float weight"]

    @staticmethod
    def sorted(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> Edges:
        # Stable, so equal weights keep their input order and results never depend on the sort.
        order = np.argsort(w, kind="stable")
        return Edges(a[order].astype(np.int64), b[order].astype(np.int64), w[order])


def _cheapest_outgoing(
    ca: np.ndarray, cb: np.ndarray, n_comp: int
) -> Annotated[np.ndarray, "(C,) int64 index of the cheapest edge leaving each component, E if none"]:
    n_edges = len(ca)
    first = np.full(n_comp, n_edges, np.int64)
    idx = np.arange(n_edges, dtype=np.int64)
    # Edges are sorted by weight, so the smallest index touching a component is its cheapest edge.
    np.minimum.at(first, ca, idx)
    np.minimum.at(first, cb, idx)
    return first


def _join(n: int, u: np.ndarray, v: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of n nodes joined by edges (u, v): their count and a compact label
    per node. Hooking and pointer jumping, whole-array steps only; a few passes suffice for the
    shallow trees a merge round builds."""
    parent = np.arange(n)
    while True:
        pu, pv = parent[u], parent[v]
        differ = pu != pv
        if not differ.any():
            break
        lo = np.minimum(pu[differ], pv[differ])
        np.minimum.at(parent, np.maximum(pu[differ], pv[differ]), lo)
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
    is_root = parent == np.arange(n)
    compact = np.cumsum(is_root) - 1
    return int(is_root.sum()), compact[parent]


def _merge(part: Partition, ca: np.ndarray, cb: np.ndarray, w: np.ndarray, chosen: np.ndarray) -> Partition:
    """Merge the components joined by the ``chosen`` edges (indices into ca, cb, w)."""
    u, v = ca[chosen], cb[chosen]
    n_new, relabel = _join(len(part.size), u, v)
    size = np.bincount(relabel, weights=part.size, minlength=n_new).astype(np.int64)
    internal = np.zeros(n_new)
    np.maximum.at(internal, relabel, part.internal)
    np.maximum.at(internal, relabel[u], w[chosen])
    return Partition(relabel[part.label], size, internal)


def _rounds(part: Partition, edges: Edges, accept, limit: float = np.inf) -> tuple[Partition, Edges]:
    """Boruvka rounds over the edges no heavier than ``limit``: each component proposes its
    cheapest such edge to another component and ``accept(own, other, w, part, n_ext)`` says
    which proposals merge (``n_ext``: edges considered on each component's boundary). Returns
    the partition and the edges still between components, in order."""
    n_in = int(np.searchsorted(edges.w, limit, side="right"))
    a, b, w = edges.a[:n_in], edges.b[:n_in], edges.w[:n_in]
    for _ in range(MAX_ROUNDS):
        ca, cb = part.label[a], part.label[b]
        ext = ca != cb
        a, b, w, ca, cb = a[ext], b[ext], w[ext], ca[ext], cb[ext]
        if len(w) == 0:
            break
        n_comp = len(part.size)
        first = _cheapest_outgoing(ca, cb, n_comp)
        own = np.flatnonzero(first < len(w))
        e = first[own]
        other = np.where(ca[e] == own, cb[e], ca[e])
        n_ext = np.bincount(ca, minlength=n_comp) + np.bincount(cb, minlength=n_comp)
        chosen = e[accept(own, other, w[e], part, n_ext)]
        if len(chosen) == 0:
            break
        part = _merge(part, ca, cb, w, chosen)
    rest = Edges(
        np.concatenate([a, edges.a[n_in:]]), np.concatenate([b, edges.b[n_in:]]), np.concatenate([w, edges.w[n_in:]])
    )
    return part, rest


def felzenszwalb(n_nodes: int, edges: Edges, k: float) -> Partition:
    """Components under the Felzenszwalb predicate with scale ``k`` (in weight x nodes)."""

    def accept(own, other, w, part, n_ext):
        limit = np.minimum(
            part.internal[own] + k / part.size[own], part.internal[other] + k / part.size[other]
        )
        return w <= limit

    part = Partition.singletons(n_nodes)
    if len(edges.w) == 0:
        return part
    top = float(edges.w[-1])
    level = max(top * MIN_LEVEL_FRAC, 1e-12)
    while len(edges.w):
        last = level >= top
        part, edges = _rounds(part, edges, accept, np.inf if last else level)
        if last:
            break
        level *= LEVEL_RATIO
    return part


def absorb_small(part: Partition, edges: Edges, min_size: int, min_width: float = 0.0, edges_per_node: int = 2) -> Partition:
    """Merge every component smaller than ``min_size`` nodes, or thinner than ``min_width``,
    into the neighbour across its cheapest edge (Felzenszwalb's post-processing, plus slivers),
    until none is left or none has a neighbour.

    Width is ``edges_per_node * size / boundary edges``: a strip w nodes wide has width w and
    an s x s square s / 2, with ``edges_per_node`` 2 for a 4-neighbour grid and 6 for an
    8-neighbour one. Slivers are the mixed pixels along a silhouette; they form their own thin
    regions because they differ from both sides.
    """
    if min_size <= 1 and min_width <= 0:
        return part

    # Only small components propose: were a large one's proposal into a small neighbour taken
    # too, two large components could fuse through the small one in a single round.
    def accept(own, other, w, part, n_ext):
        width = edges_per_node * part.size[own] / np.maximum(n_ext[own], 1)
        return (part.size[own] < min_size) | (width < min_width)

    return _rounds(part, edges, accept)[0]


def boundary_contrast(
    part: Partition, edges: Edges
) -> Annotated[np.ndarray, "(C,) float64 mean weight of the edges on each component's boundary"]:
    ca, cb = part.label[edges.a], part.label[edges.b]
    ext = ca != cb
    n = len(part.size)
    total = np.bincount(ca[ext], weights=edges.w[ext], minlength=n) + np.bincount(
        cb[ext], weights=edges.w[ext], minlength=n
    )
    count = np.bincount(ca[ext], minlength=n) + np.bincount(cb[ext], minlength=n)
    return np.divide(total, count, out=np.zeros(n), where=count > 0)
