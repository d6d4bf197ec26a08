"""fusion's write-ahead journal: what was accepted since the last snapshot, on disk before
it is acknowledged.

Layout, beside the map store's snapshots (``ROOT`` is the store's root, ``<map>/graph``)::

    ROOT/journal/000000.wal    records since the empty map (a fresh start)
    ROOT/journal/000012.wal    records accepted after snapshot 000012 was written

A snapshot cuts the journal: the next record goes to a file named after it. Files older than
the oldest snapshot the store keeps are deleted, so a fallback to the previous snapshot (the
newest one corrupt) still finds every record after it. ``--resume`` loads the newest good
snapshot and replays every file from its name on, in order; fusion skips what is already in
the map (frame indices, feature serials), so overlapping files do no harm.

A file starts with :data:`FILE_MAGIC`. Each record is a 12-byte header (:data:`RECORD_MAGIC`,
payload length, CRC-32 of the payload) and the payload: a zstd frame of msgpack
``[kind, message]``, the message in :mod:`shared.codec`'s lossless encoding (raw colour,
delta-coded depth, run-coded labels), so a replayed frame is the frame fusion fused. A crash
mid-write leaves a torn last record: its header or payload is short or its checksum fails.
Reading stops there, counts and logs it, and cuts the file back to the last whole record
so appends go on after it. A damaged record inside a file (a bad disk block) is skipped the
same way when its length is still readable, and the reader looks for the next record's
magic otherwise.

Records are encoded, compressed and written on the journal's own writer thread, one at a
time in the order they were handed in (:meth:`Journal.submit`): fusion's frame path
integrates a frame while its record is compressed (zstd and the codec's zlib release the
GIL), and waits for the record only before the frame's ack. A record reaches the operating
system (``os.write``) before its future resolves and before :meth:`Journal.append` returns,
so a killed process loses nothing it acknowledged; ``fsync`` follows at most
``fusion.journal.fsync_interval_s`` later, against a power cut. Every other operation on the
file (sync, cut, open, close) runs on the same thread, after the records before it.
"""

from __future__ import annotations

import logging
import os
import re
import struct
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
from pydantic import BaseModel

from shared.codec import CodecError, decode, encode
from shared.config.fusion import JournalConfig
from shared.config.transport import CodecConfig
from shared.io import fsync_dir
from shared.messages.frames import EndOfSequence, TrackedFrame
from shared.messages.keyframes import TrackFeatures
from shared.messages.poses import PoseCorrection

log = logging.getLogger(__name__)

FILE_MAGIC = b"TGWAL1\n\0"
RECORD_MAGIC = b"TGJR"
HEADER = struct.Struct("<4sII")
"""Record magic, payload length, CRC-32 of the payload."""
MAX_RECORD_BYTES = 1 << 31
"""A header claiming more than this is damage, not a record (a 4K RGB-D frame is ~100 MB)."""
KINDS: dict[str, type[BaseModel]] = {
    "frame": TrackedFrame,
    "features": TrackFeatures,
    "end": EndOfSequence,
    "correction": PoseCorrection,
}
FIRST = "000000"
"""Name of the journal of a map started from nothing."""
_NAME = re.compile(r"^(\d{6,})\.wal$")

# Lossless, and as large as the process's own data gets: the wire's limits are for strangers.
# Label maps go raw into the record's zstd: long runs of one track id cost zstd 0.5 ms where
# zlib took 8 ms (1200x680), and the record comes out smaller (1.36 MB against 1.39 MB).
# Records written with zlib labels still replay: every array names its own encoding.
_CODEC = CodecConfig(rgb="raw", depth="zstd", labels="raw", masks="rle", max_payload_bytes=2**33,
                     max_array_bytes=2**32, max_items=50_000_000, max_string_bytes=2**26, max_image_pixels=2**30)  # fmt: skip


class JournalError(RuntimeError):
    """The journal cannot be written (disk full, permissions); the message names the file."""


@dataclass
class Record:
    """One accepted message: ``kind`` is ``frame``, ``features``, ``end`` or ``correction``."""

    kind: str
    body: BaseModel


@dataclass
class ReplayStats:
    """What a replay read: whole records per kind, and what it dropped as torn or damaged."""

    files: int = 0
    """Journal files read."""
    records: dict[str, int] = field(default_factory=dict)
    """Whole records read, per kind: what a resume replays (``journal_replayed``)."""
    torn_bytes: int = 0
    """Bytes the dropped records (and any unreadable stretch between records) took."""
    reasons: list[str] = field(default_factory=list)
    """One line per drop, naming the file and byte offset."""

    @property
    def torn(self) -> int:
        """Records dropped: a torn tail, a failed checksum, an undecodable message."""
        return len(self.reasons)


def encode_record(kind: str, body: BaseModel, level: int) -> bytes:
    """One record: header (magic, length, CRC-32) and the zstd-compressed ``[kind, message]``."""
    import zstandard

    msg = encode(body, robot_id="journal", seq=0, stamp=0.0, cfg=_CODEC)
    payload = zstandard.ZstdCompressor(level=level).compress(
        msgpack.packb([kind, msg], use_bin_type=True)
    )
    return HEADER.pack(RECORD_MAGIC, len(payload), zlib.crc32(payload)) + payload


