"""``trackgraph bench run``: the paper's tables for one sequence and one or more configs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import CommandError


def _cmd_bench_run(args: argparse.Namespace) -> int:
    from services.bench.core import run_bench
    from services.bench.runs import BenchError

    if (args.preset is None) == (args.sequence is None):
        from shared.synth.config import PRESETS

        raise CommandError(f"give either --preset {'|'.join(PRESETS)} or --sequence SEQ_DIR --gt GT_DIR")
    if args.sequence is not None and not args.config:
        raise CommandError("--sequence needs at least one --config FILE (simulated perception works on synthetic scenes only)")
    if args.rate_seconds is not None and args.rate_seconds <= 0:
        raise CommandError(f"--rate-seconds must be positive, got {args.rate_seconds}")
    configs = args.config or []
    if args.set:  # each config with the --set items, resolved beside the bench's outputs
        from shared.config import load_config, save_resolved
        from shared.presets import config_path

        configs = [save_resolved(load_config(c, args.set), Path(args.out) / "configs" / "set" / f"{config_path(c).stem}.yaml") for c in configs or ["synthetic"]]
    try:
        res = run_bench(
            args.out, preset=args.preset, seed=args.seed, sequence=args.sequence, gt=args.gt, configs=configs,
            dataset=args.dataset, max_frames=args.max_frames, rate_trials=args.rate_trials, rate_frames=args.rate_frames,
            rate_seconds=args.rate_seconds, random_weights=args.random_weights, resume=args.resume, progress=not args.json,
        )  # fmt: skip
    except BenchError as exc:
        raise CommandError(str(exc)) from None
    if args.json:
        print(json.dumps({"out": str(args.out), "markdown": str(Path(args.out) / "bench.md"), "json": str(Path(args.out) / "bench.json"), "plots": res["plots"], "seconds": res["seconds"]}))
    else:
        print((Path(args.out) / "bench.md").read_text())
        print(f"tables: {Path(args.out) / 'bench.md'}, JSON: {Path(args.out) / 'bench.json'}, plots: {Path(args.out) / 'plots'}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'bench' to the top parser's subcommands."""
    from shared.datasets import DATASETS
    from shared.synth.config import PRESETS as SCENES  # the synthetic scenes, registered there

    be = sub.add_parser("bench", help="the paper's tables for one sequence and one or more configs")
    besub = be.add_subparsers(dest="bench_cmd", required=True)
    br = besub.add_parser("run", help="segmentation, retrieval, efficiency, tracker and gallery ablations: markdown, JSON and plots")
    br.add_argument("--preset", choices=list(SCENES), help="a synthetic scene (generated into OUT)")
    br.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene")
    br.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="a recorded sequence instead of a preset")
    br.add_argument("--gt", type=Path, metavar="GT_DIR", help="its OpenLex3D ground truth (with --sequence)")
    br.add_argument("--dataset", choices=DATASETS.names())
    br.add_argument("--config", type=Path, action="append", metavar="FILE", help="a system config (repeatable; default deploy/configs/synthetic.yaml)")
    br.add_argument("--out", type=Path, default=Path("bench_out"), metavar="DIR")
    br.add_argument("--max-frames", type=int, metavar="N", help="map only the first N frames")
    br.add_argument("--rate-trials", type=int, default=3, metavar="N", help="live runs per tracker mode in the input-rate search (0 skips it)")
    br.add_argument("--rate-frames", type=int, default=60, metavar="N", help="frames per live run")
    br.add_argument("--rate-seconds", type=float, metavar="S", help="instead: each live run sends frames for about S seconds (two keyframes at least)")
    br.add_argument("--resume", action="store_true", help="keep the maps an interrupted run of the same --out finished")
    br.add_argument("--random-weights", type=Path, metavar="DIR", help="run each config's models on random weights written to DIR: the real architectures' times and memory, meaningless maps")
    br.add_argument("--json", action="store_true", help='print {"out", "markdown", "json", "plots", "seconds"}')
    br.set_defaults(func=_cmd_bench_run)
