"""Ground truth in the OpenLex3D layout: a labelled point cloud sampled on object surfaces,
the per-object label tiers with clutter ids, the prompt list and the query-to-objects map.

Points are sampled uniformly by area on every part's triangles, then points on faces nobody
can see are dropped: a point is kept when a step of ``PROBE`` along its outward normal lands in
a room's free air (inside a room or doorway, between floor and ceiling, and outside every
solid part). That removes the backs of walls, the bottoms of objects standing on something
and the faces where parts interpenetrate. Finally only points that some frame actually saw
are kept (:func:`observed_in`), as in a reconstructed dataset's ground truth: a surface the
camera never looked at cannot be mapped, so it must not count against a map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from shared.synth import kernels
from shared.synth.primitives import contains, world_mesh
from shared.synth.textures import MaterialTable, albedo
from shared.synth.vocabulary import STRUCTURAL
from shared.synth.world import World

PROBE = 0.008
"""Step along the normal used to decide whether a surface point faces free air (m)."""
GRID = 0.25
"""Cell (m) of the xy grid that finds each part's candidate probes in :func:`_in_air`."""
SEEN_TOL = 0.02
"""A frame sees a point whose depth is within this (m, plus 1% of the depth) of its pixel's."""


@dataclass
class GroundTruthCloud:
    points: Annotated[np.ndarray, "(N, 3) float32"]
    labels: Annotated[np.ndarray, "(N,) int32 object id"]
    colors: Annotated[np.ndarray, "(N, 3) uint8 unlit albedo"]