def decode_payload(payload: bytes) -> Record:
    """The record a payload (after its header) holds; raises ValueError naming what is wrong."""
    import zstandard

    try:
        kind, msg = msgpack.unpackb(zstandard.ZstdDecompressor().decompress(payload), raw=False)
    except (zstandard.ZstdError, ValueError, TypeError, msgpack.ExtraData) as exc:
        raise ValueError(f"undecodable payload ({exc})") from None
    if kind not in KINDS or not isinstance(msg, bytes):
        raise ValueError(f"unknown record kind {kind!r}")
    try:
        return Record(kind, decode(msg, KINDS[kind], _CODEC).body)
    except CodecError as exc:
        raise ValueError(f"undecodable {kind} ({exc})") from None


def read_file(path: Path, stats: ReplayStats, *, repair: bool = False) -> Iterator[Record]:
    """The whole records of one journal file, in order; drops are counted in ``stats``. With
    ``repair`` a torn tail is cut off the file once reading reaches it."""
    tail: int | None = None
    """Where a torn tail starts: nothing whole after it."""
    with open(path, "rb") as f:
        data_len = os.fstat(f.fileno()).st_size
        head = f.read(len(FILE_MAGIC))
        if head != FILE_MAGIC:
            if data_len:
                stats.torn_bytes += data_len
                stats.reasons.append(
                    f"{path}: not a TrackGraph journal (starts {head[:8]!r}); {data_len} bytes skipped"
                )
            return
        pos = len(FILE_MAGIC)
        while pos < data_len:
            f.seek(pos)
            hdr = f.read(HEADER.size)
            if len(hdr) < HEADER.size:
                _torn(
                    stats, path, pos, data_len - pos, f"a {len(hdr)}-byte header (crash mid-write)"
                )
                tail = pos
                break
            magic, length, crc = HEADER.unpack(hdr)
            if magic != RECORD_MAGIC or length > MAX_RECORD_BYTES:
                nxt = _find_magic(f, pos + 1, data_len)
                _torn(stats, path, pos, (nxt or data_len) - pos, "no record header here (damaged)")
                if nxt is None:
                    tail = pos
                    break
                pos = nxt
                continue
            payload = f.read(length)
            if len(payload) < length:
                _torn(
                    stats,
                    path,
                    pos,
                    data_len - pos,
                    f"{len(payload)} of {length} payload bytes (crash mid-write)",
                )
                tail = pos
                break
            end = pos + HEADER.size + length
            if zlib.crc32(payload) != crc:
                _torn(stats, path, pos, end - pos, "checksum mismatch")
                pos = end
                continue
            try:
                rec = decode_payload(payload)
            except ValueError as exc:
                _torn(stats, path, pos, end - pos, str(exc))
                pos = end
                continue
            stats.records[rec.kind] = stats.records.get(rec.kind, 0) + 1
            pos = end
            yield rec
    if repair and tail is not None:
        # only the torn tail goes; damage inside the file stays, skipped on every read
        os.truncate(path, tail)
        log.info("journal %s: cut back to %d bytes (the torn tail dropped)", path, tail)


def _torn(stats: ReplayStats, path: Path, pos: int, nbytes: int, why: str) -> None:
    stats.torn_bytes += max(nbytes, 0)
    stats.reasons.append(f"{path}: record at byte {pos} dropped, {why}; {nbytes} bytes")


def _find_magic(f, start: int, end: int) -> int | None:
    chunk = 1 << 20
    pos = start
    while pos < end:
        f.seek(pos)
        buf = f.read(chunk + len(RECORD_MAGIC) - 1)
        i = buf.find(RECORD_MAGIC)
        if i >= 0:
            return pos + i
        pos += chunk
    return None


