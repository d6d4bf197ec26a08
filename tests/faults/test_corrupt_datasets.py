"""``trackgraph map`` and the source on a corrupted sequence: a truncated PNG, a NaN pose and a
zero-byte image each cost their frame only. The frame is refused with an error naming the
file, counted in ``run.json``, and every other frame is still mapped."""

from __future__ import annotations

import json
import shutil

import pytest

from services.mapping import run_map
from shared.config import TrackGraphConfig

pytestmark = pytest.mark.faults

FRAMES = 12


def config() -> TrackGraphConfig:
    return TrackGraphConfig.model_validate({
        "keyframe_vl": {"segmenter": {"backend": "simulated"}, "vl": {"backend": "simulated"}},
        "tracker": {"features": {"backend": "classical", "short_side": 240}, "device": "cpu"},
        "source": {"max_frames": FRAMES},
    })  # fmt: skip


def corrupt(seq) -> dict[int, str]:
    """Three frames broken three ways; returns frame -> the file its error must name."""
    res = seq / "results"
    depth = res / "depth000003.png"
    depth.write_bytes(depth.read_bytes()[: depth.stat().st_size // 3])
    lines = (seq / "traj.txt").read_text().splitlines()
    values = lines[5].split()
    values[3] = "nan"
    lines[5] = " ".join(values)
    (seq / "traj.txt").write_text("\n".join(lines) + "\n")
    (res / "frame000008.jpg").write_bytes(b"")
    return {3: str(depth), 5: f"{seq / 'traj.txt'}:6", 8: str(res / "frame000008.jpg")}


@pytest.mark.slow
def test_map_skips_and_counts_corrupt_frames(small, tmp_path):
    seq = tmp_path / "seq"
    shutil.copytree(small, seq)
    broken = corrupt(seq)
    summary = run_map(seq, config(), tmp_path / "map", progress=False)
    assert summary["frames"] == FRAMES - 3 and summary["frames_rejected"] == 3
    for (frame, where), msg in zip(sorted(broken.items()), summary["rejected"], strict=True):
        assert where in msg, (frame, msg)
    assert json.loads((tmp_path / "map" / "run.json").read_text())["frames_rejected"] == 3
    assert summary["segments"] > 3


def test_source_replay_skips_and_counts_corrupt_frames(small, tmp_path):
    from services.source.core import replay
    from shared.config.source import SourceConfig
    from shared.datasets import open_sequence

    seq = tmp_path / "seq"
    shutil.copytree(small, seq)
    broken = corrupt(seq)
    sent: list[int] = []
    stats = replay(open_sequence(seq), SourceConfig(mode="lossless", max_frames=FRAMES), lambda f: sent.append(f.frame_index))
    assert stats.rejected == 3 and stats.published == FRAMES - 3
    assert sent == [i for i in range(FRAMES) if i not in broken]


def test_a_sequence_with_no_readable_frame_is_refused(small, tmp_path):
    from shared.datasets.base import DatasetError

    seq = tmp_path / "seq"
    shutil.copytree(small, seq)
    for jpg in (seq / "results").glob("frame*.jpg"):
        jpg.write_bytes(b"")
    with pytest.raises(DatasetError, match="no frame could be read"):
        run_map(seq, config().model_copy(update={"source": config().source.model_copy(update={"max_frames": 3})}), tmp_path / "map", progress=False)
