"""keyframe_vl node: a :class:`~services.keyframe_vl.session.KeyframeVLSession` on Zenoh.

CLIP runs on the node's inbox worker behind a bounded queue, so the next keyframe's masks
never wait for the previous keyframe's features; when CLIP falls 8 keyframes behind, the
request subscription waits for room (its queue then drops, counted) rather than letting
the backlog grow.
"""

from __future__ import annotations

import logging
import time

from services.keyframe_vl.core import KeyframeVLCore
from services.keyframe_vl.session import ClipJob, KeyframeVLSession
from shared.config.root import TrackGraphConfig
from shared.runtime.adapter import SessionNode, open_bus, session_attr
from shared.runtime.status import StatusBook

log = logging.getLogger(__name__)

CLIP_QUEUE = 8
"""Keyframes whose masks are out and whose CLIP features wait for the CLIP worker."""


class KeyframeVLNode(SessionNode):
    """Wires a :class:`KeyframeVLCore` to Zenoh; ``close()`` undeclares everything.

    The node is alive (liveliness token, status ``running``) only once its models are loaded
    and their text path has run once (:meth:`start`): ``vl/embed`` is declared then too, so a
    query service's warm-up, and the first novel text after it, never wait for a model load.
    With ``start=False`` the caller calls :meth:`start` itself, after it has begun publishing
    ``book``'s reports (``trackgraph serve``: state ``starting`` while the models load).
    """

    requests = session_attr("requests")
    embed = session_attr("embed")

    def __init__(self, cfg: TrackGraphConfig, core: KeyframeVLCore | None = None, session=None, *, start: bool = True) -> None:
        self.cfg = cfg
        self.core = core
        super().__init__(
            open_bus(cfg, session), self._make_session, name="keyframe_vl", inbox=CLIP_QUEUE, alive="keyframe_vl",
            # State ``starting`` until start() is done; the session counts in it after.
            book=StatusBook("keyframe_vl"), start=start,
        )  # fmt: skip

    def start(self) -> None:
        """Load the models (unless a core was given), warm the text path up, then serve and
        declare the node alive. Raises what the models' loading raises; once started, does nothing."""
        from services.keyframe_vl.build import build_keyframe_vl

        if self.session is not None:
            return

        t0 = time.monotonic()
        core = self.core or build_keyframe_vl(self.cfg)
        warm = getattr(core, "warm_up", None)  # a stand-in core may have none
        if warm is not None:
            warm()
        self.core = core
        self.book.figure("startup_s", round(time.monotonic() - t0, 3))
        super().start()
        log.info("keyframe_vl ready in %.1f s (models loaded, text path warm)", time.monotonic() - t0)

    def _make_session(self, bus) -> KeyframeVLSession:
        return KeyframeVLSession(bus, self.core, defer_clip=self._defer_clip, book=self.book)

    def _defer_clip(self, job: ClipJob) -> None:
        # On the request subscription's thread: waiting here for room is the backpressure.
        self.inbox.put("clip", lambda: self.session.run_clip(job))

    @property
    def processed(self) -> int:
        return self.session.processed if self.session is not None else 0

    @property
    def failed(self) -> int:
        return self.session.failed if self.session is not None else 0

    def stats(self) -> dict:
        if self.session is None:
            return {"state": self.book.state}
        return {
            "processed": self.session.processed,
            "failed": self.session.failed,
            "requests": self.requests.stats.as_dict(),
            "embed": self.embed.stats.as_dict(),
        }


def build(cfg, *, out=None, resume: bool = False) -> KeyframeVLNode:
    """``trackgraph serve keyframe_vl``: models load in start(), once the status reports (state
    ``starting``) go out."""
    return KeyframeVLNode(cfg, start=False)
