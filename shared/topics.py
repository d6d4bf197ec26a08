"""Every Zenoh key expression of the system, built from the robot id (the contract: docs/wire.md)."""

from __future__ import annotations

from dataclasses import dataclass

from shared.config.root import ROBOT_ID

PREFIX = "trackgraph"



def service_names() -> tuple[str, ...]:
    """Services that announce themselves with a liveliness token: the services registry's."""
    from shared.registry import SERVICES

    return SERVICES.names()


@dataclass(frozen=True)
class Topics:
    """Key expressions under ``trackgraph/<robot_id>/``."""

    robot_id: str

    def __post_init__(self) -> None:
        if not ROBOT_ID.match(self.robot_id):
            raise ValueError(f"robot id {self.robot_id!r} must be letters, digits, '_' or '-'")

    @property
    def root(self) -> str:
        return f"{PREFIX}/{self.robot_id}"

    @property
    def frames(self) -> str:
        return f"{self.root}/frames"

    @property
    def end_of_sequence(self) -> str:
        return f"{self.root}/frames/end"

    @property
    def frame_ack(self) -> str:
        return f"{self.root}/frames/ack"

    @property
    def keyframe_request(self) -> str:
        return f"{self.root}/keyframe/request"

    @property
    def keyframe_masks(self) -> str:
        return f"{self.root}/keyframe/masks"

    @property
    def keyframe_features(self) -> str:
        return f"{self.root}/keyframe/features"

    @property
    def tracks_frame(self) -> str:
        return f"{self.root}/tracks/frame"

    @property
    def tracks_features(self) -> str:
        return f"{self.root}/tracks/features"

    @property
    def tracks_end(self) -> str:
        return f"{self.root}/tracks/end"

    @property
    def poses_correction(self) -> str:
        return f"{self.root}/poses/correction"

    @property
    def graph_delta(self) -> str:
        return f"{self.root}/graph/delta"

    @property
    def graph_snapshot(self) -> str:
        return f"{self.root}/graph/snapshot"

    @property
    def vl_embed(self) -> str:
        return f"{self.root}/vl/embed"

    @property
    def query(self) -> str:
        return f"{self.root}/query"

    def alive(self, service: str) -> str:
        """Liveliness token key of one service."""
        _check_service(service)
        return f"{self.root}/alive/{service}"

    def status(self, service: str) -> str:
        """Key of one service's :class:`~shared.messages.status.ServiceStatus` reports."""
        _check_service(service)
        return f"{self.root}/status/{service}"

    @property
    def status_all(self) -> str:
        return f"{self.root}/status/*"

    @property
    def alive_all(self) -> str:
        return f"{self.root}/alive/*"

    def all_keys(self) -> dict[str, str]:
        """Name -> key of every data key (for docs, ACL files and fuzz tests)."""
        names = (
            "frames", "end_of_sequence", "frame_ack", "keyframe_request", "keyframe_masks", "keyframe_features",
            "tracks_frame", "tracks_features", "tracks_end", "graph_delta", "graph_snapshot", "vl_embed", "query",
        )  # fmt: skip
        return {n: getattr(self, n) for n in names}


def service_of_alive_key(key: str) -> str:
    """The service name at the end of an ``alive/<service>`` key."""
    return key.rsplit("/", 1)[-1]


def _check_service(service: str) -> None:
    from shared.registry import SERVICES

    if service not in SERVICES:
        raise ValueError(SERVICES.unknown(service))
