"""Top-down PNG renders of a map, with query hits, for reports and headless checks.

Matplotlib's object API with the Agg canvas (no pyplot, no screen, no global state), so
renders work on a robot or in CI and from several threads. Colours come from
:func:`services.viewer.recording.segment_colors`, so a segment looks the same here and in
the Rerun recording.

The view looks down the world's up axis. The synthetic scenes and the dataset readers use a
z-up world (``shared.synth.trajectory``: "the world is z up"); ``up="auto"`` guesses the up
axis from the trajectory instead (a walking or driving camera varies least in height), for
worlds from other conventions.
"""

from __future__ import annotations

import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from matplotlib import patheffects
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from services.viewer.recording import edge_lines, segment_colors
from shared.io import atomic_write_bytes
from shared.messages.graph import GraphSnapshot
from shared.messages.rpc import QueryHit

log = logging.getLogger(__name__)

Up = Literal["z", "y", "-y", "x", "auto"]
Trajectory = Annotated[np.ndarray, "(N, 3) float camera positions"]

DPI = 150
HIT_COLOR = "#e00000"
TRAJ_COLOR = "#202020"
"""Near-black: segment colours are saturated hues, so the path never blends into a wall."""
PLACE_COLOR = "#2060d0"
MAX_SHEET_PANELS = 6
SHEET_HITS = 3
_OUTLINE = [patheffects.withStroke(linewidth=2.5, foreground="white")]
_THIN_OUTLINE = [patheffects.withStroke(linewidth=3.0, foreground="white", alpha=0.8)]


@dataclass(frozen=True)
class View:
    """Which world axes are drawn horizontally (a, b) and which one is height."""

    a: int
    b: int
    up: int
    sign: float
    """+1 if height grows along ``up``, -1 if the world is "down" along it (y down)."""

    @property
    def labels(self) -> tuple[str, str]:
        return "xyz"[self.a] + " [m]", "xyz"[self.b] + " [m]"

    def label_axes(self, ax, fontsize: float) -> None:
        """Name the plot's horizontal and vertical axes after the world axes drawn."""
        ax.set_xlabel(self.labels[0], fontsize=fontsize)
        ax.set_ylabel(self.labels[1], fontsize=fontsize)


_VIEWS = {"z": View(0, 1, 2, 1.0), "x": View(1, 2, 0, 1.0), "y": View(2, 0, 1, 1.0), "-y": View(0, 2, 1, -1.0)}


def choose_view(up: Up, trajectory: Trajectory | None) -> View:
    """The top-down view for ``up``; ``auto`` takes the trajectory axis that varies least,
    if it clearly varies least (else z, the project's convention)."""
    if up != "auto":
        return _VIEWS[up]
    t = None if trajectory is None else np.asarray(trajectory, np.float64).reshape(-1, 3)
    if t is None or len(t) < 10:
        return _VIEWS["z"]
    ext = np.ptp(t, axis=0)
    order = np.argsort(ext)
    if ext[order[0]] >= 0.5 * ext[order[1]]:
        return _VIEWS["z"]
    return _VIEWS[{0: "x", 1: "y", 2: "z"}[int(order[0])]]


def _height_cut(h: np.ndarray, traj_h: np.ndarray | None) -> float:
    """Height above which vertices are dropped, so a ceiling does not hide the room.

    With a trajectory: 0.8 m above the camera. Without: just under a ceiling, recognised as
    many vertices close to the top; no cut if there is none.
    """
    if traj_h is not None and traj_h.size:
        return float(np.median(traj_h) + 0.8)
    if not h.size:
        return math.inf
    top = float(np.percentile(h, 99.5))
    if np.mean(h > top - 0.1) > 0.05:
        return top - 0.15
    return math.inf


def top_raster(
    vertices: Annotated[np.ndarray, "(V, 3) float"],
    segment_ids: Annotated[np.ndarray, "(V,) int"],
    view: View,
    max_height: float = math.inf,
    cell: float | None = None,
) -> tuple[Annotated[np.ndarray, "(H, W, 4) float32 RGBA"] | None, tuple[float, float, float, float]]:
    """The mesh seen from above as an image: each cell shows its highest vertex (below
    ``max_height``) in its segment's colour, paled near the floor so objects stand out.
    ``cell`` (m) should be a little over the vertex spacing, so a surface has no holes;
    by default 4 cm, over the spacing of a 3 cm TSDF mesh.

    A raster rather than a scatter: scattered vertices leave a dotted moire at any marker
    size, and a raster costs the same for any number of vertices.
    """
    v = np.asarray(vertices, np.float64)
    h = v[:, view.up] * view.sign
    keep = np.isfinite(v).all(axis=1) & (h <= max_height)
    v, h, ids = v[keep], h[keep], np.asarray(segment_ids)[keep]
    if not len(v):
        return None, (0.0, 1.0, 0.0, 1.0)
    a, b = v[:, view.a], v[:, view.b]
    lo = np.array([a.min(), b.min()])
    ext = float(max(np.ptp(a), np.ptp(b), 1e-6))
    cell = max(ext / 1200.0, 0.04 if cell is None else float(cell))
    ia = ((a - lo[0]) / cell).astype(np.int64)
    ib = ((b - lo[1]) / cell).astype(np.int64)
    w, hgt = int(ia.max()) + 1, int(ib.max()) + 1
    flat = ib * w + ia
    order = np.lexsort((h, flat))  # by cell, then height: the last of each cell is the top
    last = np.r_[flat[order][1:] != flat[order][:-1], True]
    top = order[last]
    floor = float(np.percentile(h, 1))
    rgb = segment_colors(ids[top]).astype(np.float32) / 255.0
    pale = np.clip(1.0 - (h[top] - floor) / 0.3, 0.0, 1.0)[:, None] * 0.55
    rgb = rgb * (1 - pale) + pale
    img = np.zeros((hgt * w, 4), np.float32)
    img[flat[top], :3] = rgb
    img[flat[top], 3] = 1.0
    img = _fill_holes(img.reshape(hgt, w, 4))
    extent = (lo[0], lo[0] + w * cell, lo[1], lo[1] + hgt * cell)
    return img, extent


