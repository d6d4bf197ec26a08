"""``MAP_DIR/rooms.npz``: round trip, atomic write, and errors that name the file and field."""

from __future__ import annotations

import io

import numpy as np
import pytest

import shared.io
from shared.graph import roomgrid
from shared.graph.roomgrid import RoomGrid, RoomGridError, load_room_grid, save_room_grid


def _grid(names: list[str] | None = None) -> RoomGrid:
    rng = np.random.default_rng(3)
    labels = rng.choice(np.array([-1, 4, 9], np.int32), size=(7, 5)).astype(np.int32)
    return RoomGrid(labels=labels, origin=np.array([-1.25, 0.5]), resolution=0.05, room_ids=np.array([4, 9], np.int64),
                    names=["kitchen", "hall"] if names is None else names)  # fmt: skip


def _raw(grid: RoomGrid, **changes) -> bytes:
    """An .npz with the fields of ``grid``, some replaced (None: left out)."""
    fields = {
        "format": np.array(roomgrid.FORMAT), "version": np.array(roomgrid.VERSION, np.int64), "labels": grid.labels,
        "origin": grid.origin, "resolution": np.array(grid.resolution), "room_ids": grid.room_ids,
        "names": np.array(grid.names or [""] * len(grid.room_ids)),
    }  # fmt: skip
    fields.update(changes)
    buf = io.BytesIO()
    np.savez(buf, **{k: v for k, v in fields.items() if v is not None})
    return buf.getvalue()


def test_round_trip(tmp_path):
    grid = _grid()
    path = save_room_grid(tmp_path / "map" / "rooms.npz", grid)
    back = load_room_grid(path)
    assert back.labels.dtype == np.int32 and back.room_ids.dtype == np.int64 and back.origin.dtype == np.float64
    np.testing.assert_array_equal(back.labels, grid.labels)
    np.testing.assert_array_equal(back.room_ids, grid.room_ids)
    np.testing.assert_array_equal(back.origin, grid.origin)
    assert back.resolution == 0.05 and back.names == ["kitchen", "hall"]
    assert back.name_of(9) == "hall"
    # cell (i, j) covers [origin + i * res, origin + (i + 1) * res): its centre is half a cell in
    np.testing.assert_allclose(back.centers()[2, 3], [-1.25 + 2.5 * 0.05, 0.5 + 3.5 * 0.05])
    np.testing.assert_array_equal(back.cell_counts(), [(grid.labels == 4).sum(), (grid.labels == 9).sum()])


def test_integer_arrays_of_another_width_are_taken_when_they_fit(tmp_path):
    grid = RoomGrid(labels=np.array([[-1, 2], [7, 2]], np.int64), origin=[0, 0], resolution=0.1, room_ids=np.array([2, 7], np.int32))
    back = load_room_grid(save_room_grid(tmp_path / "rooms.npz", grid))
    assert back.labels.dtype == np.int32 and back.room_ids.dtype == np.int64
    np.testing.assert_array_equal(back.labels, [[-1, 2], [7, 2]])
    too_big = RoomGrid(labels=np.array([[2**40]], np.int64), origin=[0, 0], resolution=0.1, room_ids=np.array([2**40]))
    with pytest.raises(RoomGridError, match="labels: expected an \\(H, W\\) int32 array, got int64"):
        save_room_grid(tmp_path / "big.npz", too_big)


def test_unnamed_rooms_load_with_no_names(tmp_path):
    path = save_room_grid(tmp_path / "rooms.npz", _grid(names=[]))
    back = load_room_grid(path)
    assert back.names == [] and back.name_of(4) == ""


def test_write_is_atomic(tmp_path, monkeypatch):
    path = save_room_grid(tmp_path / "rooms.npz", _grid())
    before = path.read_bytes()

    def disk_full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    # The write dies after the bytes went to the temporary file, before the rename.
    monkeypatch.setattr(shared.io.os, "fsync", disk_full)
    with pytest.raises(OSError, match="No space"):
        save_room_grid(path, _grid(names=["a", "b"]))
    assert path.read_bytes() == before, "a failed write leaves the previous file"
    assert [p.name for p in tmp_path.iterdir()] == ["rooms.npz"], "no temporary file left behind"


@pytest.mark.parametrize(
    "change, field",
    [
        ({"labels": np.zeros((3, 3), np.int64)}, "labels"),
        ({"labels": np.zeros(4, np.int32)}, "labels"),
        ({"labels": np.full((2, 2), 5, np.int32)}, "labels: ids [5]"),
        ({"origin": np.zeros(3)}, "origin"),
        ({"origin": np.zeros(2, np.float32)}, "origin"),
        ({"resolution": np.array(-0.05)}, "resolution"),
        ({"resolution": np.array([0.05, 0.05])}, "resolution"),
        ({"room_ids": np.array([4, 9], np.int32)}, "room_ids"),
        ({"room_ids": np.array([4, 4], np.int64)}, "room_ids"),
        ({"names": np.array(["only one"])}, "names"),
        ({"format": np.array("something else")}, "format"),
        ({"version": np.array(99)}, "version"),
        ({"room_ids": None}, "missing keys ['room_ids']"),
    ],
)
def test_bad_files_name_the_file_and_field(tmp_path, change, field):
    path = tmp_path / "rooms.npz"
    path.write_bytes(_raw(_grid(), **change))
    with pytest.raises(RoomGridError, match=str(path)) as err:
        load_room_grid(path)
    assert field in str(err.value)


def test_unreadable_or_missing_file(tmp_path):
    path = tmp_path / "rooms.npz"
    with pytest.raises(RoomGridError, match="no such room grid file"):
        load_room_grid(path)
    path.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(RoomGridError, match="not a readable .npz"):
        load_room_grid(path)


def test_save_refuses_a_bad_grid(tmp_path):
    bad = RoomGrid(labels=np.zeros((2, 2), np.int32), origin=np.zeros(2), resolution=0.1, room_ids=np.array([1], np.int64))
    with pytest.raises(RoomGridError, match="labels: ids \\[0\\]"):
        save_room_grid(tmp_path / "rooms.npz", bad)
    assert not (tmp_path / "rooms.npz").exists()
