"""``trackgraph serve SERVICE``: one service as this process."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.common import _load_or_default


def _cmd_serve(args: argparse.Namespace) -> int:
    from services.serve import serve

    cfg = _load_or_default(args.config, args.set)
    if args.connect:
        data = cfg.model_dump()
        data["transport"]["connect"] = args.connect
        cfg = type(cfg).model_validate(data)
    if args.sequence is not None:
        from services.mapping import prepare_config

        cfg = prepare_config(cfg, args.sequence)
    serve(args.service, cfg, out=args.out, resume=args.resume, exit_at_end=args.exit_at_end, status_file=args.status_file)
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'serve' to the top parser's subcommands."""
    from shared.registry import servable_services

    sv = sub.add_parser("serve", help="run one service as this process, until Ctrl-C")
    sv.add_argument("service", choices=servable_services())
    sv.add_argument("--config", type=Path, metavar="FILE")
    sv.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    sv.add_argument("--out", type=Path, metavar="PATH", help="fusion: the map folder (snapshots, final map); viewer: the .rrd recording")
    sv.add_argument("--resume", action="store_true", help="fusion: continue from the last snapshot in MAP_DIR")
    sv.add_argument("--exit-at-end", action="store_true", help="fusion: stop once the replayed sequence is mapped")
    sv.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="a synthetic sequence whose ground truth the simulated backends use")
    sv.add_argument("--status-file", type=Path, metavar="FILE", help="write the last ServiceStatus report here as JSON at stop")
    sv.set_defaults(func=_cmd_serve)