def _vertex_spacing(mesh) -> float:
    """Median edge length of (a sample of) the mesh faces; 3 cm without faces."""
    f = mesh.faces[:20000]
    if not f.size:
        return 0.03
    v = mesh.vertices.astype(np.float64)
    e = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1)
    med = float(np.median(e))
    return med if np.isfinite(med) and med > 0 else 0.03


def _fill_holes(img: np.ndarray) -> np.ndarray:
    """Fill empty cells that have filled neighbours on both sides (gaps between vertices)."""
    alpha = img[..., 3] > 0
    out = img.copy()
    for axis in (0, 1):
        prev = np.roll(img, 1, axis=axis)
        nxt = np.roll(img, -1, axis=axis)
        hole = ~alpha & (prev[..., 3] > 0) & (nxt[..., 3] > 0) & (out[..., 3] == 0)
        out[hole] = prev[hole]
    return out


def _draw_base(ax, snapshot: GraphSnapshot, trajectory: Trajectory | None, view: View, *, small: bool = False) -> None:
    traj = None if trajectory is None else np.asarray(trajectory, np.float64).reshape(-1, 3)
    traj = None if traj is None else traj[np.isfinite(traj).all(axis=1)]
    mesh = snapshot.mesh
    if mesh is not None and mesh.vertices.shape[0]:
        cut = _height_cut(
            mesh.vertices[:, view.up].astype(np.float64) * view.sign,
            None if traj is None else traj[:, view.up] * view.sign,
        )
        img, extent = top_raster(mesh.vertices, mesh.segment_ids, view, cut, _vertex_spacing(mesh) * 1.25)
        if img is not None:
            ax.imshow(img, extent=extent, origin="lower", interpolation="nearest", zorder=1)
    lines = edge_lines(snapshot)["place_place"]
    for p, q in lines:
        ax.plot([p[view.a], q[view.a]], [p[view.b], q[view.b]], color=PLACE_COLOR, lw=0.6, alpha=0.6, zorder=3)
    if snapshot.places:
        pp = np.array([p.position for p in snapshot.places])
        ax.scatter(pp[:, view.a], pp[:, view.b], s=6 if small else 12, color=PLACE_COLOR, edgecolors="white", linewidths=0.4, zorder=4)
    if traj is not None and len(traj) >= 2:
        ax.plot(traj[:, view.a], traj[:, view.b], color=TRAJ_COLOR, lw=1.0 if small else 1.6, zorder=5, path_effects=_THIN_OUTLINE)
        ax.plot(traj[0, view.a], traj[0, view.b], "o", color=TRAJ_COLOR, ms=4 if small else 6, mec="white", zorder=6)
    for r in snapshot.rooms:
        name = f"room {r.id}" + (f" {r.name}" if r.name else "")
        ax.text(
            r.centroid[view.a], r.centroid[view.b], name, fontsize=6 if small else 9, ha="center", va="center",
            color="#0b5a2a", weight="bold", zorder=7,
            bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "#0b5a2a", "lw": 0.6, "alpha": 0.85},
        )  # fmt: skip
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3, alpha=0.4, zorder=0)
    ax.set_axisbelow(True)


def _draw_hits(ax, hits: list[QueryHit], view: View, *, small: bool = False) -> None:
    for rank, hit in enumerate(hits, start=1):
        lo, hi = hit.bbox_min, hit.bbox_max
        pad = 0.04
        x0, y0 = lo[view.a] - pad, lo[view.b] - pad
        w, h = hi[view.a] - lo[view.a] + 2 * pad, hi[view.b] - lo[view.b] + 2 * pad
        ax.add_patch(
            Rectangle((x0, y0), w, h, fill=False, ec=HIT_COLOR, lw=2.0 if small else 3.0, zorder=8, path_effects=_OUTLINE)
        )
        ax.text(
            x0, y0 + h, str(rank), fontsize=7 if small else 11, weight="bold", color="white", ha="center", va="center", zorder=9,
            bbox={"boxstyle": "circle,pad=0.2", "fc": HIT_COLOR, "ec": "white", "lw": 0.8},
        )  # fmt: skip


