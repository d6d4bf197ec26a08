"""Crash-safe on-disk snapshots of the whole map state.

Layout of a store rooted at ``ROOT``::

    ROOT/latest                      name of the newest complete snapshot ("000012")
    ROOT/snapshots/000011/ ...       the previous one, kept as a fallback
    ROOT/snapshots/000012/
        graph.msgpack                the GraphSnapshot (with mesh), lossless, via shared.codec
        extra.npz                    opaque arrays of the other stages (TSDF, tracks, ...)
        metadata.json                summary, the layout of the extra state, caller metadata
        graph.sparkdsg               the same graph for Hydra's tools (see shared.graph.dsg)
        MANIFEST.json                size and SHA-256 of every file above; written last

A save writes every file with temp + fsync + rename into a hidden ``.000013.partial``
folder, the manifest last, renames the folder to ``000013`` and only then points ``latest``
at it, so a crash at any moment leaves the previous snapshot current and intact. Older
snapshots beyond ``keep`` are deleted afterwards. A full disk (ENOSPC) aborts the save with
:class:`DiskFull`, removes the partial folder and leaves the previous snapshot current.

A load verifies the manifest, every file's size (truncation) and checksum (corruption), then
decodes. If the newest snapshot fails, it logs why and falls back to the next older one;
:class:`SnapshotCorrupt` names the file at fault when none is usable.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import logging
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.codec import CodecError, decode, encode
from shared.config.transport import CodecConfig
from shared.io import atomic_write_bytes, fsync_dir
from shared.messages.graph import GraphSnapshot

log = logging.getLogger(__name__)

FORMAT = "trackgraph-map"
FORMAT_VERSION = 1
MANIFEST = "MANIFEST.json"
GRAPH_FILE = "graph.msgpack"
EXTRA_FILE = "extra.npz"
META_FILE = "metadata.json"
DSG_FILE = "graph.sparkdsg"
REQUIRED = (GRAPH_FILE, EXTRA_FILE, META_FILE)
_NAME = re.compile(r"^\d{6,}$")

# A saved map is the process's own trusted-but-verified data, far larger than a network
# message: the wire limits would refuse a big mesh.
_STORE_CODEC = CodecConfig(
    max_payload_bytes=2**34, max_array_bytes=2**33, max_items=50_000_000, max_string_bytes=2**26
)

ExtraState = dict[str, "np.ndarray | ExtraState"]


class StoreError(RuntimeError):
    """A map snapshot could not be written or read."""


class SnapshotCorrupt(StoreError):
    """A snapshot on disk is incomplete, truncated or corrupt; ``path`` is the file at fault."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = Path(path)
        self.reason = reason


class DiskFull(StoreError):
    """The disk filled up during a save; the previous snapshot is still current."""


@dataclass
class MapState:
    """What :meth:`MapStore.load` returns."""

    snapshot: GraphSnapshot
    extra: dict[str, Any]
    metadata: dict[str, Any]
    path: Path
    fell_back_from: list[str] = field(default_factory=list)
    """Newer snapshots that were skipped, with the reason, when the newest was unusable."""


# ---------------------------------------------------------------- extra state


def _flatten(tree: dict, prefix: str = "") -> tuple[dict[str, np.ndarray], dict]:
    """Nested dict of arrays -> flat {"a/b": array} plus a skeleton that keeps empty dicts."""
    flat: dict[str, np.ndarray] = {}
    skel: dict[str, Any] = {}
    for k, v in tree.items():
        if not isinstance(k, str) or not k or "/" in k:
            raise StoreError(f"extra_state key {prefix + str(k)!r}: keys must be non-empty strings without '/'")
        if isinstance(v, dict):
            sub, skel[k] = _flatten(v, f"{prefix}{k}/")
            flat.update(sub)
        else:
            arr = np.asarray(v)
            if arr.dtype.hasobject:
                raise StoreError(f"extra_state[{prefix + k!r}] holds Python objects; only numeric/bool/str arrays are stored")
            flat[prefix + k] = arr
            skel[k] = None
    return flat, skel


def _unflatten(flat: dict[str, np.ndarray], skel: dict, prefix: str = "") -> dict:
    return {
        k: _unflatten(flat, v, f"{prefix}{k}/") if isinstance(v, dict) else flat[prefix + k]
        for k, v in skel.items()
    }


# ---------------------------------------------------------------- the store


