"""Dataset readers (docs/architecture.md, "Input formats") behind one factory, :func:`open_sequence`."""

from __future__ import annotations

from pathlib import Path

from shared.config.source import SourceConfig
from shared.datasets.base import DatasetError, SequenceReader

DATASETS = ("replica", "scannetpp", "hm3d", "tum", "rosbag")

__all__ = ["DATASETS", "DatasetError", "SequenceReader", "open_sequence"]


def open_sequence(path: Path | str, dataset: str = "replica", config: SourceConfig | None = None) -> SequenceReader:
    """Open the sequence at ``path`` with the reader for ``dataset``.

    ``config`` supplies the TUM association limit and the ROS bag topics; the other readers
    need nothing from it. Raises ValueError for an unknown dataset name, DatasetError for a
    bad sequence.
    """
    cfg = config or SourceConfig()
    if dataset == "replica":
        from shared.datasets.replica import ReplicaReader

        return ReplicaReader(path)
    if dataset == "scannetpp":
        from shared.datasets.scannetpp import ScanNetppReader

        return ScanNetppReader(path)
    if dataset == "hm3d":
        from shared.datasets.hm3d import Hm3dReader

        return Hm3dReader(path)
    if dataset == "tum":
        from shared.datasets.tum import TumReader

        return TumReader(path, cfg.tum)
    if dataset == "rosbag":
        # rosbags is only imported for bags: it is a heavy import the other readers never need.
        from shared.datasets.rosbag import RosbagReader

        return RosbagReader(path, cfg.rosbag)
    raise ValueError(f"unknown dataset {dataset!r}; choose one of: {', '.join(DATASETS)}")
