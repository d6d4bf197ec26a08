"""Ground truth of a synthetic sequence for the simulated perception backends, off the wire.

The simulated segmenter, the simulated VL encoder and the ground-truth tracker stand in for
FastSAM, CLIP and a real tracker by reading a synthetic sequence's instance images instead of
looking at pixels. No message carries ground truth: each backend is given an
:class:`InstanceSource` when it is made, and asks it

- by frame index, for keyframes and frames (``KeyframeRequest.frame_index``,
  ``Frame.frame_index``: the frame's position in its sequence, as every reader numbers it);
- by image content, for image queries (``QueryRequest.image``, ``EmbedRequest.image``): the
  image must be one of the sequence's frames or a rectangular crop of one, pixel for pixel
  (a crop of at least about 32x32 pixels: a smaller one may hold too few distinctive runs).
  An image that went through a lossy link (``transport.codec.rgb: jpeg``), was resized or comes
  from anywhere else has no ground truth, and asking for it raises :class:`GroundTruthError`.

:class:`SequenceGroundTruth` reads a sequence folder (``trackgraph synth``'s layout);
:class:`StaticGroundTruth` holds arrays (tests). No Zenoh, no torch.

Finding a crop
--------------
Every fourth row of every frame is cut into runs of 8 pixels; a run whose hash falls in one
of 32 buckets is an *anchor*, remembered with its frame and position (about 1 in 32 runs, so
the index is about 1/128 of the pixels). Anchors are chosen by content, so the crop's own runs
include the anchors of the frame rows it covers, at the same offsets: each crop anchor found in
the index votes for a placement (frame, top, left), and the best-voted placements are compared
with the frame pixel for pixel. A run that recurs more than 32 times in the sequence (a flat
wall, a tiled texture) tells nothing and is left out. The index is built once, on the first
image query or in the background from :meth:`SequenceGroundTruth.prepare_images`.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Protocol

import numpy as np

from shared.datasets.base import DatasetError

log = logging.getLogger(__name__)

Instances = Annotated[np.ndarray, "(H, W) int32 object id, -1 = none"]
RGB = Annotated[np.ndarray, "(H, W, 3) uint8"]

RUN_PX = 8
"""Pixels per hashed run of a row."""
ROW_STEP = 4
"""Every ROW_STEP-th row of a frame is indexed; a crop needs at least this many rows."""
ANCHOR_MASK = np.uint64(31)
"""A run is an anchor when its hash's low bits are zero: 1 in 32 runs."""
MAX_OCCURRENCES = 32
"""A run found more often than this in the sequence is not used to place a crop."""
VERIFY = 8
"""Best-voted placements compared pixel for pixel before giving up."""
CACHE_FRAMES = 8
"""Instance and colour images kept per source: a keyframe is read by the segmenter, then by
the encoder, and image queries of one scene tend to come from a few frames."""

_HASH_BASE = np.uint64(0x100000001B3)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


class GroundTruthError(ValueError):
    """No ground truth for what was asked; the message names the frame or image, and the sequence."""


class InstanceSource(Protocol):
    """Where a simulated backend reads ground truth."""

    def frame_instances(self, frame_index: int) -> Instances:
        """The instance ids of frame ``frame_index``; GroundTruthError if there is no such frame."""
        ...

    def image_instances(self, rgb: RGB) -> Instances:
        """The instance ids under an image that is a sequence frame or a crop of one, pixel for
        pixel; GroundTruthError for any other image."""
        ...


# ---------------------------------------------------------------- locating a folder


