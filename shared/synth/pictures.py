"""Overview pictures of a generated sequence: a contact sheet of frames and a top-down map.

Figures are drawn on matplotlib ``Figure`` objects directly (no pyplot, so no global backend
state) and saved without the software tag, so the same inputs give byte-identical PNGs.
"""

from __future__ import annotations

import io
from typing import Annotated

import numpy as np

from shared.synth.trajectory import Trajectory
from shared.synth.world import World

PNG_META = {"Software": None}


def instance_colors(n: int) -> Annotated[np.ndarray, "(n, 3) uint8; row 0 (no object) is black"]:
    """A fixed random colour per instance value (object id + 1)."""
    rng = np.random.default_rng(12345)
    colors = rng.integers(40, 256, size=(max(n, 1), 3)).astype(np.uint8)
    colors[0] = 0
    return colors


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata=PNG_META)
    return buf.getvalue()


def contact_sheet(frames: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]], depth_max: float, n_ids: int) -> bytes:
    """PNG of rows (RGB, colour-mapped depth, instance ids) for ``(index, rgb, depth_m,
    instances)`` tuples; instances as written (0 = none, else object id + 1)."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    depth_cmap = colormaps["turbo"].with_extremes(bad="black")
    rows = len(frames)
    h, w = frames[0][1].shape[:2]
    aspect = h / w
    fig = Figure(figsize=(3 * 3.6, rows * 3.6 * aspect + 0.6), dpi=110)
    fig.suptitle("Synthetic sequence: RGB, depth (m) and instance ids of sampled frames", fontsize=10)
    palette = instance_colors(n_ids + 1)
    for r, (idx, rgb, depth, inst) in enumerate(frames):
        ax = fig.add_subplot(rows, 3, 3 * r + 1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_title(f"frame {idx:06d}: RGB", fontsize=8)
        ax.axis("off")
        ax = fig.add_subplot(rows, 3, 3 * r + 2)
        shown = np.where(depth > 0, depth, np.nan)
        im = ax.imshow(shown, cmap=depth_cmap, vmin=0.0, vmax=depth_max, interpolation="nearest")
        ax.set_title(f"frame {idx:06d}: depth (black: no reading)", fontsize=8)
        ax.axis("off")
        cb = fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02)
        cb.ax.tick_params(labelsize=6)
        ax = fig.add_subplot(rows, 3, 3 * r + 3)
        ax.imshow(palette[np.clip(inst, 0, len(palette) - 1)], interpolation="nearest")
        ax.set_title(f"frame {idx:06d}: {len(np.unique(inst[inst > 0]))} instances", fontsize=8)
        ax.axis("off")
    fig.subplots_adjust(left=0.01, right=0.97, top=0.93, bottom=0.01, wspace=0.12, hspace=0.18)
    return _png(fig)


def topdown(world: World, traj: Trajectory, title: str) -> bytes:
    """PNG map: rooms, walls, doorways, object footprints with categories, and the walk."""
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    layout = world.layout
    bx0, by0, bx1, by1 = layout.bounds()
    width = 13.0
    # The map axes take about 70% of the width (colour bar and legend on the right).
    height = float(np.clip(0.7 * width * (by1 - by0 + 0.6) / (bx1 - bx0 + 0.6) + 1.4, 4.5, 14.0))
    fig = Figure(figsize=(width, height), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    cats = sorted({o.category for o in world.objects if not o.structural})
    cmap = colormaps["tab20"]
    color = {c: cmap(i % 20) for i, c in enumerate(cats)}

    for room in layout.rooms:
        x0, y0, x1, y1 = room.inner(layout.wall_thickness)
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor="#f4f1ea", edgecolor="none", zorder=0))
        ax.text(x0 + 0.08, y1 - 0.08, f"{room.name} ({room.kind})", fontsize=8, va="top", ha="left",
                color="#444444", style="italic", zorder=11,
                bbox={"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": "none", "alpha": 0.8})
    for o in world.objects:
        if o.category != "wall":
            continue
        for p in o.parts:
            c, half = p.pose[:3, 3], np.abs(p.pose[:3, :3]) @ (np.asarray(p.dims) / 2)
            ax.add_patch(Rectangle((c[0] - half[0], c[1] - half[1]), 2 * half[0], 2 * half[1],
                                   facecolor="#3a3a3a" if c[2] - half[2] < 0.01 else "#9a9a9a", edgecolor="none", zorder=3))
    for d in layout.doors:
        x0, y0, x1, y1 = d.passage(layout.wall_thickness)
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, facecolor="#2ca02c", edgecolor="none", zorder=4))

    order = {"flat": 1, "floor": 2, "wall": 4, "item": 5}
    for o in sorted((o for o in world.objects if not o.structural), key=lambda o: (order[o.mount], o.id)):
        x0, y0 = o.lo[:2]
        w, h = (o.hi - o.lo)[:2]
        col = color[o.category]
        if o.mount == "flat":
            ax.add_patch(Rectangle((x0, y0), w, h, facecolor=col, alpha=0.18, edgecolor=col, linestyle="--", lw=1, zorder=1))
        elif o.mount == "item":
            ax.add_patch(Rectangle((x0, y0), w, h, facecolor=col, edgecolor="black", lw=0.3, zorder=5))
        else:
            ax.add_patch(Rectangle((x0, y0), w, h, facecolor=col, alpha=0.55, edgecolor="black", lw=0.6, zorder=2 if o.mount == "floor" else 4))
        big = o.mount in ("floor", "flat", "wall")
        cx, cy = (o.lo[:2] + o.hi[:2]) / 2
        if o.mount == "flat":
            # A rug lies under furniture whose label sits at the centre: label its corner.
            cx, cy = o.lo[0] + 0.05, o.lo[1] + 0.05
        ax.text(cx, cy, o.category, fontsize=6.5 if big else 4.5, ha="left" if o.mount == "flat" else "center",
                va="bottom" if o.mount == "flat" else "center", zorder=7, color="black", alpha=0.9 if big else 0.75)

    pos = traj.positions[:, :2]
    seg = np.stack([pos[:-1], pos[1:]], axis=1)
    lc = LineCollection(seg, cmap="viridis", linewidths=2.0, zorder=8)
    lc.set_array(np.arange(len(seg), dtype=float))
    ax.add_collection(lc)
    cb = fig.colorbar(lc, ax=ax, fraction=0.025, pad=0.01)
    cb.set_label("frame index")
    step = max(1, len(pos) // 40)
    fwd = traj.poses[::step, :2, 2]
    fwd = fwd / np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-9)
    ax.quiver(pos[::step, 0], pos[::step, 1], fwd[:, 0], fwd[:, 1], color="#d62728", scale=28, width=0.0025, zorder=9)
    ax.plot(*pos[0], marker="o", color="#2ca02c", markersize=9, markeredgecolor="black", zorder=10)
    ax.plot(*pos[-1], marker="s", color="#d62728", markersize=8, markeredgecolor="black", zorder=10)

    ax.set_xlim(bx0 - 0.3, bx1 + 0.3)
    ax.set_ylim(by0 - 0.3, by1 + 0.3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.set_title(title, fontsize=11)
    handles = [
        Patch(facecolor="#3a3a3a", label="wall"),
        Patch(facecolor="#9a9a9a", label="lintel over doorway"),
        Patch(facecolor="#2ca02c", label="doorway"),
        Patch(facecolor="#bbbbbb", edgecolor="black", alpha=0.55, label="furniture footprint"),
        Patch(facecolor="#bbbbbb", edgecolor="#888888", linestyle="--", alpha=0.3, label="rug"),
        Patch(facecolor="#bbbbbb", edgecolor="black", label="small object"),
        Line2D([], [], color="#440154", lw=2, label="camera path (colour: frame)"),
        Line2D([], [], color="#d62728", marker=r"$\rightarrow$", lw=0, markersize=10, label="view direction"),
        Line2D([], [], color="#2ca02c", marker="o", lw=0, markeredgecolor="black", label="start"),
        Line2D([], [], color="#d62728", marker="s", lw=0, markeredgecolor="black", label="end"),
    ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.08, 1.0), fontsize=7, frameon=True)
    fig.subplots_adjust(left=0.05, right=0.8, top=1 - 0.5 / height, bottom=0.7 / height)
    return _png(fig)
