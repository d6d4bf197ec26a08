"""``trackgraph query MAP_DIR "TEXT"``: the query core on a saved map, no Zenoh.

The map's newest snapshot gives the segments and the rooms (with their features); queries are embedded with the encoder of the
map's own resolved config (``MAP_DIR/config.yaml``, written by ``trackgraph map`` and the
fusion service), or of ``--config``, so the query lands in the space the galleries are in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.query.core import QueryEngine, QueryError, QueryIndex
from shared.config.root import TrackGraphConfig
from shared.messages.rpc import EmbedRequest, QueryReply, QueryRequest


def load_index(map_dir: Path, min_view_share: float = 0.0) -> QueryIndex:
    """The query index of the newest good snapshot in ``MAP_DIR/graph``."""
    from shared.graph.store import MapStore, StoreError

    store = MapStore(Path(map_dir) / "graph")
    if store.latest_name() is None:
        raise QueryError(f"{map_dir}: no map snapshot in {Path(map_dir) / 'graph'} (is this a trackgraph map folder?)")
    try:
        snap = store.load().snapshot
    except StoreError as exc:
        raise QueryError(f"{map_dir}: {exc}") from None
    return QueryIndex.build(snap.graph_seq, snap.segments, snap.rooms, min_view_share=min_view_share)


def map_config(map_dir: Path, override: Path | str | None = None, sets: list[str] | None = None) -> TrackGraphConfig:
    """The config a saved map was made with (``MAP_DIR/config.yaml``), or ``override`` (a file
    or a preset's name), with ``sets`` (``KEY=VALUE``) on top."""
    from shared.config import load_config

    if override is not None:
        return load_config(override, sets or [])
    path = Path(map_dir) / "config.yaml"
    if not path.is_file():
        raise QueryError(f"{path}: no config to build the query encoder from; pass --config FILE")
    return load_config(path, sets or [])


class OfflineQueries:
    """A saved map and a local encoder; answers any number of queries."""

    def __init__(self, map_dir: Path, cfg: TrackGraphConfig | None = None) -> None:
        from services.keyframe_vl.embedder import Embedder
        from shared.devices import resolve_device
        from shared.perception.encoders import make_vl_encoder

        self.cfg = cfg or map_config(map_dir)
        self.index = load_index(map_dir, self.cfg.query.min_view_share)
        encoder = make_vl_encoder(
            self.cfg.keyframe_vl.vl, device=resolve_device(self.cfg.query.device, "query.device"), fp16=self.cfg.keyframe_vl.fp16
        )
        self.embedder = Embedder(encoder, self.cfg.keyframe_vl.embed_cache_size)
        self.engine = QueryEngine(self.cfg.query, self._embed, self.cfg.fusion.graph.room_labels)

    def _embed(self, req: EmbedRequest) -> np.ndarray:
        reply = self.embedder.embed(req)
        if reply.error is not None or reply.embedding is None:
            raise QueryError(f"cannot embed the query: {reply.error or 'no embedding returned'}")
        return reply.embedding

    def ask(self, req: QueryRequest) -> QueryReply:
        return self.engine.answer(self.index, req)


class MapTextEncoder:
    """The text tower of a map's own VL encoder, as the evaluation's ``TextEncoder``: a map
    built with CLIP is scored in CLIP's space, not in the MiniLM space of simulated maps."""

    def __init__(self, cfg: TrackGraphConfig) -> None:
        from shared.devices import resolve_device
        from shared.perception.encoders import make_vl_encoder

        self._encoder = make_vl_encoder(
            cfg.keyframe_vl.vl, device=resolve_device(cfg.query.device, "query.device"), fp16=cfg.keyframe_vl.fp16
        )
        self.name = self._encoder.name
        self.dim = int(self._encoder.dim)

    def encode(self, texts: list[str]) -> np.ndarray:
        return self._encoder.encode_text(list(texts))


def map_text_encoder(map_dir: Path, cfg: TrackGraphConfig | None = None):
    """The text encoder to score ``map_dir`` with: MiniLM for the simulated VL backend (its
    labels are MiniLM embeddings), else the map's own encoder from its ``config.yaml``."""
    from shared.eval.text import default_encoder

    cfg = cfg or map_config(map_dir)
    if cfg.keyframe_vl.vl.backend == "simulated":
        return default_encoder()
    return MapTextEncoder(cfg)
