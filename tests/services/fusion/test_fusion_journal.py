"""fusion's write-ahead journal: records read back as written, a torn tail (a crash mid-write,
cut at seeded random bytes) loses only the torn record and says so, damage inside a file is
skipped, snapshots cut and prune it, a fusion session abandoned without closing (as a
SIGKILL leaves it) resumes with every frame and feature message it acknowledged, and a
frame's record is written beside its fusion (the writer thread) yet on disk before its ack."""

from __future__ import annotations

import logging
import os
import threading
import time

import numpy as np
import pytest

from services.fusion.durability.journal import FILE_MAGIC, HEADER, Journal, ReplayStats, read_file
from shared.config.fusion import JournalConfig
from shared.graph.store import MapStore
from shared.messages.frames import EndOfSequence, FrameAck, TrackedFrame
from shared.messages.keyframes import TrackFeature, TrackFeatures
from tests.services.conftest import tiny_frame
from tests.services.fusion.test_fusion_session import FakeFusion, Rig


def tracked(i: int, h: int = 12, w: int = 16) -> TrackedFrame:
    fr = tiny_frame(i, h, w)
    rng = np.random.default_rng(i)
    fr = fr.model_copy(update={"rgb": rng.integers(0, 256, (h, w, 3), np.uint8), "depth": rng.integers(500, 3000, (h, w)).astype(np.uint16)})
    ids = rng.integers(-1, 4, (h, w)).astype(np.int32)
    return TrackedFrame(frame=fr, track_ids=ids, tracks=[])


def features(i: int, serial: int | None = None) -> TrackFeatures:
    return TrackFeatures(frame_index=i, tracks=[TrackFeature(track_id=i, dino=np.full(4, i, np.float32))], serial=serial)


def write(tmp_path, n: int = 12) -> tuple[Journal, list[int]]:
    """``n`` records, frames and feature messages alternating, the last an end; returns the
    journal and each record's end offset."""
    j = Journal(tmp_path / "journal", JournalConfig())
    j.reset()
    ends = []
    for i in range(n - 1):
        j.append("frame", tracked(i)) if i % 2 == 0 else j.append("features", features(i, serial=i))
        ends.append(j.bytes)
    j.append("end", EndOfSequence(frames_published=n, frames_dropped=0, last_frame_index=n))
    ends.append(j.bytes)
    j.close()
    return j, ends


def test_records_read_back_as_written(tmp_path):
    j, ends = write(tmp_path)
    records, stats = j.replay(None)
    assert [r.kind for r in records] == ["frame", "features"] * 5 + ["frame", "end"]
    assert stats.torn == 0 and stats.records == {"frame": 6, "features": 5, "end": 1}
    got, want = records[4].body, tracked(4)
    np.testing.assert_array_equal(got.frame.rgb, want.frame.rgb)  # lossless, colour included
    np.testing.assert_array_equal(got.frame.depth, want.frame.depth)
    np.testing.assert_array_equal(got.track_ids, want.track_ids)
    assert records[3].body.serial == 3 and records[-1].body.frames_published == 12
    # compressed: the 12x16 frames' labels and depth take less than their raw bytes
    assert ends[0] - len(FILE_MAGIC) < 12 * 16 * (3 + 2 + 4)


@pytest.mark.parametrize("seed", range(6))
def test_a_torn_tail_loses_only_the_torn_record_and_says_so(tmp_path, seed, caplog):
    j, ends = write(tmp_path)
    path = j.path("000000")
    size = path.stat().st_size
    cut = int(np.random.default_rng(seed).integers(len(FILE_MAGIC) + 1, size))
    with open(path, "r+b") as f:
        f.truncate(cut)
    whole = sum(e <= cut for e in ends)
    with caplog.at_level(logging.WARNING, logger="services.fusion.durability.journal"):
        records, stats = j.replay(None)
    assert len(records) == whole
    torn = cut not in ends
    assert stats.torn == int(torn)
    if torn:
        assert stats.torn_bytes == cut - (ends[whole - 1] if whole else len(FILE_MAGIC))
        assert "crash mid-write" in caplog.text and str(path) in caplog.text
    # the file is cut back to its last whole record, and appends go on after it
    assert path.stat().st_size == (ends[whole - 1] if whole else len(FILE_MAGIC))
    j.open("000000")
    j.append("features", features(99, serial=99))
    j.close()
    again, stats = j.replay(None)
    assert len(again) == whole + 1 and stats.torn == 0 and again[-1].body.serial == 99


