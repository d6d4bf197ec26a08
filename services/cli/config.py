"""``trackgraph config show`` and ``config check``: inspect and validate config files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import add_actions


def _cmd_config_show(args: argparse.Namespace) -> int:
    from shared.config import dump_yaml, load_config

    cfg = load_config(args.path, args.set)
    if args.json:
        print(json.dumps(cfg.model_dump(mode="json"), indent=2))
    else:
        print(dump_yaml(cfg), end="")
    return 0


def _cmd_config_check(args: argparse.Namespace) -> int:
    from shared.config import load_config

    load_config(args.path, args.set)
    print(f"ok: {args.path}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'config' to the top parser's subcommands."""
    csub = add_actions(sub, "config", "inspect and validate config files")
    show = csub.add_parser("show", help="print the resolved config, defaults included")
    show.add_argument("path", type=Path)
    show.add_argument("--json", action="store_true", help="JSON instead of YAML")
    show.set_defaults(func=_cmd_config_show)
    check = csub.add_parser("check", help="validate a config; non-zero exit names the bad key")
    check.add_argument("path", type=Path)
    check.set_defaults(func=_cmd_config_check)
