"""What Hydra's own tools derive and we write for them: the 2D place outlines with Hydra's
ellipse, a room's box from its places, the place each camera pose passed, and the derived
edges (odometry, place -> agent, room - room, outline - outline)."""

from __future__ import annotations

from typing import Annotated

import numpy as np
import spark_dsg as sd

from shared.graph.dsg.layout import KEY_AGENT, KEY_PLACE, KEY_PLACE_2D, KEY_ROOM
from shared.messages.graph import GraphSnapshot, PlaceNode


def place_2d(p: PlaceNode, color: np.ndarray) -> sd.Place2dNodeAttributes:
    a = sd.Place2dNodeAttributes()
    a.position = np.asarray(p.position, np.float64)
    z = float(p.position[2])
    a.boundary = [np.array([x, y, z], np.float64) for x, y in p.boundary]
    a.is_active = bool(p.active)
    a.color = color
    ellipse = _hydra_ellipse(p.boundary)
    if ellipse is not None:
        centre, expand, compress = ellipse
        a.ellipse_centroid = np.array([centre[0], centre[1], z], np.float64)
        a.ellipse_matrix_expand = expand
        a.ellipse_matrix_compress = compress
    else:
        a.ellipse_centroid = np.array([p.position[0], p.position[1], z], np.float64)
        a.ellipse_matrix_expand = np.zeros((2, 2))
        a.ellipse_matrix_compress = np.zeros((2, 2))
    return a