def _hit_legend(ax, hits: list[QueryHit], query_text: str | None) -> None:
    handles: list = [
        Patch(fill=False, ec=HIT_COLOR, lw=2.5, label=f"#{i} seg {h.segment}  score {h.score:.3f}"
              + ("" if h.room is None else f"  room {h.room}"))
        for i, h in enumerate(hits, start=1)
    ]  # fmt: skip
    title = f"query: \u201c{query_text}\u201d" if query_text else "query hits"
    ax.add_artist(
        ax.legend(handles=handles, title=title, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, title_fontsize=10)
    )


def _frame_legend(ax) -> None:
    handles = [
        Line2D([], [], color=TRAJ_COLOR, lw=1.6, label="camera path (dot: start)"),
        Line2D([], [], color=PLACE_COLOR, lw=0.8, marker="o", ms=4, label="places, traversable edges"),
        Line2D([], [], ls="none", marker="s", ms=5, color="#808080", label="mesh (colour: segment; grey: none)"),
    ]
    ax.legend(handles=handles, loc="lower left", bbox_to_anchor=(1.01, 0.0), fontsize=8, title="map", title_fontsize=9)


def _save(fig: Figure, out_png: Path) -> Path:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return atomic_write_bytes(Path(out_png), buf.getvalue())


def _summary(snapshot: GraphSnapshot) -> str:
    return f"graph {snapshot.graph_seq}: {len(snapshot.segments)} segments, {len(snapshot.places)} places, {len(snapshot.rooms)} rooms"


def render_map_png(
    snapshot: GraphSnapshot,
    out_png: Path,
    *,
    trajectory: Trajectory | None = None,
    hits: list[QueryHit] | None = None,
    title: str = "",
    query_text: str | None = None,
    up: Up = "z",
) -> Path:
    """A top-down render of the map, with the hits of one query boxed and ranked."""
    view = choose_view(up, trajectory)
    fig = Figure(figsize=(11, 7.5), layout="constrained")
    ax = fig.add_subplot()
    _draw_base(ax, snapshot, trajectory, view)
    if hits:
        _draw_hits(ax, hits, view)
        _hit_legend(ax, hits, query_text)
    _frame_legend(ax)
    view.label_axes(ax, 10)
    ax.set_title(title or _summary(snapshot), fontsize=12)
    return _save(fig, out_png)


def render_query_sheet(
    snapshot: GraphSnapshot,
    out_png: Path,
    queries: dict[str, list[QueryHit]],
    trajectory: Trajectory | None = None,
    *,
    up: Up = "z",
    title: str = "",
) -> Path:
    """One small top-down panel per query (the first six), each with its top hits."""
    items = list(queries.items())[:MAX_SHEET_PANELS]
    if len(queries) > MAX_SHEET_PANELS:
        log.info("query sheet shows %d of %d queries", MAX_SHEET_PANELS, len(queries))
    view = choose_view(up, trajectory)
    n = max(len(items), 1)
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(4.6 * cols, 4.0 * rows + 0.5), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    for k, ax in enumerate(axes.flat):
        if k >= len(items):
            ax.set_axis_off()
            if not items:
                ax.text(0.5, 0.5, "no queries", ha="center", va="center", transform=ax.transAxes, fontsize=12)
            continue
        text, hits = items[k]
        top = hits[:SHEET_HITS]
        _draw_base(ax, snapshot, trajectory, view, small=True)
        _draw_hits(ax, top, view, small=True)
        scores = ", ".join(f"#{i} {h.score:.2f}" for i, h in enumerate(top, start=1)) or "no hits"
        ax.set_title(f"\u201c{text}\u201d\n{scores}", fontsize=9)
        ax.tick_params(labelsize=7)
        view.label_axes(ax, 7)
    fig.suptitle(title or _summary(snapshot), fontsize=11)
    return _save(fig, out_png)


def render_map_pictures(
    snapshot: GraphSnapshot,
    out_dir: Path,
    queries: dict[str, list[QueryHit]],
    trajectory: Trajectory | None = None,
    *,
    up: Up = "z",
) -> list[Path]:
    """``map.png``, ``query_<i>.png`` for each query and, with queries, ``queries.png``:
    the pictures of ``trackgraph view --png`` and of the demo."""
    out_dir = Path(out_dir)
    title = f"{len(snapshot.segments)} segments, {len(snapshot.rooms)} rooms"
    paths = [render_map_png(snapshot, out_dir / "map.png", trajectory=trajectory, title=title, up=up)]
    for i, (text, hits) in enumerate(queries.items()):
        paths.append(render_map_png(snapshot, out_dir / f"query_{i}.png", trajectory=trajectory, hits=hits, query_text=text, title=f"query: {text}", up=up))
    if queries:
        paths.append(render_query_sheet(snapshot, out_dir / "queries.png", queries, trajectory, up=up))
    return paths
