"""Whether keyframe_vl keeps up: when each keyframe was asked for, when its masks and its CLIP
features came back, and which never did.

A live tracker never waits for masks, so a keyframe_vl slower than the keyframe rate does not
stop the stream: its answers just come later and later, or are dropped, and the tracker
propagates on stale labels. Frame drops alone cannot show that, so the input-rate search
(``services.bench.rate``) also asks this ledger whether every keyframe was answered and
whether the answers kept the requests' pace.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class KeyframeLedger:
    """Times (monotonic seconds) of every keyframe's request, masks and features."""

    asked: dict[int, float] = field(default_factory=dict)
    masked: dict[int, float] = field(default_factory=dict)
    done: dict[int, float] = field(default_factory=dict)
    failed: int = 0
    """Answers that carried an error, from segmentation or CLIP."""
    stale: int = 0
    """Masks that came after their keyframe had left the tracker's history."""
    timed_out: int = 0
    """Keyframes with no masks after ``tracker.keyframe_timeout_s``."""

    def request(self, frame_index: int, t: float) -> None:
        self.asked[frame_index] = t

    def masks(self, frame_index: int, t: float) -> None:
        if frame_index in self.asked:
            self.masked[frame_index] = t

    def features(self, frame_index: int, t: float) -> None:
        if frame_index in self.masked:
            self.done[frame_index] = t

    def as_dict(self) -> dict:
        """Counts, answer latency and the two rates: requests per second and answers (CLIP
        features, a keyframe's last reply) per second, each first to last."""
        lat = [self.done[k] - self.asked[k] for k in self.done]
        return {
            "requested": len(self.asked),
            "masks": len(self.masked),
            "answered": len(self.done),
            "failed": self.failed,
            "stale": self.stale,
            "timed_out": self.timed_out,
            "latency_max_s": round(max(lat), 3) if lat else None,
            "latency_mean_s": round(sum(lat) / len(lat), 3) if lat else None,
            "request_hz": _rate(list(self.asked.values())),
            "answer_hz": _rate(list(self.done.values())),
        }


def _rate(times: list[float]) -> float | None:
    if len(times) < 2:
        return None
    span = max(times) - min(times)
    return round((len(times) - 1) / span, 6) if span > 0 else None


def kept_up(stats: dict, share: float) -> bool:
    """Every keyframe answered without error, and answered at ``share`` of the request rate
    or faster (a trial needs two keyframes for that; with one, being answered is all). A
    tracker that asks for none (``ground_truth`` mode) keeps up by definition."""
    n = stats.get("requested") or 0
    if n == 0:
        return True
    if stats.get("answered") != n or stats.get("failed") or stats.get("stale") or stats.get("timed_out"):
        return False
    if n < 2:
        return True
    req, ans = stats.get("request_hz"), stats.get("answer_hz")
    return req is not None and ans is not None and ans >= share * req
