"""Long-term re-identification of revisited segments against historical ones (paper III-E).

Once a segment leaves the active window its surface is re-meshed from fresh vertices that
carry no hypotheses of its old tracks, so the active-window matching of III-D cannot see the
revisit. Here an active query segment q is compared with the historical segments h whose
centroids lie within ``search_radius_m`` (the set H_q) by

    o_qh = |{x in S_q : min_y in S_h ||x - y|| <= r_nn}| / |S_q|          (eq. 8)
    J_qh = lambda_o * o_qh + lambda_a * cos(f_q, f_h)                     (eq. 9)

and merged into the candidate with the largest J_qh among those passing all three gates.
The paper does not say how near a centroid must be to enter H_q; ``search_radius_m`` (2 m)
is this project's choice.
The segment bookkeeping of a merge lives in ``segments.SegmentLayer``; this module only scores.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.spatial import cKDTree

from shared.config.fusion import ReidConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReidMatch:
    """An accepted association of query ``query`` with historical segment ``target``."""

    query: int
    target: int
    overlap: float
    """o_qh (eq. 8)."""
    cosine: float
    """cos(f_q, f_h) of the aggregated DINOv3 features."""
    score: float
    """J_qh (eq. 9)."""


def unit(v: Annotated[np.ndarray, "(D,) float"]) -> Annotated[np.ndarray, "(D,) float64"]:
    """``v`` scaled to unit length (a zero vector stays zero, so every cosine with it is 0)."""
    v = np.asarray(v, np.float64)
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def within(
    points: Annotated[np.ndarray, "(N, 3) float"], tree: cKDTree, radius: float
) -> Annotated[np.ndarray, "(N,) bool"]:
    """Which points have a tree point at distance <= ``radius`` (inclusive, as eq. 8 states)."""
    out = np.zeros(len(points), bool)
    if len(points) == 0 or tree.n == 0:
        return out
    # Only points in the tree's box grown by the radius can have a neighbour; a large query
    # segment mostly lies outside a small historical one, so this skips most tree walks.
    near = np.all((points >= tree.mins - radius) & (points <= tree.maxes + radius), axis=1)
    if not near.any():
        return out
    # cKDTree.query bounds strictly (d < bound); nudging the bound up one ulp makes it d <= r.
    d, _ = tree.query(points[near], k=1, distance_upper_bound=float(np.nextafter(radius, np.inf)))
    out[near] = np.isfinite(d)
    return out


def overlap_fraction(
    query_points: Annotated[np.ndarray, "(Nq, 3) float"], target_tree: cKDTree, r_nn: float
) -> float:
    """o_qh of eq. 8: the fraction of query points within ``r_nn`` of any target point."""
    if len(query_points) == 0:
        return 0.0
    return float(np.count_nonzero(within(query_points, target_tree, r_nn))) / len(query_points)


def combined_score(overlap: float, cosine: float, cfg: ReidConfig) -> float:
    """J_qh of eq. 9."""
    return cfg.lambda_o * overlap + cfg.lambda_a * cosine


def accepts(overlap: float, cosine: float, score: float, cfg: ReidConfig) -> bool:
    """All three gates of IV-A: o >= o_min, cos >= cos_min and J >= j_min."""
    return overlap >= cfg.o_min and cosine >= cfg.cos_min and score >= cfg.j_min


def best_match(
    query: int,
    query_points: Annotated[np.ndarray, "(Nq, 3) float"],
    query_dino: Annotated[np.ndarray, "(D,) float"],
    candidates: Sequence[int],
    dino_of: Callable[[int], np.ndarray],
    tree_of: Callable[[int], cKDTree],
    cfg: ReidConfig,
) -> ReidMatch | None:
    """The accepted candidate of largest J_qh, or None; ties go to the smaller id.

    The cosine gate, and the best J the candidate could still reach with o = 1, are checked
    before the vertex overlap, since eq. 8 needs a nearest-neighbour query per query vertex
    and most nearby historical segments fail on appearance alone.
    """
    fq = unit(query_dino)
    best: ReidMatch | None = None
    for h in sorted(candidates):
        cos = float(fq @ unit(dino_of(h)))
        if cos < cfg.cos_min or combined_score(1.0, cos, cfg) < cfg.j_min:
            continue
        o = overlap_fraction(query_points, tree_of(h), cfg.r_nn)
        j = combined_score(o, cos, cfg)
        log.debug("reid %d -> %d: o=%.3f cos=%.3f J=%.3f", query, h, o, cos, j)
        if accepts(o, cos, j, cfg) and (best is None or j > best.score):
            best = ReidMatch(query, h, o, cos, j)
    return best
