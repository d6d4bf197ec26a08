"""``trackgraph demo``: the synthetic demo scene through the whole distributed system."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import CommandError


def _cmd_demo(args: argparse.Namespace) -> int:
    from services.demo import run_demo
    from services.launch import LaunchError

    try:
        r = run_demo(args.out, preset=args.preset, seed=args.seed, config=args.config, sets=args.set)
    except LaunchError as exc:
        raise CommandError(f"the demo's launch failed: {exc}") from None
    if args.json:
        print(json.dumps(r))
        return 0
    m = r["metrics"]
    print(f"perception: {r['perception']}")
    print(f"mapped {r['frames']} frames as separate processes in {r['timings'].get('distributed_map_s', 0):.0f} s: {r['segments']} segments")
    for q in r["queries"]:
        top = q["hits"][0] if q["hits"] else None
        print(f"  {q['query']!r:<28} {q['ms']:6.0f} ms  -> " + (f"segment {top['segment']} ({top['object']}, IoU {top['iou']:.2f})" if top else "no hit"))
    print(f"instance AP50 {m['ap50']:.3f}, top-1 hits of synonym queries over 20 cm {m['top1_synonym_queries_over_20cm']:.3f}, synonyms {m['synonyms']:.3f}")
    for what, path in r["files"].items():
        print(f"{what:<15} {path}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'demo' to the top parser's subcommands."""
    from shared.synth.config import PRESETS as SCENES  # the synthetic scenes, registered there

    dm = sub.add_parser("demo", help="the synthetic demo scene through the whole distributed system, with example queries and a report")
    dm.add_argument("--out", type=Path, default=Path("demo_out"), metavar="DIR")
    dm.add_argument("--preset", choices=list(SCENES), default="demo")
    dm.add_argument("--seed", type=int, default=0)
    dm.add_argument("--config", type=Path, metavar="FILE", help="default: the paper's models if their weights are present, else simulated perception")
    dm.add_argument("--json", action="store_true", help="print the report's figures as JSON")
    dm.set_defaults(func=_cmd_demo)
