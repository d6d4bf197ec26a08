"""Data passed between the fusion stages: TSDF -> mesh -> segments -> graph."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import numpy as np


@dataclass
class HypothesisMesh:
    """Marching-cubes mesh of the active window; each vertex inherits its voxel's hypotheses
    H = {(tau_k, l_k)} (III-C)."""

    vertices: Annotated[np.ndarray, "(V, 3) float32 world metres"]
    colors: Annotated[np.ndarray, "(V, 3) uint8"]
    faces: Annotated[np.ndarray, "(F, 3) int32"]
    hyp_ids: Annotated[np.ndarray, "(V, K) int32 track ids, -1 = empty slot"]
    hyp_weights: Annotated[np.ndarray, "(V, K) float32 accumulated weights l"]
    anchors: Annotated[np.ndarray, "(V,) int32 frame index, -1 = unknown"] | None = None
    """The frame each vertex's voxel was last fused from (a pose correction moves it with
    that frame); None where the mesh was not read from a grid."""

    def vertex_anchors(self) -> Annotated[np.ndarray, "(V,) int32"]:
        return self.anchors if self.anchors is not None else np.full(len(self), -1, np.int32)

    def __len__(self) -> int:
        return int(self.vertices.shape[0])

    def winners(self) -> Annotated[np.ndarray, "(V,) int32 winning track per vertex, -1 = none"]:
        """tau* = argmax_k l_k per vertex (III-D); -1 where no slot is filled."""
        if len(self) == 0:
            return np.zeros(0, np.int32)
        w = np.where(self.hyp_ids >= 0, self.hyp_weights, -np.inf)
        k = np.argmax(w, axis=1)
        win = self.hyp_ids[np.arange(len(self)), k]
        return np.where(np.isfinite(w.max(axis=1)), win, -1).astype(np.int32)

    @staticmethod
    def empty(k: int) -> HypothesisMesh:
        return HypothesisMesh(
            np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.int32),
            np.full((0, k), -1, np.int32), np.zeros((0, k), np.float32),
        )  # fmt: skip


@dataclass
class TrackState:
    """What fusion knows of one source track (tau_i in III-B), from ``tracks/features``."""

    track_id: int
    dino: Annotated[np.ndarray, "(D,) float32 unit"] | None = None
    clip: Annotated[np.ndarray, "(Dc,) float32"] | None = None
    clip_count: int = 0
    displaced_weight: float = 0.0
    """Weight this track lost to slot replacement (III-C); still counted by the segments."""
    retired: bool = False
    extra: dict = field(default_factory=dict)