def sequence_folder(path: str | Path | None, field: str, user: str) -> Path:
    """The synthetic sequence folder ``path`` names (the folder itself, or its ``gt/``
    subfolder, as older configs gave ``keyframe_vl.vl.ground_truth``).

    ``field`` is the config key it came from and ``user`` the backend that needs it; both are
    named in the error when the folder is unset, missing or has no ``instances/``.
    """
    if path is None or str(path).strip() == "":
        raise GroundTruthError(
            f"{field} is not set: the {user} needs a synthetic sequence folder with instances/ "
            "(`trackgraph synth` writes one; `trackgraph map`, `launch` and `serve --sequence` set it from the sequence)"
        )
    root = Path(path).expanduser()
    if not root.is_dir():
        raise GroundTruthError(f"{field}: {root} is not a folder (the {user} needs a synthetic sequence folder)")
    if (root / "instances").is_dir():
        return root
    if root.name == "gt" and (root.parent / "instances").is_dir():
        return root.parent
    raise GroundTruthError(
        f"{field}: {root} has no instances/ folder: the {user} works only on synthetic sequences (`trackgraph synth`)"
    )


# ---------------------------------------------------------------- run hashes


def _run_hashes(rows: Annotated[np.ndarray, "(R, W, 3) uint8"]) -> Annotated[np.ndarray, "(R, W - RUN_PX + 1) uint64"]:
    """A mixed polynomial hash of every run of RUN_PX pixels along each row."""
    p = (rows[..., 0].astype(np.uint64) << np.uint64(16)) | (rows[..., 1].astype(np.uint64) << np.uint64(8)) | rows[..., 2].astype(np.uint64)
    n = p.shape[1] - RUN_PX + 1
    h = np.zeros((p.shape[0], max(n, 0)), np.uint64)
    if n <= 0:
        return h
    for k in range(RUN_PX):
        h = h * _HASH_BASE + p[:, k : k + n]  # wraps modulo 2**64, as a hash should
    # splitmix64's finaliser: the low bits (the anchor test) depend on every pixel of the run
    h ^= h >> np.uint64(30)
    h *= _MIX1
    h ^= h >> np.uint64(27)
    h *= _MIX2
    h ^= h >> np.uint64(31)
    return h