def test_damage_inside_a_file_skips_that_record_only(tmp_path):
    j, ends = write(tmp_path)
    path = j.path("000000")
    data = bytearray(path.read_bytes())
    data[ends[3] + HEADER.size + 5] ^= 0xFF  # inside record 4's payload
    path.write_bytes(bytes(data))
    stats = ReplayStats()
    records = list(read_file(path, stats, repair=True))
    assert len(records) == len(ends) - 1 and stats.torn == 1 and "checksum mismatch" in stats.reasons[0]
    assert [r.body.frame.frame_index for r in records if r.kind == "frame"][:3] == [0, 2, 6]
    assert path.stat().st_size == len(data)  # not a tail: nothing cut
    # a header wiped out: the reader finds the next record's magic
    data[ends[5] : ends[5] + 4] = b"XXXX"
    path.write_bytes(bytes(data))
    stats = ReplayStats()
    assert len(list(read_file(path, stats))) == len(ends) - 2 and stats.torn == 2 and "no record header" in stats.reasons[1]


def test_not_a_journal_is_skipped_with_the_reason(tmp_path):
    root = tmp_path / "journal"
    root.mkdir()
    (root / "000003.wal").write_bytes(b"garbage, not a journal")
    records, stats = Journal(root, JournalConfig()).replay(None)
    assert records == [] and stats.torn == 1 and "not a TrackGraph journal" in stats.reasons[0]


# ---------------------------------------------------------------- in the fusion session


def stored_rig(clock, tmp_path, **kw) -> Rig:
    store = MapStore(tmp_path / "graph", write_dsg=False)
    rig = Rig(clock, kw.pop("core", None) or FakeFusion(), store=store, out=tmp_path, **kw)
    rig.epochs = []
    rig.through = []
    rig.bus.subscribe(rig.topics.frame_ack, FrameAck, lambda env: (rig.epochs.append(env.body.epoch), rig.through.append(env.body.features_through)))
    return rig


def send_features(rig: Rig, i: int, serial: int) -> None:
    rig.features.put(features(i, serial=serial))
    rig.bus.drain()


def test_an_abandoned_session_resumes_with_everything_it_acknowledged(clock, make_frame, tmp_path, monkeypatch):
    # the fake core has no mesh to export at the end
    monkeypatch.setattr("services.fusion.export.export_map", lambda out, core: None)
    monkeypatch.setattr("services.fusion.export.run_summary", lambda *a, **kw: {})
    rig = stored_rig(clock, tmp_path, epoch=1)
    for i in range(3):
        send_features(rig, i, serial=i)
        rig.frame(make_frame, i)
    rig.tick(11.0)  # a snapshot: the journal is cut
    store = rig.session.store
    assert store.latest_name() == "000001"
    assert rig.session.disk.journal.files() == ["000001"]  # what came before is in the snapshot
    for i in range(3, 6):
        send_features(rig, i, serial=i)
        rig.frame(make_frame, i)
    rig.end.put(EndOfSequence(frames_published=8, frames_dropped=0, last_frame_index=7, track_features_published=8))
    rig.bus.drain()
    assert rig.acks[-1] == 5 and rig.epochs[-1] == 1 and rig.through[-1] == 6
    # SIGKILL: nothing closed, nothing saved

    again = stored_rig(clock, tmp_path, core=FakeFusion(), resume=True, epoch=2)
    s = again.session
    # the snapshot's frames and what the journal held after it
    assert again.core.last_frame_index == 5 and again.core.frames == 6 and again.core.features == [3, 4, 5]
    assert s.disk.replay.records == {"features": 3, "frame": 3, "end": 1} and s.disk.replay.torn == 0
    assert s.features.next == 6 and s.features.in_map == 6
    assert s.ending.end is not None and s.ending.end.last_frame_index == 7
    # the restart announced while nothing comes (the source may wait for fusion)
    again.tick(1.0)
    assert again.acks == [5] and again.epochs == [2] and again.through == [6]
    # the tracker sends again what it kept: duplicates skipped, the rest fused, the map ends
    for i in (4, 5, 6, 7):
        send_features(again, i, serial=i)
        again.frame(make_frame, i)
    assert again.core.features == [3, 4, 5, 6, 7] and s.features.duplicate == 2 and s.duplicates == 2
    assert s.finished.is_set() and (tmp_path / "run.json").is_file()
    d = s.delivery()
    assert d["frames_lost"] == 0 and d["frames_in_map"] == 8 and d["features_in_map"] == 8 and d["journal_replayed"]["frame"] == 3
    again.session.close()


def test_resume_without_a_snapshot_replays_from_the_empty_map(clock, make_frame, tmp_path):
    rig = stored_rig(clock, tmp_path)
    for i in range(4):
        rig.frame(make_frame, i)
    assert rig.session.store.latest_name() is None
    again = stored_rig(clock, tmp_path, resume=True)
    assert again.session.resumed_from is None and again.core.frames == 4 and again.session.disk.replay.records == {"frame": 4}
    again.session.close(save=False)
    # a start without --resume is a new map: the old journal goes
    fresh = stored_rig(clock, tmp_path)
    assert fresh.session.disk.journal.files() == ["000000"] and fresh.session.disk.replay.records == {}
    assert list(fresh.session.disk.journal.replay(None)[0]) == []


