"""Per-frame source-track maps as ``trackgraph map --save-tracks`` writes them, and the
ground-truth instance maps of a sequence.

Layout of a run::

    RUN_DIR/tracks/track000000.png   uint16 PNG per processed frame index:
                                     0 = no track, track id + 1 otherwise
    RUN_DIR/tracks/keyframes.json    JSON list of the keyframes' frame indices, ascending

Ground truth (written by ``shared.synth``, Replica layout)::

    SEQ_DIR/instances/instance000000.png   uint16 PNG: 0 = no object, object id + 1 otherwise

In memory both are ``(H, W) int32`` maps with -1 for "none", ids >= 0 otherwise.
"""

from __future__ import annotations

import io
import json
import logging
import re
from pathlib import Path
from typing import Annotated

import numpy as np
from PIL import Image

from shared.eval.errors import EvalInputError
from shared.io import atomic_write_bytes, atomic_write_text

log = logging.getLogger(__name__)

TRACKS_DIR = "tracks"
KEYFRAMES_FILE = "keyframes.json"
TRACK_PATTERN = "track{:06d}.png"
INSTANCES_DIR = "instances"
INSTANCE_PATTERN = "instance{:06d}.png"
MAX_ID = 65534
"""Largest id a uint16 PNG can hold (stored as id + 1)."""

IdMap = Annotated[np.ndarray, "(H, W) int32, -1 = none"]


def tracks_dir(run_dir: str | Path) -> Path:
    """``RUN_DIR/tracks`` (``run_dir`` itself if it already is a tracks folder)."""
    run_dir = Path(run_dir)
    if run_dir.name == TRACKS_DIR and not (run_dir / TRACKS_DIR).is_dir():
        return run_dir
    return run_dir / TRACKS_DIR


def track_path(run_dir: str | Path, frame: int) -> Path:
    return tracks_dir(run_dir) / TRACK_PATTERN.format(int(frame))


def instance_path(seq_dir: str | Path, frame: int) -> Path:
    return Path(seq_dir) / INSTANCES_DIR / INSTANCE_PATTERN.format(int(frame))


def encode_id_png(ids: IdMap) -> bytes:
    """PNG bytes of an id map (-1 -> 0, id -> id + 1, as uint16)."""
    ids = np.asarray(ids)
    if ids.ndim != 2 or ids.dtype.kind not in "iu":
        raise ValueError(f"expected an integer (H, W) id map (got {ids.dtype} {ids.shape})")
    if ids.size and (ids.min() < -1 or ids.max() > MAX_ID):
        raise ValueError(f"ids must be -1 (none) or in [0, {MAX_ID}] (found {ids.min()}..{ids.max()})")
    img = Image.fromarray((ids.astype(np.int64) + 1).astype(np.uint16))
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def read_id_png(path: str | Path) -> IdMap:
    """An id map from a uint16 (or 8-bit) single-channel PNG: 0 -> -1, v -> v - 1."""
    path = Path(path)
    if not path.is_file():
        raise EvalInputError(path, "missing")
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode not in ("I;16", "I;16B", "I;16L", "I", "L", "P"):
                raise EvalInputError(path, f"expected a single-channel id PNG (got mode {img.mode})")
            arr = np.array(img)
    except EvalInputError:
        raise
    except (OSError, ValueError, SyntaxError) as exc:
        raise EvalInputError(path, f"not a readable PNG ({exc})") from exc
    if arr.ndim != 2:
        raise EvalInputError(path, f"expected a single-channel image (got shape {arr.shape})")
    return arr.astype(np.int32) - 1


class TrackWriter:
    """Writes a run's per-frame track maps and its keyframe list.

    ``keyframes.json`` is rewritten (atomically) whenever a keyframe is added, so an
    interrupted run is still readable; ``close()`` writes it in any case.
    """

    def __init__(self, run_dir: str | Path) -> None:
        self.dir = tracks_dir(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.keyframes: list[int] = []
        self.frames_written = 0
        self._flush_keyframes()

    def write(self, frame: int, track_ids: IdMap, *, keyframe: bool = False) -> Path:
        """Store the track map of frame index ``frame`` (-1 = no track)."""
        if int(frame) < 0:
            raise ValueError(f"frame index must be >= 0 (got {frame})")
        path = atomic_write_bytes(self.dir / TRACK_PATTERN.format(int(frame)), encode_id_png(track_ids))
        self.frames_written += 1
        if keyframe:
            self.add_keyframe(frame)
        return path

    def add_keyframe(self, frame: int) -> None:
        if int(frame) not in self.keyframes:
            self.keyframes.append(int(frame))
            self._flush_keyframes()

    def _flush_keyframes(self) -> None:
        atomic_write_text(self.dir / KEYFRAMES_FILE, json.dumps(sorted(self.keyframes)))

    def close(self) -> None:
        self._flush_keyframes()
        log.debug("wrote %d track maps and %d keyframes to %s", self.frames_written, len(self.keyframes), self.dir)

    def __enter__(self) -> TrackWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_keyframes(run_dir: str | Path) -> list[int]:
    """The keyframe indices of a run, ascending."""
    path = tracks_dir(run_dir) / KEYFRAMES_FILE
    if not path.is_file():
        raise EvalInputError(path, "missing (was the map run with --save-tracks?)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EvalInputError(path, f"not readable JSON ({exc})") from exc
    if not isinstance(data, list) or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in data):
        raise EvalInputError(path, "expected a JSON list of non-negative frame indices")
    return sorted(set(data))


def list_track_frames(run_dir: str | Path) -> list[int]:
    """Frame indices that have a track map, ascending."""
    folder = tracks_dir(run_dir)
    if not folder.is_dir():
        raise EvalInputError(folder, "missing track folder (was the map run with --save-tracks?)")
    pattern = re.compile(r"^track(\d+)\.png$")
    return sorted(int(m.group(1)) for p in folder.iterdir() if (m := pattern.match(p.name)))


def read_track_map(run_dir: str | Path, frame: int) -> IdMap:
    return read_id_png(track_path(run_dir, frame))


def read_instance_map(seq_dir: str | Path, frame: int) -> IdMap:
    return read_id_png(instance_path(seq_dir, frame))
