"""``trackgraph map``: map a recorded sequence in-process."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import _corrections_file, _load_or_default


def _cmd_map(args: argparse.Namespace) -> int:
    from services.mapping import run_map

    cfg = _load_or_default(args.config, args.set)
    corrections = None if args.corrections is None else _corrections_file(args.corrections)
    summary = run_map(
        args.sequence, cfg, args.out, dataset=args.dataset, save_tracks=args.save_tracks,
        stride=args.stride, max_frames=args.max_frames, progress=not args.json, corrections=corrections,
    )  # fmt: skip
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"mapped {summary['frames']} frames in {summary['seconds']:.1f} s ({summary['hz']:.2f} Hz), "
            f"{summary['segments']} segments, peak RSS {summary['peak_rss_mb']:.0f} MB -> {args.out}"
        )
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'map' to the top parser's subcommands."""
    from shared.datasets import DATASETS

    mp = sub.add_parser("map", help="map a recorded sequence in-process (no Zenoh)")
    mp.add_argument("sequence", type=Path, metavar="SEQ_DIR")
    mp.add_argument("--config", type=Path, metavar="FILE", help="system config (default: the paper's settings)")
    mp.add_argument("--out", type=Path, required=True, metavar="MAP_DIR")
    mp.add_argument("--dataset", choices=DATASETS.names())
    mp.add_argument("--save-tracks", action="store_true", help="write per-frame track maps for eval tracking")
    mp.add_argument("--stride", type=int, metavar="N")
    mp.add_argument("--max-frames", type=int, metavar="N")
    mp.add_argument("--corrections", type=Path, metavar="FILE",
                    help="pose corrections (JSON lines, e.g. a drifting synth's corrections.jsonl), each applied when the map reaches its frame")
    mp.add_argument("--json", action="store_true", help='print {"frames", "seconds", "hz", "peak_rss_mb", "segments", "corrections"}')
    mp.set_defaults(func=_cmd_map)
