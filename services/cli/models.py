"""``trackgraph models check`` and ``trackgraph export-onnx``: the weight files a config needs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import _load_or_default, add_actions


def _cmd_models_check(args: argparse.Namespace) -> int:
    from services.models.check import check_models

    result = check_models(_load_or_default(args.config, args.set), load=not args.no_load)
    if args.json:
        print(json.dumps(result))
    else:
        if not result["models"]:
            print("this config needs no weight files")
        for m in result["models"]:
            state = "ok" if m["loads"] else ("present" if m["present"] and m["loads"] is None else "MISSING" if not m["present"] else "FAILS")
            # The absolute path: a relative one is read from wherever the command runs.
            print(f"{m['role']:<15} {m['backend']:<13} {state:<8} {m.get('resolved') or m['path']}")
            if m.get("loader"):
                print(f"{'':<15} loader: {m['loader']}")
            if m["error"]:
                print(f"{'':<15} {m['error']}")
            # A file that fails to load is as good as missing: say where the right one is.
            if not m["present"] or m["loads"] is False:
                print(f"{'':<15} get it: {m['source']}")
    return 0 if result["ok"] else 1


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    from services.models.export import export_all

    only = set(args.only) if args.only else None
    for role, path in export_all(_load_or_default(args.config, args.set), args.out, only, fastsam_static=args.fastsam_static).items():
        print(f"{role}: {path}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'models', 'export-onnx' to the top parser's subcommands."""
    mosub = add_actions(sub, "models", "weight files a config needs")
    mc = mosub.add_parser("check", help="which weight files the config needs, whether present and loadable, where to get them")
    mc.add_argument("--config", type=Path, metavar="FILE")
    mc.add_argument("--no-load", action="store_true", help="only check that the files exist")
    mc.add_argument("--json", action="store_true", help='print {"ok", "missing": [...], "models": [...]}')
    mc.set_defaults(func=_cmd_models_check)

    ex = sub.add_parser("export-onnx", help="export the configured FastSAM, CLIP and DINOv3 to ONNX")
    ex.add_argument("--config", type=Path, required=True, metavar="FILE")
    ex.add_argument("--out", type=Path, required=True, metavar="DIR")
    ex.add_argument("--only", action="append", choices=["segmenter", "vl_encoder", "dense_features"])
    ex.add_argument(
        "--fastsam-static", action="store_true",
        help="fix FastSAM's input at imgsz x imgsz (default: dynamic, letterboxed like the .pt path; "
        "a static export's masks differ from the .pt path's on non-square frames)",
    )
    ex.set_defaults(func=_cmd_export_onnx)
