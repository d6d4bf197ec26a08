"""``trackgraph query``: ranked segments or rooms for a text or image query, offline or ``--live``."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from services.cli.common import CommandError, _load_or_default

# The name the single-module CLI logged under, so the --in-room log line reads as before.
log = logging.getLogger("services.cli")


def _query_request(args: argparse.Namespace, text: str | None):
    import numpy as np

    from shared.messages.rpc import QueryRequest

    image = None
    if args.image is not None:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(args.image) as im:
                image = np.asarray(im.convert("RGB"))
        except (OSError, UnidentifiedImageError) as exc:
            raise CommandError(f"{args.image}: not a readable image ({exc})") from None
    if (text is None) == (image is None):
        raise CommandError("give a query TEXT or --image FILE (one of them)")
    if (args.near is None) != (args.radius is None):
        raise CommandError("--near X Y Z and --radius R go together")
    if args.in_room is not None and args.room is not None:
        raise CommandError("--in-room TEXT and --room ID both choose the room: give one of them")
    if args.rooms and args.in_room is not None:
        raise CommandError("--in-room TEXT filters segments; --rooms ranks the rooms themselves: give one of them")
    try:
        return QueryRequest(
            text=text, image=image, top_k=args.top_k, room=args.room, room_text=args.in_room, radius=args.radius,
            gallery=args.gallery, center=None if args.near is None else np.asarray(args.near, np.float64),
            target="rooms" if args.rooms else "segments",
        )  # fmt: skip
    except ValueError as exc:
        raise CommandError(f"bad query: {'; '.join(str(exc).splitlines()[:2])}") from None


def _print_ranked(rows: list[dict], cells: list[list[str]], as_json: bool, title: str, columns: tuple[str, ...], left: tuple[str, ...], empty: str) -> None:
    """``rows`` as the ``--json`` list, or a rich table of ``cells`` under ``columns`` (those in
    ``left`` left-aligned), or ``empty`` when there are none."""
    if as_json:
        print(json.dumps(rows))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_header=True, header_style="bold")
    for col in columns:
        table.add_column(col, justify="left" if col in left else "right")
    for row in cells:
        table.add_row(*row)
    Console().print(table if cells else f"{title}: {empty}")


def _centroid(r: dict) -> str:
    return " ".join(f"{v:+.2f}" for v in r["centroid"])


def _print_hits(hits, as_json: bool, title: str) -> None:
    from services.query.core import hit_rows

    rows = hit_rows(hits)
    cells = [
        [
            str(i), str(h.segment), f"{h.score:.3f}", _centroid(r), " x ".join(f"{v:.2f}" for v in (h.bbox_max - h.bbox_min).tolist()),
            "-" if h.room is None else str(h.room), "-" if h.best_track is None else str(h.best_track),
        ]
        for i, (h, r) in enumerate(zip(hits, rows, strict=True), 1)
    ]  # fmt: skip
    columns = ("rank", "segment", "score", "centroid (m)", "size (m)", "room", "best track")
    _print_ranked(rows, cells, as_json, title, columns, ("centroid (m)", "size (m)"), "no segments")


def _print_rooms(rooms, as_json: bool, title: str) -> None:
    from services.query.core import room_rows

    rows = room_rows(rooms)
    cells = [
        [
            str(i), str(h.room), h.name or "-", f"{h.score:.3f}", "-" if h.margin is None else f"{h.margin:+.3f}", _centroid(r),
            "-" if r["bbox"] is None else " x ".join(f"{b - a:.2f}" for a, b in zip(*r["bbox"], strict=True)),
        ]
        for i, (h, r) in enumerate(zip(rooms, rows, strict=True), 1)
    ]  # fmt: skip
    columns = ("rank", "room", "name", "score", "margin", "centroid (m)", "size (m)")
    _print_ranked(rows, cells, as_json, title, columns, ("name", "centroid (m)", "size (m)"), "no room has a feature yet")


def _chosen_room(rooms) -> str:
    """``room N (name, score)`` of the room a ``--in-room`` query took (the best-ranked)."""
    best = rooms[0]
    return f"room {best.room} ({best.name or 'unnamed'}, {best.score:.3f})"


def _cmd_query(args: argparse.Namespace) -> int:
    pos = list(args.args)
    if args.live:
        if len(pos) > 1:
            raise CommandError(f"--live takes one query TEXT, got {len(pos)} arguments")
        text = pos[0] if pos else None
        if args.timeout is not None and not args.timeout > 0:
            raise CommandError(f"--timeout must be a positive number of seconds, got {args.timeout}")
        req = _query_request(args, text)
        from services.query.client import QueryClient

        cfg = _load_or_default(args.config, args.set)
        transport = cfg.transport
        if args.connect:
            transport = transport.model_copy(update={"connect": args.connect})
        with QueryClient(transport, robot_id=args.robot or cfg.robot_id, timeout_s=args.timeout) as client:
            reply = client.ask(req)
        where = f"live, graph version {reply.graph_seq}"
    else:
        if not pos or len(pos) > 2:
            raise CommandError('give MAP_DIR and a query TEXT (or MAP_DIR --image FILE), or --live "TEXT"')
        map_dir, text = Path(pos[0]), (pos[1] if len(pos) > 1 else None)
        if not map_dir.is_dir():
            raise CommandError(f"{map_dir}: no such map folder (for a running system use --live)")
        req = _query_request(args, text)
        from services.query.core import QueryError
        from services.query.offline import OfflineQueries, map_config

        try:
            reply = OfflineQueries(map_dir, map_config(map_dir, args.config, args.set)).ask(req)
        except QueryError as exc:
            raise CommandError(str(exc)) from None
        where = str(map_dir)
    if reply.error is not None:
        raise CommandError(f"query refused: {reply.error}")
    title = f"{text or args.image} ({where})"
    if args.rooms:
        _print_rooms(reply.rooms, args.json, title)
        return 0
    if args.in_room is not None and reply.rooms:
        chosen = _chosen_room(reply.rooms)
        if args.json:
            # stdout stays the contract's list of hit rows; which room was taken goes to the log.
            log.info("--in-room %r: %s", args.in_room, chosen)
        else:
            print(f"in {chosen}")
    _print_hits(reply.hits, args.json, title)
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'query' to the top parser's subcommands."""
    q = sub.add_parser("query", help='ranked segments (or with --rooms rooms) for a text or image query: MAP_DIR "TEXT", or --live "TEXT"')
    q.add_argument("args", nargs="*", metavar="[MAP_DIR] TEXT", help='a saved map and the query, or only the query with --live')
    q.add_argument("--live", action="store_true", help="ask the running query service over Zenoh")
    q.add_argument("--image", type=Path, metavar="FILE", help="an image query instead of text")
    q.add_argument("--top-k", type=int, metavar="K")
    q.add_argument("--room", type=int, metavar="ID", help="only segments in this room")
    q.add_argument("--in-room", metavar="TEXT", help='only segments in the room that best matches TEXT (e.g. "kitchen"); not with --room')
    q.add_argument("--rooms", action="store_true", help='rank the rooms instead of the segments ("which room is the kitchen")')
    q.add_argument("--near", type=float, nargs=3, metavar=("X", "Y", "Z"), help="only segments within --radius of this point")
    q.add_argument("--radius", type=float, metavar="M")
    q.add_argument("--gallery", choices=["max", "mean"], help="eq. 10 max over the gallery (default) or the mean feature")
    q.add_argument("--config", type=Path, metavar="FILE", help="offline: the encoder's config (default MAP_DIR/config.yaml); live: transport and robot id")
    q.add_argument("--connect", action="append", metavar="ENDPOINT", help="live: router endpoint(s)")
    q.add_argument("--robot", metavar="ID", help="live: robot id (default: the config's)")
    q.add_argument("--timeout", type=float, metavar="S", help="live: seconds to wait for the answer (the request's deadline is a little under it)")
    q.add_argument("--json", action="store_true", help='print [{"segment", "score", "centroid", "bbox", "room", "best_track"}]; with --rooms [{"room", "score", "margin", "name", "centroid", "bbox"}]')
    q.set_defaults(func=_cmd_query)