def _anchors(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hash, row, column) of the anchor runs of ``rows``."""
    h = _run_hashes(rows)
    r, x = np.nonzero((h & ANCHOR_MASK) == 0)
    return h[r, x], r, x


class _ImageIndex:
    """Anchor runs of every indexed row of every frame, sorted by hash."""

    def __init__(self, hashes: np.ndarray, frames: np.ndarray, ys: np.ndarray, xs: np.ndarray, shape: tuple[int, int]) -> None:
        self.hashes, self.frames, self.ys, self.xs, self.shape = hashes, frames, ys, xs, shape

    @staticmethod
    def build(n_frames: int, read_rgb, shape: tuple[int, int]) -> _ImageIndex:
        parts: list[tuple[np.ndarray, ...]] = []
        for i in range(n_frames):
            hs, r, x = _anchors(read_rgb(i)[::ROW_STEP])
            # Runs repeated within one frame (a flat wall) would flood the index before the
            # sequence-wide count leaves them out; they say nothing about placement anyway.
            _, inv, counts = np.unique(hs, return_inverse=True, return_counts=True)
            keep = counts[inv] == 1
            parts.append((hs[keep], np.full(int(keep.sum()), i, np.int32), (r[keep] * ROW_STEP).astype(np.int32), x[keep].astype(np.int32)))
        if not parts:
            empty = np.zeros(0, np.int32)
            return _ImageIndex(np.zeros(0, np.uint64), empty, empty, empty, shape)
        hs, fs, ys, xs = (np.concatenate(c) for c in zip(*parts, strict=True))
        order = np.argsort(hs, kind="stable")
        hs, fs, ys, xs = hs[order], fs[order], ys[order], xs[order]
        _, inv, counts = np.unique(hs, return_inverse=True, return_counts=True)
        keep = counts[inv] <= MAX_OCCURRENCES
        return _ImageIndex(hs[keep], fs[keep], ys[keep], xs[keep], shape)

    def placements(self, rgb: RGB) -> list[tuple[int, int, int]]:
        """Candidate (frame, top, left) placements of ``rgb``, most votes first."""
        hq, rq, xq = _anchors(rgb)
        lo = np.searchsorted(self.hashes, hq, "left")
        hi = np.searchsorted(self.hashes, hq, "right")
        counts = hi - lo
        total = int(counts.sum())
        if total == 0:
            return []
        which = np.repeat(np.arange(len(hq)), counts)
        pos = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(lo, counts)
        f = self.frames[pos]
        top = self.ys[pos] - rq[which]
        left = self.xs[pos] - xq[which]
        h, w = rgb.shape[:2]
        fits = (top >= 0) & (left >= 0) & (top + h <= self.shape[0]) & (left + w <= self.shape[1])
        if not fits.any():
            return []
        cand, votes = np.unique(np.stack([f[fits], top[fits], left[fits]]), axis=1, return_counts=True)
        best = np.lexsort((cand[2], cand[1], cand[0], -votes))[:VERIFY]
        return [(int(cand[0, k]), int(cand[1, k]), int(cand[2, k])) for k in best]


# ---------------------------------------------------------------- sources


class SequenceGroundTruth:
    """The ground truth of a synthetic sequence folder, read on demand (thread-safe)."""

    def __init__(self, path: str | Path | None, *, field: str = "ground_truth", user: str = "simulated backend") -> None:
        from shared.datasets.replica import ReplicaReader

        self.field, self.user = field, user
        self.root = sequence_folder(path, field, user)
        try:
            self._reader = ReplicaReader(self.root)
        except DatasetError as exc:
            raise GroundTruthError(f"{field}: {self.root} is not a readable synthetic sequence ({exc})") from None
        self.shape = (self._reader.intrinsics.height, self._reader.intrinsics.width)
        self._instances = functools.lru_cache(maxsize=CACHE_FRAMES)(self._read_instances)
        self._rgb = functools.lru_cache(maxsize=CACHE_FRAMES)(self._read_rgb)
        self._index: _ImageIndex | None = None
        self._index_error: BaseException | None = None
        self._index_lock = threading.Lock()
        self._index_thread: threading.Thread | None = None

    def __len__(self) -> int:
        return len(self._reader)

    def _check_index(self, frame_index: int) -> int:
        if isinstance(frame_index, bool) or not isinstance(frame_index, (int, np.integer)):
            raise GroundTruthError(f"frame_index {frame_index!r} is not an integer")
        i = int(frame_index)
        if not 0 <= i < len(self._reader):
            raise GroundTruthError(f"frame_index {i} is not a frame of the sequence {self.root} (frames 0 to {len(self._reader) - 1})")
        return i

    def _read_instances(self, i: int) -> Instances:
        ids = self._reader.instances(i)
        assert ids is not None  # sequence_folder checked for instances/
        ids.flags.writeable = False  # cached and shared between callers
        return ids

    def _read_rgb(self, i: int) -> RGB:
        rgb = self._reader.rgb(i)
        rgb.flags.writeable = False
        return rgb

    def frame_instances(self, frame_index: int) -> Instances:
        return self._instances(self._check_index(frame_index))

    # ------------------------------------------------------------ images

    def prepare_images(self, background: bool = True) -> None:
        """Build the image index now (on a daemon thread with ``background``) rather than on
        the first image query, which otherwise waits for it (about 3 ms a frame). Safe to
        call more than once."""
        with self._index_lock:
            if self._index is not None or self._index_thread is not None:
                thread = self._index_thread
            else:
                thread = self._index_thread = threading.Thread(target=self._build_index, name="ground-truth:index", daemon=True)
                thread.start()
        if not background and thread is not None:
            thread.join()

    def _build_index(self) -> None:
        t0 = time.perf_counter()
        try:
            index = _ImageIndex.build(len(self._reader), self._reader.rgb, self.shape)
        except BaseException as exc:  # noqa: BLE001 - handed to whoever waits for the index
            self._index_error = exc
            log.error("ground-truth image index of %s failed: %s", self.root, exc)
            return
        self._index = index
        log.info("ground-truth image index of %s: %d frames, %d anchor runs in %.1f s", self.root, len(self._reader), len(index.hashes), time.perf_counter() - t0)

    def _image_index(self) -> _ImageIndex:
        self.prepare_images(background=False)
        if self._index is None:
            raise GroundTruthError(f"the image index of {self.root} could not be built: {self._index_error}")
        return self._index

    def locate(self, rgb: RGB) -> tuple[int, int, int]:
        """(frame index, top, left) of the sequence frame ``rgb`` was cut from."""
        rgb = _check_rgb(rgb)
        h, w = rgb.shape[:2]
        if h < ROW_STEP or w < RUN_PX:
            raise GroundTruthError(f"an image of {w}x{h} pixels is too small to find in the sequence {self.root} (at least {RUN_PX}x{ROW_STEP})")
        if h > self.shape[0] or w > self.shape[1]:
            raise GroundTruthError(f"an image of {w}x{h} pixels is larger than the frames of the sequence {self.root} ({self.shape[1]}x{self.shape[0]})")
        placements = self._image_index().placements(rgb)
        for f, top, left in placements:
            if np.array_equal(self._rgb(f)[top : top + h, left : left + w], rgb):
                return f, top, left
        # A small crop may hold no anchor run at all: say so, it is the likelier cause then.
        hint = "" if placements or h * w >= 32 * 32 else " (a crop smaller than about 32x32 pixels may hold too few distinctive runs to be found)"
        raise GroundTruthError(
            f"an image of {w}x{h} pixels is neither a frame of the sequence {self.root} nor a crop of one, pixel for pixel: "
            f"the {self.user} knows the ground truth of that sequence's own pixels only (an image sent as JPEG, resized or "
            f"taken elsewhere has none){hint}"
        )

    def image_instances(self, rgb: RGB) -> Instances:
        f, top, left = self.locate(rgb)
        h, w = rgb.shape[:2]
        return self._instances(f)[top : top + h, left : left + w]


class StaticGroundTruth:
    """Ground truth held in memory: instance ids per frame index, and whole images with their
    ids for image queries (tests, and callers that already have the arrays)."""

    def __init__(self, frames: Mapping[int, Instances], images: Sequence[tuple[RGB, Instances]] = ()) -> None:
        self._frames = {int(k): np.asarray(v, np.int32) for k, v in frames.items()}
        self._images: dict[bytes, Instances] = {}
        for rgb, ids in images:
            rgb = _check_rgb(rgb)
            ids = np.asarray(ids, np.int32)
            if ids.shape != rgb.shape[:2]:
                raise ValueError(f"instances of shape {ids.shape} for an image of shape {rgb.shape[:2]}")
            self._images[_digest(rgb)] = ids

    def frame_instances(self, frame_index: int) -> Instances:
        ids = self._frames.get(int(frame_index))
        if ids is None:
            known = ", ".join(str(k) for k in sorted(self._frames)[:8]) or "none"
            raise GroundTruthError(f"frame_index {frame_index} has no ground truth (frames known: {known})")
        return ids

    def image_instances(self, rgb: RGB) -> Instances:
        rgb = _check_rgb(rgb)
        ids = self._images.get(_digest(rgb))
        if ids is None:
            h, w = rgb.shape[:2]
            raise GroundTruthError(f"an image of {w}x{h} pixels is none of the {len(self._images)} images with ground truth")
        return ids


def _check_rgb(rgb: np.ndarray) -> RGB:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise GroundTruthError(f"expected an (H, W, 3) uint8 image, got {rgb.dtype} {rgb.shape}")
    return np.ascontiguousarray(rgb)


def _digest(rgb: RGB) -> bytes:
    return hashlib.blake2b(np.ascontiguousarray(rgb).tobytes() + repr(rgb.shape).encode(), digest_size=16).digest()