def _convex_hull(xy: Annotated[np.ndarray, "(N, 2)"]) -> Annotated[np.ndarray, "(H, 2) counter-clockwise"] | None:
    """The outline's convex hull (qhull), None where it has no area."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(xy, np.float64)
    if pts.shape[0] < 3:
        return None
    try:
        return pts[ConvexHull(pts).vertices]
    except QhullError:  # collinear or repeated points
        return None


def _hydra_ellipse(
    xy: Annotated[np.ndarray, "(B, 2)"],
) -> tuple[Annotated[np.ndarray, "(2,)"], Annotated[np.ndarray, "(2, 2)"], Annotated[np.ndarray, "(2, 2)"]] | None:
    """Hydra's 2D-place ellipse (``addRectInfo``, scale factor 1): the minimum-area rectangle of
    the outline, ``expand`` = sqrt(2)/2 * [side1 side2] as columns, ``compress`` =
    inv(expand)^T inv(expand); None for an outline of no area."""
    hull = _convex_hull(xy)
    if hull is None:
        return None
    edges = np.roll(hull, -1, axis=0) - hull
    lengths = np.linalg.norm(edges, axis=1)
    keep = lengths > 0
    u = edges[keep] / lengths[keep, None]
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    pu, pv = hull @ u.T, hull @ v.T  # (H, E): the hull projected on each edge's axes
    du, dv = pu.max(0) - pu.min(0), pv.max(0) - pv.min(0)
    best = int(np.argmin(du * dv))
    if du[best] * dv[best] <= 1e-12:
        return None
    cu, cv = (pu[:, best].max() + pu[:, best].min()) / 2, (pv[:, best].max() + pv[:, best].min()) / 2
    centre = u[best] * cu + v[best] * cv
    expand = np.sqrt(2.0) / 2.0 * np.stack([u[best] * du[best], v[best] * dv[best]], axis=1)
    inv = np.linalg.inv(expand)
    return centre, expand, inv.T @ inv


def box_of_places(places: list[PlaceNode]) -> tuple[np.ndarray, np.ndarray] | None:
    """A room's box from its places: xy from their outlines (their free-space discs where none
    has one), z from their heights +- their free-space radius."""
    if not places:
        return None
    outlines = [p.boundary for p in places if p.boundary.shape[0]]
    if outlines:
        xy = np.concatenate(outlines)
        xy_lo, xy_hi = xy.min(0), xy.max(0)
    else:
        pos, rad = np.array([p.position[:2] for p in places]), np.array([p.radius for p in places])[:, None]
        xy_lo, xy_hi = (pos - rad).min(0), (pos + rad).max(0)
    z = np.array([p.position[2] for p in places])
    rad = np.array([p.radius for p in places])
    return np.r_[xy_lo, (z - rad).min()], np.r_[xy_hi, (z + rad).max()]


def _inside(points: Annotated[np.ndarray, "(N, 2)"], polygon: Annotated[np.ndarray, "(B, 2)"]) -> Annotated[np.ndarray, "(N,) bool"]:
    """Even-odd point-in-polygon test of each point."""
    x, y = points[:, :1], points[:, 1:2]
    xi, yi = polygon[:, 0][None], polygon[:, 1][None]
    xj, yj = np.roll(polygon[:, 0], 1)[None], np.roll(polygon[:, 1], 1)[None]
    crosses = (yi > y) != (yj > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = (xj - xi) * (y - yi) / (yj - yi) + xi
    return (np.count_nonzero(crosses & (x < x_at), axis=1) % 2) == 1


def agent_places(
    snap: GraphSnapshot, chunk: int = 2048
) -> Annotated[np.ndarray, "(M,) int64 place id per trajectory row, -1 without places"]:
    """The place each trajectory pose passed: the nearest (3D) place whose outline contains the
    pose's xy, else the nearest place."""
    traj = snap.trajectory
    out = np.full(traj.shape[0], -1, np.int64)
    if not snap.places or traj.shape[0] == 0:
        return out
    pos = traj[:, :3]
    ids = np.array([p.id for p in snap.places], np.int64)
    centres = np.array([p.position for p in snap.places], np.float64)
    best_d = np.full(traj.shape[0], np.inf)
    outlined = [p for p in snap.places if p.boundary.shape[0] >= 3]
    lo = np.array([p.boundary.min(0) for p in outlined]).reshape(-1, 2)
    hi = np.array([p.boundary.max(0) for p in outlined]).reshape(-1, 2)
    # Poses within each outline's box, found for all outlines at once, chunk by chunk.
    hits: list[list[np.ndarray]] = [[] for _ in outlined]
    for s in range(0, traj.shape[0], chunk):
        xy = pos[s : s + chunk, None, :2]
        rows, cols = np.nonzero(np.all((xy >= lo[None]) & (xy <= hi[None]), axis=2))
        if cols.size == 0:
            continue  # no pose of this chunk within any outline's box
        order = np.argsort(cols, kind="stable")
        uniq, start = np.unique(cols[order], return_index=True)
        for j, grp in zip(uniq, np.split(rows[order] + s, start[1:]), strict=True):
            hits[j].append(grp)
    for p, found in zip(outlined, hits, strict=True):
        if not found:
            continue
        cand = np.concatenate(found)
        cand = cand[_inside(pos[cand, :2], p.boundary)]
        d = np.linalg.norm(pos[cand] - p.position, axis=1)
        closer = d < best_d[cand]
        best_d[cand[closer]] = d[closer]
        out[cand[closer]] = p.id
    rest = np.flatnonzero(out < 0)
    if rest.size:
        from scipy.spatial import cKDTree

        out[rest] = ids[cKDTree(centres).query(pos[rest])[1]]
    return out


def derived_edges(g: sd.DynamicSceneGraph, snap: GraphSnapshot, place_room: dict[int, int]) -> None:
    sym = sd.NodeSymbol
    with_outline = {p.id for p in snap.places if p.boundary.shape[0]}
    for e in snap.edges:
        if e.kind != "place_place":
            continue
        if e.source in with_outline and e.target in with_outline:
            g.insert_edge(sym(KEY_PLACE_2D, e.source), sym(KEY_PLACE_2D, e.target))
        ra, rb = place_room.get(e.source), place_room.get(e.target)
        if ra is not None and rb is not None and ra != rb and g.has_node(sym(KEY_ROOM, ra)) and g.has_node(sym(KEY_ROOM, rb)):
            g.insert_edge(sym(KEY_ROOM, ra), sym(KEY_ROOM, rb))
    for k in range(1, snap.trajectory.shape[0]):
        g.insert_edge(sym(KEY_AGENT, k - 1), sym(KEY_AGENT, k))
    for k, pid in enumerate(agent_places(snap)):
        if pid >= 0:
            # The place is the parent, one per agent, as Hydra's LayerConnector inserts it.
            g.insert_edge(sym(KEY_PLACE, int(pid)), sym(KEY_AGENT, k), True)
