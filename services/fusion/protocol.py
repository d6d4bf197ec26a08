"""What a fusion session drives of its core: :class:`~services.fusion.core.FusionCore` has all
of it, and so do the tests' doubles, so the session never asks a core what it has."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np

    from services.fusion.core import CorrectionOutcome
    from services.fusion.corrections.observations import ObservationLog
    from shared.messages.frames import TrackedFrame
    from shared.messages.graph import GraphDelta, GraphSnapshot
    from shared.messages.keyframes import TrackFeatures
    from shared.messages.poses import PoseCorrection


class GraphLike(Protocol):
    """The scene graph, as far as the session numbers its deltas."""

    graph_seq: int


class SegmentsLike(Protocol):
    """The segment layer, as far as the session counts segments."""

    segments: dict[int, Any]


class CountersLike(Protocol):
    """The core's pose-correction counters (the ``corrections`` status figure)."""

    def as_dict(self) -> dict[str, Any]: ...


@runtime_checkable
class FusionCoreLike(Protocol):
    """Tracked frames and feature messages in, graph deltas out; pose corrections, the room
    vocabulary, snapshots and the state a snapshot keeps."""

    frames: int
    """Frames in the map (across restarts)."""
    last_frame_index: int
    """Index of the newest frame fused; -1 before the first."""
    graph: GraphLike
    segments: SegmentsLike
    corrections: CountersLike
    observations: ObservationLog | None
    """The fused frames kept for a re-fusion (``fusion.refuse``); the session opens it."""
    room_vocabulary: Any
    """The room labels' embeddings once :meth:`set_room_vocabulary` gave them; None before."""

    def add_frame(self, tf: TrackedFrame) -> GraphDelta | None: ...

    def add_track_features(self, msg: TrackFeatures) -> None: ...

    def apply_correction(self, c: PoseCorrection) -> CorrectionOutcome: ...

    def set_room_vocabulary(self, labels: list[str], embeddings: Annotated[np.ndarray, "(L, D) float32"]) -> None: ...

    def finish(self) -> GraphDelta: ...

    def snapshot(self, with_mesh: bool = False, whole_map: bool = False) -> GraphSnapshot: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any], snapshot: GraphSnapshot) -> None: ...