class MapStore:
    """Snapshots of the map under one root folder."""

    def __init__(self, root: Path | str, keep: int = 2, write_dsg: bool = True, robot_id: str = "robot0") -> None:
        if keep < 1:
            raise ValueError("keep must be at least 1")
        self.root = Path(root)
        self.keep = keep
        self.write_dsg = write_dsg
        self.robot_id = robot_id

    @property
    def snapshots_dir(self) -> Path:
        return self.root / "snapshots"

    def names(self) -> list[str]:
        """Names of finished snapshot folders (with or without a valid manifest), oldest first."""
        if not self.snapshots_dir.is_dir():
            return []
        return sorted((p.name for p in self.snapshots_dir.iterdir() if p.is_dir() and _NAME.match(p.name)), key=int)

    def latest_name(self) -> str | None:
        """What ``latest`` points at, or None if it is missing or unreadable."""
        try:
            name = (self.root / "latest").read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError):
            return None
        return name if _NAME.match(name) else None

    # ------------------------------------------------------------ save

    def save(
        self,
        snapshot: GraphSnapshot,
        extra_state: ExtraState | None = None,
        metadata: dict[str, Any] | None = None,
    ) -> Path:
        """Write a new snapshot and make it current; returns its folder."""
        flat, skel = _flatten(extra_state or {})
        existing = self.names()
        number = int(existing[-1]) + 1 if existing else 1
        name = f"{number:06d}"
        final = self.snapshots_dir / name
        partial = self.snapshots_dir / f".{name}.partial"
        previous = self.latest_name()
        current = "<folder>"
        t0 = time.perf_counter()
        try:
            if partial.exists():
                shutil.rmtree(partial)
            partial.mkdir(parents=True)
            files: dict[str, dict[str, Any]] = {}

            def put(fname: str, data: bytes) -> None:
                atomic_write_bytes(partial / fname, data)
                files[fname] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}

            current = GRAPH_FILE
            put(GRAPH_FILE, encode(snapshot, robot_id=self.robot_id, seq=snapshot.graph_seq, stamp=time.time(), cfg=_STORE_CODEC))
            current = EXTRA_FILE
            buf = io.BytesIO()
            np.savez(buf, **flat)
            put(EXTRA_FILE, buf.getvalue())
            current = META_FILE
            meta = {
                "format": FORMAT,
                "version": FORMAT_VERSION,
                "graph_seq": snapshot.graph_seq,
                "frame_index": snapshot.frame_index,
                "counts": {
                    "segments": len(snapshot.segments),
                    "places": len(snapshot.places),
                    "rooms": len(snapshot.rooms),
                    "edges": len(snapshot.edges),
                    "mesh_vertices": 0 if snapshot.mesh is None else int(snapshot.mesh.vertices.shape[0]),
                },
                "saved_unix": time.time(),
                "robot_id": self.robot_id,
                "extra_layout": skel,
                "user": metadata or {},
            }
            put(META_FILE, json.dumps(meta, indent=1, sort_keys=True).encode("utf-8"))
            if self.write_dsg:
                current = DSG_FILE
                self._write_dsg(snapshot, partial / DSG_FILE, files)
            current = MANIFEST
            manifest = {
                "format": FORMAT,
                "version": FORMAT_VERSION,
                "name": name,
                "graph_seq": snapshot.graph_seq,
                "files": files,
            }
            atomic_write_bytes(partial / MANIFEST, json.dumps(manifest, indent=1, sort_keys=True).encode("utf-8"))
            fsync_dir(partial)
            current = "<rename>"
            os.rename(partial, final)
            fsync_dir(self.snapshots_dir)
            current = "latest"
            atomic_write_bytes(self.root / "latest", f"{name}\n".encode())
        except OSError as exc:
            shutil.rmtree(partial, ignore_errors=True)
            if current == "latest":
                # Never leave a complete snapshot newer than what ``latest`` says.
                shutil.rmtree(final, ignore_errors=True)
            where = f"{current} of snapshot {name} in {self.root}"
            kept = f"previous snapshot {previous} is still current" if previous else "no earlier snapshot exists"
            if exc.errno == errno.ENOSPC:
                raise DiskFull(f"disk full while writing {where}; {kept}") from exc
            raise StoreError(f"cannot write {where} ({exc}); {kept}") from exc
        except (TypeError, ValueError) as exc:
            # CodecError is a ValueError: the graph itself would not encode; otherwise the
            # caller's metadata is not JSON.
            shutil.rmtree(partial, ignore_errors=True)
            raise StoreError(f"cannot serialise {current} of snapshot {name}: {exc}") from exc
        log.info("saved map snapshot %s (graph_seq %d) in %.2f s", final, snapshot.graph_seq, time.perf_counter() - t0)
        self._prune(keep_name=name)
        return final

    def _write_dsg(self, snapshot: GraphSnapshot, path: Path, files: dict[str, dict[str, Any]]) -> None:
        try:
            from shared.graph.dsg import save_dsg
        except ImportError as exc:
            log.warning("spark_dsg unavailable (%s): snapshot written without %s", exc, DSG_FILE)
            return
        try:
            save_dsg(snapshot, path)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - spark_dsg raises RuntimeError for I/O failures
            free = shutil.disk_usage(path.parent).free
            err = errno.ENOSPC if free == 0 else errno.EIO
            raise OSError(err, f"spark_dsg could not write {path.name}: {exc}") from exc
        data = path.read_bytes()
        files[DSG_FILE] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}

    def _prune(self, keep_name: str) -> None:
        names = self.names()
        doomed = [n for n in names[: max(len(names) - self.keep, 0)] if n != keep_name]
        for n in doomed:
            shutil.rmtree(self.snapshots_dir / n, ignore_errors=True)
        for p in self.snapshots_dir.glob(".*.partial"):
            shutil.rmtree(p, ignore_errors=True)
        if doomed:
            log.debug("pruned snapshots %s", doomed)

    # ------------------------------------------------------------ load

    def verify(self, name: str) -> dict[str, Any]:
        """Check one snapshot's manifest, sizes and checksums; returns the manifest."""
        folder = self.snapshots_dir / name
        mpath = folder / MANIFEST
        if not folder.is_dir():
            raise SnapshotCorrupt(folder, "no such snapshot folder")
        if not mpath.is_file():
            raise SnapshotCorrupt(mpath, "missing (the save was interrupted)")
        try:
            manifest = json.loads(mpath.read_bytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SnapshotCorrupt(mpath, f"corrupt or truncated manifest ({exc})") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or not isinstance(manifest.get("files"), dict):
            raise SnapshotCorrupt(mpath, "not a trackgraph map manifest")
        if manifest.get("version") != FORMAT_VERSION:
            raise SnapshotCorrupt(mpath, f"format version {manifest.get('version')!r}, this build reads {FORMAT_VERSION}")
        files = manifest["files"]
        for req in REQUIRED:
            if req not in files:
                raise SnapshotCorrupt(mpath, f"does not list {req}")
        for fname, info in files.items():
            fpath = folder / fname
            if "/" in fname or not isinstance(info, dict):
                raise SnapshotCorrupt(mpath, f"bad entry {fname!r}")
            if not fpath.is_file():
                raise SnapshotCorrupt(fpath, "missing")
            data = fpath.read_bytes()
            if len(data) != info.get("bytes"):
                raise SnapshotCorrupt(fpath, f"truncated or overwritten: {len(data)} bytes, manifest says {info.get('bytes')}")
            if hashlib.sha256(data).hexdigest() != info.get("sha256"):
                raise SnapshotCorrupt(fpath, "checksum mismatch (corrupt)")
        return manifest

    def load_name(self, name: str) -> MapState:
        """Load one snapshot by name, verifying it first."""
        self.verify(name)
        folder = self.snapshots_dir / name
        try:
            snap = decode((folder / GRAPH_FILE).read_bytes(), GraphSnapshot, _STORE_CODEC).body
        except CodecError as exc:
            raise SnapshotCorrupt(folder / GRAPH_FILE, f"undecodable graph ({exc})") from None
        try:
            meta = json.loads((folder / META_FILE).read_bytes().decode("utf-8"))
            skel = meta["extra_layout"]
        except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
            raise SnapshotCorrupt(folder / META_FILE, f"unreadable metadata ({exc})") from None
        try:
            with np.load(io.BytesIO((folder / EXTRA_FILE).read_bytes()), allow_pickle=False) as npz:
                flat = {k: npz[k] for k in npz.files}
            extra = _unflatten(flat, skel)
        except (ValueError, OSError, KeyError, EOFError) as exc:
            raise SnapshotCorrupt(folder / EXTRA_FILE, f"unreadable extra state ({exc})") from None
        return MapState(snapshot=snap, extra=extra, metadata=meta, path=folder)

    def load(self, fallback: bool = True) -> MapState:
        """The newest usable snapshot: ``latest`` first, then older ones newest first."""
        names = self.names()
        latest = self.latest_name()
        order = ([latest] if latest else []) + [n for n in reversed(names) if n != latest]
        if not order:
            raise StoreError(f"no map snapshot in {self.root}")
        failures: list[str] = []
        for name in order:
            try:
                state = self.load_name(name)
            except SnapshotCorrupt as exc:
                log.warning("map snapshot %s unusable: %s", name, exc)
                if not fallback:
                    raise
                failures.append(f"{name}: {exc}")
                continue
            if failures:
                log.warning("fell back to map snapshot %s", name)
            state.fell_back_from = failures
            return state
        raise StoreError(f"no usable map snapshot in {self.root}: " + "; ".join(failures))

