"""``trackgraph ros2 play`` and ``ros2 bag``: ROS 2 bags over Zenoh."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import CommandError, _load_or_default, _with_ros2, add_actions


def _cmd_ros2_play(args: argparse.Namespace) -> int:
    from services.ros2.node import play_bag
    from shared.ros2.bagio import BagError

    cfg = _with_ros2(_load_or_default(args.config, args.set), args)
    try:
        stats = play_bag(args.bag, cfg, rate=args.rate, topics=args.topic, wait_subscribers_s=args.wait, progress=not args.json)
    except (BagError, ValueError) as e:
        raise CommandError(str(e)) from None
    out = {"messages": stats.messages, "topics": stats.topics, "seconds": stats.seconds, "late_s": stats.late_s}
    print(json.dumps(out) if args.json else f"played {stats.messages} messages on {len(stats.topics)} topics in {stats.seconds:.1f} s (at most {stats.late_s:.3f} s late)")
    return 0


def _cmd_ros2_bag(args: argparse.Namespace) -> int:
    from shared.ros2.bagio import BagError, write_sequence_bag

    try:
        # The writer replaces only a bag (a folder with metadata.yaml), and only once the new
        # one is complete: a failed run keeps the old bag, and no other folder is ever deleted.
        summary = write_sequence_bag(args.sequence, args.out, distro=args.distro, rate_hz=args.rate, compressed_rgb=args.compressed,
                                     overwrite=args.overwrite, progress=not args.json)  # fmt: skip
    except BagError as e:
        raise CommandError(str(e)) from None
    except ValueError as e:
        raise CommandError(f"ros2 bag: {e}".replace("rate_hz", "--rate")) from None
    out = {"out": str(summary.path), "frames": summary.frames, "seconds": summary.seconds, "topics": {t: list(v) for t, v in summary.topics.items()}}
    print(json.dumps(out) if args.json else f"wrote {summary.frames} frames ({summary.seconds:.1f} s) as a ROS 2 bag to {summary.path}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'ros2' to the top parser's subcommands."""
    r2sub = add_actions(sub, "ros2", "ROS 2 bags over Zenoh: play one as a robot would send it, or write a sequence as one")
    pl = r2sub.add_parser("play", help="publish a ROS 2 bag's topics over Zenoh at the recorded pace (rmw_zenoh or bridge convention)")
    pl.add_argument("bag", type=Path, metavar="BAG")
    pl.add_argument("--config", type=Path, metavar="FILE", help="transport and the ros2.link section (default: rmw_zenoh, domain 0)")
    pl.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    pl.add_argument("--convention", choices=["rmw_zenoh", "bridge"])
    pl.add_argument("--domain", type=int, metavar="ID", help="ROS_DOMAIN_ID")
    pl.add_argument("--rate", type=float, default=1.0, metavar="R", help="play R times the recorded pace (as ros2 bag play --rate)")
    pl.add_argument("--topic", action="append", metavar="TOPIC", help="only these topics (repeatable; default all)")
    pl.add_argument("--wait", type=float, default=0.0, metavar="S", help="first wait up to S seconds for subscribers of the sensor_msgs topics (images, CameraInfo)")
    pl.add_argument("--json", action="store_true", help='print {"messages", "topics", "seconds", "late_s"}')
    pl.set_defaults(func=_cmd_ros2_play)
    bg = r2sub.add_parser("bag", help="write a sequence folder as a ROS 2 bag (colour, depth, CameraInfo, TF)")
    bg.add_argument("sequence", type=Path, metavar="SEQ_DIR")
    bg.add_argument("--out", type=Path, required=True, metavar="BAG")
    bg.add_argument("--distro", choices=["humble", "iron", "jazzy", "kilted"], default="jazzy", help="message definitions written into the bag")
    bg.add_argument("--rate", type=float, metavar="HZ", help="frame rate of the stamps (default the sequence's, else 30)")
    bg.add_argument("--compressed", action="store_true", help="colour as JPEG CompressedImage on .../compressed")
    bg.add_argument("--overwrite", action="store_true", help="replace an existing BAG")
    bg.add_argument("--json", action="store_true", help='print {"out", "frames", "seconds", "topics"}')
    bg.set_defaults(func=_cmd_ros2_bag)