def _sample_part(v: np.ndarray, f: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(2 * area, 1e-12)[:, None]
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    pts = a[tri] + r1[:, None] * (b[tri] - a[tri]) + r2[:, None] * (c[tri] - a[tri])
    return pts, normals[tri]


def _in_air(world: World, probes: Annotated[np.ndarray, "(N, 3)"]) -> Annotated[np.ndarray, "(N,) bool"]:
    layout = world.layout
    t = layout.wall_thickness
    x, y, z = probes[:, 0], probes[:, 1], probes[:, 2]
    inside = np.zeros(len(probes), bool)
    rects = [r.inner(t) for r in layout.rooms] + [d.passage(t) for d in layout.doors]
    for x0, y0, x1, y1 in rects:
        inside |= (x > x0) & (x < x1) & (y > y0) & (y < y1)
    inside &= (z > 0) & (z < layout.wall_height)
    solid = np.zeros(len(probes), bool)
    use_kernel = kernels.ENABLED and probes.dtype == np.float64 and len(probes) > 0
    if use_kernel:
        # Candidates per part come from a grid in xy (GRID m cells); each part's are then put
        # in the order the numpy path's sort on x gives them (x, then index), so that
        # ``contains`` sees the very same arrays.
        probes = np.ascontiguousarray(probes)
        origin = probes[:, :2].min(axis=0)
        nx, ny = (np.floor((probes[:, :2].max(axis=0) - origin) / GRID).astype(np.int64) + 1).tolist()
        cell_start = np.zeros(nx * ny + 1, np.int64)
        members = np.empty(len(probes), np.int64)
        kernels.grid_points(probes, origin, GRID, nx, ny, cell_start, members)
        scratch = np.empty(len(probes), np.int64)
    else:
        # Candidates per part come from a sort on x, so each part tests only nearby points.
        order = np.argsort(x, kind="stable")
        xs = x[order]
    for o in world.objects:
        for part in o.parts:
            v, _ = world_mesh(part)
            lo, hi = v.min(axis=0), v.max(axis=0)
            if use_kernel:
                cand = scratch[:kernels.in_box(probes, cell_start, members, origin, GRID, nx, ny, lo, hi, scratch)]
                cand = cand[np.lexsort((cand, probes[cand, 0]))]
                pc = probes[cand]
            else:
                a, b = np.searchsorted(xs, lo[0]), np.searchsorted(xs, hi[0], side="right")
                if a >= b:
                    continue
                cand = order[a:b]
                pc = probes[cand]
                box = np.all((pc >= lo) & (pc <= hi), axis=1)
                cand, pc = cand[box], pc[box]
            if len(cand) == 0:
                continue
            inv = np.linalg.inv(part.pose)
            local = pc @ inv[:3, :3].T + inv[:3, 3]
            solid[cand[contains(part, local)]] = True
    return inside & ~solid


def sample_cloud(world: World, keep: set[int], spacing: float, seed: int, textures: bool = True) -> GroundTruthCloud:
    """Points on the visible surfaces of the objects in ``keep`` (about one per spacing^2)."""
    parts, owner = world.parts()
    table = MaterialTable.from_parts(parts)
    pts_all, nrm_all, lab_all, part_all = [], [], [], []
    base = 0
    for o in world.objects:
        if o.id not in keep:
            base += len(o.parts)
            continue
        rng = np.random.default_rng([seed, 7, o.id])
        for k, part in enumerate(o.parts):
            v, f = world_mesh(part)
            a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
            area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
            n = max(1, int(round(area / spacing**2)))
            p, nr = _sample_part(v, f, n, rng)
            pts_all.append(p)
            nrm_all.append(nr)
            lab_all.append(np.full(n, o.id, np.int32))
            part_all.append(np.full(n, base + k, np.int64))
        base += len(o.parts)
    if not pts_all:
        return GroundTruthCloud(np.zeros((0, 3), np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.uint8))
    pts, nrm = np.vstack(pts_all), np.vstack(nrm_all)
    labels, part_idx = np.concatenate(lab_all), np.concatenate(part_all)
    visible = _in_air(world, pts + PROBE * nrm)
    # An object seen in the frames keeps at least its raw samples if the probe test drops all.
    present = np.zeros(len(world.objects), bool)
    present[labels[visible]] = True
    visible |= ~present[labels]
    pts, labels, part_idx = pts[visible], labels[visible], part_idx[visible]
    local = table.to_local(part_idx, pts)
    colors = np.clip(np.rint(albedo(table, part_idx, local, textures) * 255), 0, 255).astype(np.uint8)
    return GroundTruthCloud(pts.astype(np.float32), labels, colors)


def observed_in(
    points: Annotated[np.ndarray, "(N, 3) float32 world"],
    depth_m: Annotated[np.ndarray, "(H, W) float metres, 0 = none"],
    K,
    T_world_cam: Annotated[np.ndarray, "(4, 4)"],
    tol_m: float = SEEN_TOL,
) -> Annotated[np.ndarray, "(M,) int64 indices of points this frame sees"]:
    """Points that project inside the image and agree with the rendered depth there."""
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    cam = (points - t) @ R
    z = cam[:, 2]
    front = np.flatnonzero(z > 0.05)
    u = np.floor(cam[front, 0] / z[front] * K.fx + K.cx + 0.5).astype(np.int64)
    v = np.floor(cam[front, 1] / z[front] * K.fy + K.cy + 0.5).astype(np.int64)
    h, w = depth_m.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    front, u, v = front[inside], u[inside], v[inside]
    d = depth_m[v, u]
    seen = (d > 0) & (np.abs(z[front] - d) < tol_m + 0.01 * d)
    return front[seen]


CHUNK_SIZE = 0.5
"""Edge (m) of the cubes :class:`PointChunks` groups an object's points by."""


@dataclass
class PointChunks:
    """A cloud's point indices grouped by object and, within one, by :data:`CHUNK_SIZE` cube,
    with each group's bounding box: a frame skips the groups it cannot see at all (most of a
    wall's or a floor's points are outside any one view)."""

    @property
    def bounds(self) -> Annotated[np.ndarray, "(objects + 1,) int64: object o's points are order[bounds[o]:bounds[o + 1]]"]:
        return self.chunk_start[self.object_chunks]

    order: Annotated[np.ndarray, "(N,) int64 point indices"]
    object_chunks: Annotated[np.ndarray, "(objects + 1,) int64: object o's chunks are object_chunks[o]:object_chunks[o + 1]"]
    chunk_start: Annotated[np.ndarray, "(C + 1,) int64: chunk c's points are order[chunk_start[c]:chunk_start[c + 1]]"]
    lo: Annotated[np.ndarray, "(C, 3) float64 chunk box"]
    hi: Annotated[np.ndarray, "(C, 3) float64"]


def point_chunks(points: Annotated[np.ndarray, "(N, 3) float32 world"], labels: Annotated[np.ndarray, "(N,) int object id"],
                 n_objects: int) -> PointChunks:
    """Group ``points`` by object id (0 to ``n_objects`` - 1) and cube (see :class:`PointChunks`)."""
    n = len(points)
    if n == 0:
        empty = np.zeros(n_objects + 1, np.int64)
        return PointChunks(np.zeros(0, np.int64), empty, np.zeros(1, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    cell = np.floor(points / np.float32(CHUNK_SIZE)).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    key = ((labels.astype(np.int64) * span[0] + cell[:, 0]) * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key = key[order]
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    chunk_start = np.append(starts, n).astype(np.int64)
    object_chunks = np.searchsorted(labels[order[starts]], np.arange(n_objects + 1)).astype(np.int64)
    grouped = points[order].astype(np.float64)
    return PointChunks(order.astype(np.int64), object_chunks, chunk_start,
                       np.minimum.reduceat(grouped, starts), np.maximum.reduceat(grouped, starts))


def observed_objects(
    points: Annotated[np.ndarray, "(N, 3) float32 world"],
    chunks: PointChunks,
    shown: Annotated[np.ndarray, "(S,) int64 object ids"],
    depth_m: Annotated[np.ndarray, "(H, W) float32 metres, 0 = none"],
    K,
    T_world_cam: Annotated[np.ndarray, "(4, 4)"],
) -> Annotated[np.ndarray, "(M,) int64 indices into points"]:
    """:func:`observed_in` over the points of the objects in ``shown`` (those a frame's pixels
    show; ``chunks`` from :func:`point_chunks`): the indices of those it sees, in no
    particular order."""
    shown = np.asarray(shown, np.int64)
    order, bounds = chunks.order, chunks.bounds
    if not (kernels.ENABLED and points.dtype == np.float32 and depth_m.dtype == np.float32):
        cand = np.concatenate([order[bounds[o]:bounds[o + 1]] for o in shown]) if len(shown) else np.zeros(0, np.int64)
        return cand[observed_in(points[cand], depth_m, K, T_world_cam)]
    n = int((bounds[shown + 1] - bounds[shown]).sum())
    seen = np.empty(n, np.int64)
    unsure = np.empty(n, np.int64)
    n_seen, n_unsure = kernels.observed_points(
        np.ascontiguousarray(points), order, chunks.object_chunks, chunks.chunk_start, chunks.lo, chunks.hi,
        shown, np.ascontiguousarray(depth_m), np.ascontiguousarray(T_world_cam[:3, :3], np.float64),
        np.ascontiguousarray(T_world_cam[:3, 3], np.float64), float(K.fx), float(K.fy), float(K.cx), float(K.cy),
        np.float32(SEEN_TOL), seen, unsure,
    )
    seen = seen[:n_seen]
    if n_unsure:
        # Points within rounding of an edge: numpy's own projection decides them.
        unsure = unsure[:n_unsure]
        seen = np.concatenate([seen, unsure[observed_in(points[unsure], depth_m, K, T_world_cam)]])
    return seen


def keep_observed(cloud: GroundTruthCloud, observed: Annotated[np.ndarray, "(N,) bool"], keep: set[int]) -> GroundTruthCloud:
    """Points of the objects in ``keep`` that some frame saw. An object seen only in pixels
    too few to catch a sample keeps its raw samples, so every kept object has points."""
    mine = np.isin(cloud.labels, np.fromiter(keep, np.int64, len(keep)))
    m = mine & observed
    lacking = np.setdiff1d(np.unique(cloud.labels[mine]), np.unique(cloud.labels[m]))
    m |= mine & np.isin(cloud.labels, lacking)
    return GroundTruthCloud(cloud.points[m], cloud.labels[m], cloud.colors[m])


def categories_json(world: World, keep: set[int], clutter: dict[int, list[int]], name: str) -> dict:
    """``gt_categories.json`` as OpenLex3D reads it: ``dataset.samples[*]`` with ``object_id``,
    ``name`` and ``labels.image_attributes.{synonyms, depictions, vis_sim, clutter}`` (clutter
    ids as strings, as OpenLex3D's clutter adder writes them)."""
    samples = []
    for o in world.objects:
        if o.id not in keep:
            continue
        samples.append({
            "object_id": o.id,
            "name": o.category,
            "room": o.room,
            "labels": {"image_attributes": {
                "synonyms": list(o.labels.synonyms),
                "depictions": list(o.labels.depictions),
                "vis_sim": list(o.labels.vis_sim),
                "clutter": [str(j) for j in clutter[o.id] if j in keep],
            }},
        })
    return {"name": name, "dataset": {"samples": samples}}


def query_mapping(world: World, keep: set[int]) -> dict[str, dict[str, list[int]]]:
    """OpenLex3D's query file: ``{"level0": {synonym: [object ids]}}``; the room shell is
    excluded, as in OpenLex3D."""
    mapping: dict[str, list[int]] = {}
    for o in world.objects:
        if o.id not in keep or o.category in STRUCTURAL:
            continue
        for s in o.labels.synonyms:
            mapping.setdefault(s, []).append(o.id)
    return {"level0": {k: sorted(v) for k, v in sorted(mapping.items())}}
