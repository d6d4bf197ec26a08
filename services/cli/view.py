"""``trackgraph view``: a Rerun recording of a saved map, optional query hits and PNG renders."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from services.cli.common import CommandError


def _cmd_view(args: argparse.Namespace) -> int:
    from shared.graph.store import MapStore

    map_dir = args.map_dir
    if not (map_dir / "graph").is_dir():
        raise CommandError(f"{map_dir}: no graph/ folder (is it a trackgraph map folder?)")
    queries = {}
    if args.query:
        from services.query.core import QueryError
        from services.query.offline import OfflineQueries, map_config
        from shared.messages.rpc import QueryRequest

        try:
            offline = OfflineQueries(map_dir, map_config(map_dir, args.config, args.set))
        except QueryError as exc:
            raise CommandError(str(exc)) from None
        for text in args.query:
            reply = offline.ask(QueryRequest(text=text, top_k=args.top_k))
            if reply.error is not None:
                raise CommandError(f"query {text!r} refused: {reply.error}")
            queries[text] = reply.hits
    from services.viewer.recording import write_map_recording

    out = args.out or map_dir / "map.rrd"
    try:
        write_map_recording(map_dir, out, queries=queries, sequence_dir=args.sequence, max_frames=args.frames)
    except FileNotFoundError as exc:
        raise CommandError(str(exc)) from None
    print(f"wrote {out}  (open it with: rerun {out})")
    if args.png is not None:
        import numpy as np

        from services.viewer.render import render_map_pictures

        state = MapStore(map_dir / "graph").load()
        traj = np.asarray(state.extra.get("trajectory", np.zeros((0, 3))))
        for path in render_map_pictures(state.snapshot, args.png, queries, traj):
            print(f"wrote {path}")
    if args.open:
        import shutil

        viewer = shutil.which("rerun")
        if viewer is None:
            raise CommandError("the rerun viewer is not on PATH (pip install rerun-sdk gives it)")
        os.execv(viewer, [viewer, str(out)])
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'view' to the top parser's subcommands."""
    vw = sub.add_parser("view", help="a Rerun recording (.rrd) of a saved map, optional query hits and PNG renders")
    vw.add_argument("map_dir", type=Path, metavar="MAP_DIR")
    vw.add_argument("--out", type=Path, metavar="FILE.rrd", help="default MAP_DIR/map.rrd")
    vw.add_argument("--query", action="append", metavar="TEXT", help="highlight this query's hits (repeatable)")
    vw.add_argument("--top-k", type=int, default=3, metavar="K", help="hits per query")
    vw.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="add tracked frames (needs map --save-tracks)")
    vw.add_argument("--frames", type=int, default=60, metavar="N", help="at most this many tracked frames")
    vw.add_argument("--png", type=Path, metavar="DIR", help="also render top-down PNGs of the map and of each query")
    vw.add_argument("--config", type=Path, metavar="FILE", help="the query encoder's config (default MAP_DIR/config.yaml)")
    vw.add_argument("--open", action="store_true", help="open the recording in the Rerun viewer")
    vw.set_defaults(func=_cmd_view)
