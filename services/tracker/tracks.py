"""Source tracks (paper III-B): identity, aggregated DINOv3 and CLIP features.

Besides the paper's tuple, a track remembers the 3D footprint of its keyframe masks, and
the book keeps tracks that went unmatched in a bounded *lost* pool instead of dropping them at
once (see ``services.tracker.core`` for why and how they come back).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from services.tracker.association import ema, running_mean
from services.tracker.footprints import Footprint

MAX_LOST = 256
"""Lost tracks kept for re-identification; the longest-lost are retired beyond this."""


@dataclass
class Track:
    """tau_i = (id_i, f_dino, f_ov, n_ov), plus when it was last detected and where."""

    id: int
    dino: Annotated[np.ndarray, "(D,) float32 unit"]
    last_detection: int
    """Processed-frame count of the last keyframe detection assigned to the track."""
    clip: Annotated[np.ndarray, "(Dc,) float32"] | None = None
    clip_count: int = 0
    footprint: Footprint | None = None
    """World points under the keyframe masks assigned to the track (``footprints``); None
    once the track is retired."""

    def detected(self, feature: np.ndarray, count: int, eta: float) -> None:
        self.dino = ema(self.dino, feature, eta)
        self.last_detection = count

    def add_clip(self, feature: np.ndarray) -> None:
        self.clip, self.clip_count = running_mean(self.clip, self.clip_count, feature)


@dataclass
class TrackBook:
    """All tracks ever made; ``active`` ids are the ones propagated, ``lost`` ids the ones
    that may still be re-identified (oldest first)."""

    tracks: dict[int, Track] = field(default_factory=dict)
    active: list[int] = field(default_factory=list)
    lost: OrderedDict[int, int] = field(default_factory=OrderedDict)
    """Lost track id -> processed-frame count at which it went unmatched."""
    next_id: int = 0
    changed: set[int] = field(default_factory=set)
    retired: list[int] = field(default_factory=list)
    max_lost: int = MAX_LOST

    def new(self, feature: np.ndarray, count: int) -> Track:
        t = Track(id=self.next_id, dino=feature.astype(np.float32), last_detection=count)
        self.tracks[t.id] = t
        self.next_id += 1
        self.changed.add(t.id)
        return t

    def lose(self, ids: list[int], count: int) -> None:
        """Active tracks that went unmatched: kept for re-identification, the pool bounded."""
        for tid in ids:
            self.lost[tid] = count
            self.lost.move_to_end(tid)
        while len(self.lost) > self.max_lost:
            tid, _ = self.lost.popitem(last=False)
            self._retire(tid)

    def revive(self, tid: int) -> None:
        del self.lost[tid]

    def retire(self, ids: list[int]) -> None:
        """Lost tracks that will not be re-identified any more."""
        for tid in ids:
            del self.lost[tid]
            self._retire(tid)

    def _retire(self, tid: int) -> None:
        # The track object stays: frames propagated before its retirement still carry its id,
        # and late CLIP features still fold into its mean. Only re-identification reads the
        # footprint (up to 4,000 points), so it goes; keeping it grew a live tracker without bound.
        self.tracks[tid].footprint = None
        self.retired.append(tid)

    def take_changes(self) -> tuple[list[Track], list[int]]:
        """Tracks changed and retired since the last call (for ``tracks/features``)."""
        changed = [self.tracks[i] for i in sorted(self.changed)]
        retired = list(self.retired)
        self.changed.clear()
        self.retired.clear()
        return changed, retired
