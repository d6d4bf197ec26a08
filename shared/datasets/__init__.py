"""Dataset readers (docs/architecture.md, "Input formats") behind one factory, :func:`open_sequence`,
and one registry, ``DATASETS``: a reader is a :class:`SequenceReader` in a module of its own,
registered here with one line. A reader of one image file per frame builds on
:class:`shared.datasets.folder.FolderReader`, which reads and checks the frames."""

from __future__ import annotations

from pathlib import Path

from shared.config.source import SourceConfig
from shared.datasets.base import DATASETS, DatasetError, SequenceReader
from shared.registry import load_object

__all__ = ["DATASETS", "DatasetError", "SequenceReader", "open_sequence"]

DATASETS.register("replica", "shared.datasets.replica:ReplicaReader")
DATASETS.register("scannetpp", "shared.datasets.scannetpp:ScanNetppReader")
DATASETS.register("hm3d", "shared.datasets.hm3d:Hm3dReader")
DATASETS.register("tum", "shared.datasets.tum:TumReader")
DATASETS.register("rosbag", "shared.datasets.rosbag:RosbagReader")


def open_sequence(path: Path | str, dataset: str = "replica", config: SourceConfig | None = None) -> SequenceReader:
    """Open the sequence at ``path`` with the reader registered for ``dataset``.

    ``config`` supplies the TUM association limit and the ROS bag topics; the other readers
    need nothing from it. Raises ValueError for an unknown dataset name (naming the choices),
    DatasetError for a bad sequence.
    """
    reader: type[SequenceReader] = load_object(DATASETS.get(dataset))
    return reader.open(path, config or SourceConfig())