def test_a_torn_frame_at_resume_is_counted_and_sent_again(clock, make_frame, tmp_path):
    rig = stored_rig(clock, tmp_path)
    for i in range(3):
        rig.frame(make_frame, i)
    path = rig.session.disk.journal.path("000000")
    with open(path, "r+b") as f:
        f.truncate(path.stat().st_size - 3)  # the last frame's record torn mid-write
    again = stored_rig(clock, tmp_path, resume=True)
    assert again.core.frames == 2 and again.session.disk.replay.torn == 1 and again.session.delivery()["journal_torn"] == 1
    again.frame(make_frame, 2)  # the tracker still had it: never acknowledged in the real crash
    assert again.core.frames == 3 and again.session.duplicates == 0


def test_snapshots_prune_the_journal_and_a_full_journal_forces_one(clock, make_frame, tmp_path):
    rig = stored_rig(clock, tmp_path, config={"fusion": {"snapshot_interval_s": 10.0, "journal": {"max_bytes": 4000}}})
    store, journal = rig.session.store, rig.session.disk.journal
    names = []
    for i in range(40):
        rig.frame(make_frame, i)
        names.append(store.latest_name())
    assert store.latest_name() is not None and int(store.latest_name()) >= 3  # by size, not by the 10 s interval
    kept = store.names()
    assert journal.files()[0] == kept[0] and journal.files()[-1] == store.latest_name()  # older files deleted
    again = stored_rig(clock, tmp_path, core=FakeFusion(), resume=True)
    assert again.core.last_frame_index == 39 and again.core.frames == 40
    again.session.close(save=False)


def test_records_keep_their_order_from_the_writer_thread(tmp_path):
    """Records handed in without waiting land in the order they were handed in."""
    j = Journal(tmp_path / "journal", JournalConfig())
    j.reset()
    pending = [j.submit("frame", tracked(i)) if i % 3 else j.submit("features", features(i, serial=i)) for i in range(9)]
    sizes = [p.result(timeout=30) for p in pending]
    j.close()
    records, stats = j.replay(None)
    assert stats.torn == 0 and all(s > 0 for s in sizes)
    assert [(r.kind, r.body.frame.frame_index if r.kind == "frame" else r.body.frame_index) for r in records] == [
        ("frame" if i % 3 else "features", i) for i in range(9)
    ]


def test_a_failed_write_reaches_the_caller_of_its_record(tmp_path):
    from services.fusion.durability.journal import JournalError

    j = Journal(tmp_path / "journal", JournalConfig())
    j.reset()
    j._wait(lambda: os.close(j._fd))  # the file gone from under it (as a disk error leaves it)
    with pytest.raises(JournalError, match="write failed"):
        j.submit("frame", tracked(0)).result(timeout=30)
    j._fd = None
    j.close()


class _SaysWhenFusing(FakeFusion):
    """A core that says when it fuses a frame."""

    def __init__(self, fusing: threading.Event) -> None:
        super().__init__(every=100)
        self.fusing = fusing

    def add_frame(self, tf: TrackedFrame):
        self.fusing.set()
        return super().add_frame(tf)


def test_a_frame_is_journaled_while_it_is_fused_and_on_disk_before_its_ack(clock, make_frame, tmp_path, monkeypatch):
    from services.fusion.durability import journal as journal_module

    fusing = threading.Event()
    overlapped: list[bool] = []
    encode = journal_module.encode_record

    def encode_beside_fusion(kind, body, level):
        # A journal written on the frame path, before the frame is applied, waits here in vain.
        overlapped.append(fusing.wait(2))
        time.sleep(0.05)  # still compressing when the frame is fused: the ack must wait for it
        return encode(kind, body, level)

    monkeypatch.setattr(journal_module, "encode_record", encode_beside_fusion)
    rig = stored_rig(clock, tmp_path, core=_SaysWhenFusing(fusing))
    on_disk_at_ack: list[int] = []

    def at_ack(env) -> None:
        records, _ = Journal(tmp_path / "graph" / "journal", JournalConfig()).replay(None)
        on_disk_at_ack.append(sum(r.kind == "frame" and r.body.frame.frame_index == env.body.frame_index for r in records))

    rig.bus.subscribe(rig.topics.frame_ack, FrameAck, at_ack)
    for i in range(3):
        fusing.clear()
        rig.frame(make_frame, i)
    assert rig.acks == [0, 1, 2] and rig.core.frames == 3
    assert overlapped == [True, True, True]
    assert on_disk_at_ack == [1, 1, 1]  # each frame's record was in the file when its ack went out
    rig.session.close(save=False)
