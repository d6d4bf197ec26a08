"""``trackgraph synth``: a synthetic RGB-D sequence with ground truth (optionally a ROS 2 bag, drift)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import CommandError


def _cmd_synth(args: argparse.Namespace) -> int:
    from shared.synth import run_synth

    if args.drift is not None:
        from shared.synth.drift import validate_rate

        try:
            validate_rate(args.drift)  # before the minutes of rendering, not after
        except ValueError as exc:
            raise CommandError(f"--drift: {exc}") from None
    resolution = None
    if args.resolution is not None:
        from shared.synth.config import parse_resolution

        try:
            resolution = parse_resolution(args.resolution)
        except ValueError as exc:
            raise CommandError(f"--resolution: {exc}") from None
    result = run_synth(args.preset, args.seed, args.out, overwrite=args.overwrite, drift=args.drift, resolution=resolution)
    if args.rosbag is not None:
        from shared.ros2.bagio import write_sequence_bag

        bag = args.rosbag if args.rosbag.is_absolute() or args.rosbag.parent != Path(".") else Path(result["out"]) / args.rosbag
        result["rosbag"] = str(write_sequence_bag(Path(result["out"]), bag, overwrite=args.overwrite, progress=not args.json).path)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"wrote {result['frames']} frames with {result['objects']} objects to {result['out']}")
        print(f"  pictures: {Path(result['out']) / 'contact_sheet.png'}, {Path(result['out']) / 'topdown.png'}")
        if "resolution" in result:
            width, height = result["resolution"]
            print(f"  resolution: {width}x{height}, intrinsics in {Path(result['out']) / 'intrinsics.json'}")
        if "rosbag" in result:
            print(f"  ROS 2 bag: {result['rosbag']}")
        if "drift" in result:
            out = Path(result["out"])
            print(f"  odometry drift {result['drift']:g} m/m: {out / 'traj.txt'} (drifted), {out / 'traj_gt.txt'} (true), "
                  f"{result['corrections']} corrections in {out / 'corrections.jsonl'}, picture {out / 'drift.png'}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'synth' to the top parser's subcommands."""
    from shared.synth.config import PRESETS as SCENES  # the synthetic scenes, registered there

    sy = sub.add_parser("synth", help="generate a synthetic RGB-D sequence with ground truth")
    sy.add_argument("--preset", choices=list(SCENES), default="small")
    sy.add_argument("--seed", type=int, default=0)
    sy.add_argument("--out", type=Path, required=True, metavar="DIR")
    sy.add_argument("--overwrite", action="store_true", help="replace a non-empty DIR")
    sy.add_argument("--rosbag", type=Path, metavar="BAG", help="also write the sequence as a ROS 2 bag (images, CameraInfo, TF); a bare name goes inside DIR")
    sy.add_argument("--drift", type=float, metavar="RATE",
                    help="odometry drift in metres per metre travelled (0 < RATE <= 0.5): writes traj.txt drifted, "
                         "the true poses to traj_gt.txt and the loop-closure corrections to corrections.jsonl")
    sy.add_argument("--resolution", metavar="WxH",
                    help="render the preset at W x H pixels (e.g. 1200x680, each from 32 to 4096): the same world and "
                         "poses; the preset's horizontal field of view, square pixels, principal point at the centre")
    sy.add_argument("--json", action="store_true", help='print {"frames", "objects", "out"} (and "rosbag" with --rosbag, '
                                                        '"drift" and "corrections" with --drift, '
                                                        '"resolution": [W, H] with --resolution)')
    sy.set_defaults(func=_cmd_synth)
