"""Top-down PNG renders: size, content, the hit boxes, the query sheet, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from test_recording import BOXES, make_hits, make_snapshot, make_trajectory

from services.viewer import render
from shared.messages.graph import GraphSnapshot


def _rgb(path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).astype(int)


def _hit_red(img: np.ndarray) -> np.ndarray:
    """Pixels of the hit colour (#e00000), give or take anti-aliasing."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 190) & (g < 50) & (b < 50)


def test_map_png_size_and_content(tmp_path):
    out = render.render_map_png(make_snapshot(), tmp_path / "map.png", trajectory=make_trajectory(), title="test map")
    assert out == tmp_path / "map.png"
    img = _rgb(out)
    assert img.shape == (1125, 1650, 3)  # 11 x 7.5 in at 150 dpi
    assert img.std() > 20, "the render is blank"
    colours = {tuple(c) for c in img[::7, ::7].reshape(-1, 3)}
    assert len(colours) > 50
    assert [p.name for p in tmp_path.iterdir()] == ["map.png"], "no temporary file may be left"


def test_hit_boxes_are_red_where_the_hit_is(tmp_path):
    snap, traj = make_snapshot(), make_trajectory()
    base = _rgb(render.render_map_png(snap, tmp_path / "a.png", trajectory=traj))
    hits = make_hits(ids=(0,))  # segment 0: bottom-left of the 6 x 4 m room
    lit = _rgb(render.render_map_png(snap, tmp_path / "b.png", trajectory=traj, hits=hits, query_text="red chair"))
    new = _hit_red(lit) & ~_hit_red(base)
    # Within the plot (the legend with its red swatch sits right of the axes).
    left = new[:, : int(0.6 * new.shape[1])]
    ys, xs = np.nonzero(left)
    assert len(ys) > 300, "no thick red box"
    plot_rows, plot_cols = np.nonzero((base[:, : left.shape[1]] != 255).any(axis=-1))
    # Segment 0 spans x 0.5-1.5 of 0-6 m and y 0.5-1.5 of 0-4 m: left and low in the plot.
    assert np.median(xs) < np.median(plot_cols)
    assert np.median(ys) > np.median(plot_rows)


def test_auto_view_finds_the_up_axis():
    traj = make_trajectory()
    assert render.choose_view("auto", traj).up == 2
    y_up = traj[:, [0, 2, 1]]  # height along y
    assert render.choose_view("auto", y_up).up == 1
    assert render.choose_view("auto", None).up == 2
    assert render.choose_view("-y", None).sign == -1.0


def test_y_up_world_renders(tmp_path):
    snap = make_snapshot()
    swap = [0, 2, 1]
    mesh = snap.mesh.model_copy(update={"vertices": np.ascontiguousarray(snap.mesh.vertices[:, swap])})
    snap = snap.model_copy(update={"mesh": mesh, "places": [], "rooms": [], "edges": []})
    out = render.render_map_png(snap, tmp_path / "y.png", trajectory=make_trajectory()[:, swap], up="auto")
    assert _rgb(out).std() > 20


def test_empty_graph_renders(tmp_path):
    out = render.render_map_png(GraphSnapshot(graph_seq=0, frame_index=-1), tmp_path / "e.png", hits=[])
    assert _rgb(out).shape == (1125, 1650, 3)
    sheet = render.render_query_sheet(GraphSnapshot(graph_seq=0, frame_index=-1), tmp_path / "s.png", {})
    assert sheet.is_file()


@pytest.mark.parametrize(("n", "size"), [(2, (1380, 675)), (7, (2070, 1275))])
def test_query_sheet_grid(tmp_path, n, size):
    queries = {f"query {k}": make_hits(ids=(k % len(BOXES), (k + 1) % len(BOXES))) for k in range(n)}
    out = render.render_query_sheet(make_snapshot(), tmp_path / "sheet.png", queries, trajectory=make_trajectory())
    with Image.open(out) as im:
        assert im.size == size
    img = _rgb(out)
    assert _hit_red(img).sum() > 300 * min(n, render.MAX_SHEET_PANELS)


def test_raster_has_no_holes_on_a_surface():
    snap = make_snapshot()
    img, extent = render.top_raster(snap.mesh.vertices, snap.mesh.segment_ids, render.choose_view("z", None), cell=0.12)
    assert img is not None and extent[1] > extent[0]
    assert (img[..., 3] > 0).mean() > 0.95
