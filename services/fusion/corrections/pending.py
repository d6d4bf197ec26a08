"""Pose corrections a fusion session received and has not applied yet: each waits until the
map has fused its ``apply_after_frame`` (at once without one), then moves the map. Counted
in the session's status; kept in snapshots as JSON lines, since the journal is cut there."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np

from services.fusion.corrections.poses import CorrectionError
from shared.messages.poses import PoseCorrection, parse_correction

if TYPE_CHECKING:
    from services.fusion.protocol import FusionCoreLike
    from shared.messages.graph import GraphDelta
    from shared.runtime.status import StatusBook

log = logging.getLogger(__name__)


class PendingCorrections:
    """The waiting corrections of ``core``, in arrival order; refusals and failures are
    counted in ``book`` under ``poses_correction``."""

    def __init__(self, core: FusionCoreLike, book: StatusBook) -> None:
        self.core, self.book = core, book
        self.pending: list[PoseCorrection] = []
        """Received and not applied yet, in arrival order."""
        self.error: str | None = None
        """Why the newest refused correction was refused."""

    def __len__(self) -> int:
        return len(self.pending)

    def apply_due(self, publish: Callable[[GraphDelta], Any], final: bool = False, before: Callable[[], Any] | None = None) -> None:
        """Apply every correction that is due (``final``: all of them, at the map's end); each
        graph update after a move goes to ``publish``. ``before`` runs first when any is due
        (the session waits there for the map path's running update)."""
        last = self.core.last_frame_index
        due = [c for c in self.pending if final or c.apply_after_frame is None or last >= c.apply_after_frame]
        if due and before is not None:
            before()
        # by identity: models holding arrays do not compare with ==
        self.pending = [c for c in self.pending if all(c is not d for d in due)]
        for c in due:
            try:
                out = self.core.apply_correction(c)
            except CorrectionError as exc:
                self.error = f"correction {c.correction_id} refused: {exc}"
                self.book.count("poses_correction", "rejected")
                self.book.error()
                log.error("fusion: %s", self.error)
                continue
            except Exception:  # noqa: BLE001 - one bad correction must not stop the map
                self.book.count("poses_correction", "rejected")
                self.book.error()
                log.exception("fusion failed on PoseCorrection %d", c.correction_id)
                continue
            self.book.count("poses_correction", "processed")
            if out.delta is not None:
                publish(out.delta)

    def figure(self) -> dict[str, Any]:
        """The ``corrections`` status figure: the core's counters, what waits, the last refusal."""
        return {**self.core.corrections.as_dict(), "pending": len(self.pending), "last_error": self.error}

    def state(self) -> Annotated[np.ndarray, "(B,) uint8"]:
        """The waiting corrections as JSON lines, for a snapshot."""
        return np.frombuffer("\n".join(c.to_json() for c in self.pending).encode(), np.uint8).copy()

    def load(self, state: Annotated[np.ndarray, "(B,) uint8"]) -> None:
        """Back from :meth:`state`."""
        text = bytes(np.asarray(state, np.uint8)).decode()
        self.pending = [parse_correction(json.loads(line)) for line in text.splitlines() if line.strip()]
