"""``trackgraph source``: replay a sequence over Zenoh, or with ``--ros2`` take a live robot's topics."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from services.cli.common import CommandError, _corrections_file, _load_or_default, _with_ros2


def _cmd_source(args: argparse.Namespace) -> int:
    cfg = _load_or_default(args.config, args.set)
    if args.ros2:
        return _source_ros2(args, cfg)
    if args.sequence is None:
        raise CommandError("source: give SEQ_DIR (a sequence to replay), or --ros2 for a live robot's topics")
    live_only = [f for f in ("convention", "domain", "seconds") if getattr(args, f) is not None]
    if live_only:
        raise CommandError(f"source: --{live_only[0]} is for --ros2 (a live robot), not for replaying {args.sequence}")
    from services.source.node import run_source

    src = cfg.source.model_dump()
    for key in ("dataset", "mode", "stride", "max_frames"):
        if getattr(args, key) is not None:
            src[key] = getattr(args, key)
    if args.rate is not None:
        src["rate_hz"] = args.rate
    if args.corrections is not None:
        src["corrections"] = str(_corrections_file(args.corrections))
    update = {"source": type(cfg.source).model_validate(src)}
    if args.connect:
        update["transport"] = cfg.transport.model_copy(update={"connect": args.connect})
    cfg = type(cfg).model_validate({**cfg.model_dump(), **{k: v.model_dump() for k, v in update.items()}})
    stats = run_source(cfg, args.sequence, wait_subscribers_s=args.wait, status_file=args.status_file)
    out = {"published": stats.published, "dropped": stats.dropped, "seconds": round(stats.seconds, 3)}
    print(json.dumps(out) if args.json else f"published {stats.published} frames, dropped {stats.dropped}, in {stats.seconds:.1f} s")
    return 0


def _source_ros2(args: argparse.Namespace, cfg) -> int:
    from services.ros2.node import run_ros2_source

    if args.sequence is not None:
        raise CommandError("source --ros2 takes its frames from the robot's topics: drop SEQ_DIR")
    bad = [f for f in ("dataset", "mode", "stride", "max_frames", "rate") if getattr(args, f) is not None]
    if bad:
        raise CommandError(f"source --ros2: --{bad[0].replace('_', '-')} is for replaying a sequence (set ros2.input in the config)")
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise CommandError(f"source --ros2: --seconds must be a positive number of seconds, got {args.seconds}")
    cfg = _with_ros2(cfg, args)
    stats = run_ros2_source(cfg, status_file=args.status_file, max_seconds=args.seconds)
    out = {"published": stats.published, "dropped": stats.dropped, "seconds": stats.seconds, "received": stats.received, "rejected": stats.rejected, "error": stats.error}
    print(json.dumps(out) if args.json else f"published {stats.published} frames, dropped {stats.dropped}, in {stats.seconds:.1f} s; rejected {stats.rejected or 'none'}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'source' to the top parser's subcommands."""
    from shared.datasets import DATASETS

    so = sub.add_parser("source", help="replay a sequence as frames over Zenoh, or with --ros2 take a live robot's ROS 2 topics")
    so.add_argument("sequence", type=Path, metavar="SEQ_DIR", nargs="?")
    so.add_argument("--ros2", action="store_true", help="frames from the robot's ROS 2 camera and pose topics (config section ros2) until Ctrl-C")
    so.add_argument("--convention", choices=["rmw_zenoh", "bridge"], help="--ros2: the ROS 2 key convention (default: the config's)")
    so.add_argument("--domain", type=int, metavar="ID", help="--ros2: ROS_DOMAIN_ID (default: the config's)")
    so.add_argument("--seconds", type=float, metavar="S", help="--ros2: stop after S seconds")
    so.add_argument("--config", type=Path, metavar="FILE")
    so.add_argument("--dataset", choices=DATASETS.names())
    so.add_argument("--mode", choices=["lossless", "live"])
    so.add_argument("--rate", type=float, metavar="HZ", help="live-mode rate")
    so.add_argument("--stride", type=int, metavar="N")
    so.add_argument("--max-frames", type=int, metavar="N")
    so.add_argument("--corrections", type=Path, metavar="FILE", help="pose corrections (JSON lines) to send on poses/correction as the replay passes their frames")
    so.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    so.add_argument("--wait", type=float, default=30.0, metavar="S", help="lossless: wait this long for a subscriber")
    so.add_argument("--status-file", type=Path, metavar="FILE", help="write the last ServiceStatus report here as JSON at stop")
    so.add_argument("--json", action="store_true", help='print {"published", "dropped", "seconds"} (--ros2 adds "received", "rejected", "error")')
    so.set_defaults(func=_cmd_source)
