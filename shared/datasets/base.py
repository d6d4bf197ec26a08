"""One interface for every dataset reader: an indexed sequence of :class:`Frame`.

Poses are camera-to-world in OpenCV camera axes (x right, y down, z forward), whatever the
format stores; readers convert. Every error names the file it comes from.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, ClassVar

import numpy as np

from shared.geometry import Intrinsics, Pose
from shared.messages.frames import Frame
from shared.registry import Registry

if TYPE_CHECKING:
    from shared.config.source import SourceConfig

DATASETS: Registry[str] = Registry("dataset", modules=("shared.datasets",))
"""Dataset readers by name (``source.dataset``, ``--dataset``): ``"module:ReaderClass"``,
registered in shared/datasets/__init__.py and imported only when a sequence is opened (the bag
reader imports rosbags, which the other readers never need)."""


class DatasetError(ValueError):
    """A dataset file is missing, unreadable or inconsistent. The message names the file."""


class SequenceReader(ABC):
    """A recorded RGB-D sequence with poses."""

    root: Path
    intrinsics: Intrinsics
    depth_scale: float
    options: ClassVar[str | None] = None
    """The section of the source config this reader takes as its second argument (``"tum"``
    for TUM's association limit, ``"rosbag"`` for a bag's topics); None: it takes none."""

    @classmethod
    def open(cls, path: Path | str, config: SourceConfig) -> SequenceReader:
        """The reader of the sequence at ``path``; ``config`` is the source config."""
        return cls(path, getattr(config, cls.options)) if cls.options else cls(path)

    @abstractmethod
    def __len__(self) -> int:
        """Number of frames."""

    @abstractmethod
    def pose(self, i: int) -> Pose:
        """Camera-to-world pose of frame ``i`` (OpenCV axes)."""

    @abstractmethod
    def frame(self, i: int) -> Frame:
        """Load frame ``i`` (RGB, depth, intrinsics, pose)."""

    def instances(self, i: int) -> Annotated[np.ndarray, "(H, W) int32 object id, -1 = none"] | None:
        """Ground-truth instance ids of frame ``i`` where the dataset has them (synthetic
        sequences), else None. Evaluation and the simulated perception backends read them here:
        ground truth never travels in a :class:`Frame`."""
        return None

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    def poses(self) -> np.ndarray:
        """(N, 4, 4) all poses."""
        return np.stack([self.pose(i) for i in range(len(self))]) if len(self) else np.zeros((0, 4, 4))

    def close(self) -> None:
        """Release open files (a ROS bag); folder readers hold none. Safe to call twice."""
        return None

    def __enter__(self) -> SequenceReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
