"""The query service's room ranking on a saved map, as ``trackgraph eval rooms`` and the
bench ask it: "which room is the X" (``QueryRequest.target: rooms``) through the query core
and the map's own encoder, exactly as ``trackgraph query MAP_DIR --rooms`` answers."""

from __future__ import annotations

import logging
from pathlib import Path

from services.query.offline import OfflineQueries, map_config
from shared.eval.errors import EvalInputError
from shared.eval.rooms import RoomRanker
from shared.messages.rpc import QueryRequest

log = logging.getLogger(__name__)


def map_room_ranker(map_dir: str | Path) -> RoomRanker | None:
    """Ranks ``map_dir``'s rooms for a text, or None when the map has no room features (a map
    written before rooms had them, or without a VL encoder's views and galleries)."""
    map_dir = Path(map_dir)
    offline = OfflineQueries(map_dir, map_config(map_dir))
    if not offline.index.room_features_count:
        log.info("%s: no room has a feature; the room-type queries are left out", map_dir)
        return None

    def rank(text: str) -> list[int]:
        reply = offline.ask(QueryRequest(text=text, target="rooms", top_k=offline.cfg.query.max_top_k))
        if reply.error is not None:
            raise EvalInputError(map_dir, f"room query {text!r} refused: {reply.error}")
        return [h.room for h in reply.rooms]

    return rank