class Journal:
    """The journal folder ``root`` (``<map>/graph/journal``): replay, append, cut, prune."""

    def __init__(
        self, root: Path, cfg: JournalConfig, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.root = Path(root)
        self.cfg = cfg
        self.clock = clock
        self.name: str | None = None
        """The file appended to now (a snapshot name, or :data:`FIRST`)."""
        self._fd: int | None = None
        self._last_sync = clock()
        self._dirty = False
        self.bytes = 0
        """Bytes in the current file (since the last cut)."""
        self.appended = 0
        self.appended_bytes = 0
        self.append_s = 0.0
        """Seconds spent encoding and writing records (the journal's cost, for the status and benchmarks)."""
        self._writer: ThreadPoolExecutor | None = None
        """One thread: records and file operations in the order they were handed in."""

    def _call(self, fn: Callable[..., object], *args: object) -> Future:
        if self._writer is None:
            self._writer = ThreadPoolExecutor(1, thread_name_prefix="journal")
        return self._writer.submit(fn, *args)

    def _wait(self, fn: Callable[..., object], *args: object) -> object:
        """``fn(*args)`` on the writer thread, after everything handed in before it."""
        return self._call(fn, *args).result()

    # ---------------------------------------------------------------- files

    def files(self) -> list[str]:
        """Names of the journal files, oldest first."""
        if not self.root.is_dir():
            return []
        names = [m.group(1) for p in self.root.iterdir() if (m := _NAME.match(p.name))]
        return sorted(names, key=int)

    def path(self, name: str) -> Path:
        return self.root / f"{name}.wal"

    def replay(self, after: str | None) -> tuple[list[Record], ReplayStats]:
        """Every whole record from the file named ``after`` (the snapshot resumed from;
        None: the map starts empty, every file) on, in order. Torn tails are cut off their
        files; every drop is logged."""
        stats = ReplayStats()
        start = int(after) if after is not None else -1
        records: list[Record] = []
        for name in self.files():
            if int(name) < start:
                continue
            stats.files += 1
            records.extend(read_file(self.path(name), stats, repair=True))
        for why in stats.reasons:
            log.warning("journal: %s", why)
        return records, stats

    def open(self, name: str) -> None:
        """Append to file ``name`` from now on (created with its magic if new or empty)."""
        self._wait(self._open, name)

    def _open(self, name: str) -> None:
        self._close()
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.path(name)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o666)
            size = os.fstat(fd).st_size
            if size == 0:
                os.write(fd, FILE_MAGIC)
                size = len(FILE_MAGIC)
                fsync_dir(self.root)
        except OSError as exc:
            raise JournalError(f"journal {path}: cannot open for writing ({exc.strerror})") from exc
        self._fd, self.name, self.bytes = fd, name, size
        self._last_sync = self.clock()

    def reset(self) -> None:
        """A fresh map: the old journal files go, and appends start at :data:`FIRST`."""
        self._wait(self._reset)

    def _reset(self) -> None:
        for name in self.files():
            self.path(name).unlink(missing_ok=True)
        self._open(FIRST)

    def append(self, kind: str, body: BaseModel) -> int:
        """Write one record; returns its size. The bytes are with the operating system when
        this returns (a killed process loses nothing); fsync when the interval is up."""
        return self.submit(kind, body).result()

    def submit(self, kind: str, body: BaseModel) -> Future:
        """Write one record on the writer thread, after those handed in before it. The
        future's result is the record's size once its bytes are with the operating system, or
        the :class:`JournalError` that stopped them. ``body`` must not change until then."""
        return self._call(self._append, kind, body)

    def _append(self, kind: str, body: BaseModel) -> int:
        if self._fd is None:
            raise JournalError(f"journal {self.root}: not open")
        t0 = time.perf_counter()
        rec = encode_record(kind, body, self.cfg.zstd_level)
        try:
            view = memoryview(rec)
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
        except OSError as exc:
            raise JournalError(
                f"journal {self.path(self.name or FIRST)}: write failed ({exc.strerror})"
            ) from exc
        self._dirty = True
        self.bytes += len(rec)
        self.appended += 1
        self.appended_bytes += len(rec)
        now = self.clock()
        if now - self._last_sync >= self.cfg.fsync_interval_s:
            self._sync(now)
        self.append_s += time.perf_counter() - t0
        return len(rec)

    def sync(self, now: float | None = None) -> None:
        """fsync what was appended (called by ``append`` and the session's tick)."""
        self._wait(self._sync, now)

    def _sync(self, now: float | None = None) -> None:
        if self._fd is not None and self._dirty:
            try:
                os.fsync(self._fd)
            except OSError as exc:
                log.warning(
                    "journal %s: fsync failed (%s)", self.path(self.name or FIRST), exc.strerror
                )
            self._dirty = False
        self._last_sync = self.clock() if now is None else now

    def due(self, now: float) -> bool:
        """Whether an fsync is owed (appended since the last, and the interval is up)."""
        return self._dirty and now - self._last_sync >= self.cfg.fsync_interval_s

    def cut(self, snapshot: str, keep_from: str | None) -> None:
        """Snapshot ``snapshot`` holds everything appended so far: later records go to its own
        file. Files older than ``keep_from`` (the oldest snapshot the store keeps) are deleted."""
        self._wait(self._cut, snapshot, keep_from)

    def _cut(self, snapshot: str, keep_from: str | None) -> None:
        self._sync()
        self._open(snapshot)
        if keep_from is not None:
            for name in self.files():
                if int(name) < int(keep_from) and name != self.name:
                    self.path(name).unlink(missing_ok=True)

    def close(self) -> None:
        """Write what was handed in, fsync, close the file and stop the writer thread."""
        if self._writer is None:
            return
        try:
            self._wait(self._close)
        finally:
            self._writer.shutdown(wait=True)
            self._writer = None

    def _close(self) -> None:
        if self._fd is not None:
            self._sync()
            os.close(self._fd)
            self._fd = None

    def stats(self) -> dict:
        """For the status and ``run.json``: records and bytes appended, ms per record."""
        n = self.appended
        return {
            "records": n, "bytes": self.appended_bytes, "file_bytes": self.bytes, "file": self.name,
            "ms_per_record": round(1000 * self.append_s / n, 3) if n else None,
            "bytes_per_record": round(self.appended_bytes / n) if n else None,
        }  # fmt: skip

