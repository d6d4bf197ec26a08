"""``trackgraph launch`` and ``trackgraph status``: a whole system as separate processes, and its live status."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import CommandError, _load_or_default


def _cmd_launch(args: argparse.Namespace) -> int:
    from services.launch import LaunchError, run_launch

    try:
        summary = run_launch(args.file, sequence=args.sequence, out=args.out, log_dir=args.log_dir, status=not args.json, sets=args.set)
    except LaunchError as exc:
        raise CommandError(str(exc)) from None
    if args.json:
        print(json.dumps(summary))
    else:
        for name, s in summary["services"].items():
            print(f"{name:<12} {s['state']:<9} restarts {s['restarts']}  log {s['log']}")
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from services.monitor import MonitorError, run_status

    cfg = _load_or_default(args.config, args.set)
    transport = cfg.transport
    if args.connect:
        transport = transport.model_copy(update={"connect": args.connect})
    try:
        return run_status(transport, args.robot or cfg.robot_id, once=args.once, as_json=args.json, timeout=args.timeout)
    except MonitorError as exc:
        raise CommandError(str(exc)) from None


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'launch', 'status' to the top parser's subcommands."""
    la = sub.add_parser("launch", help="start a router and every service of a launch file as separate processes")
    la.add_argument("file", type=Path, metavar="LAUNCH_FILE", help="e.g. deploy/local.yaml")
    la.add_argument("--sequence", type=Path, metavar="SEQ_DIR", help="what the source replays (overrides the file)")
    la.add_argument("--out", type=Path, metavar="MAP_DIR", help="fusion's map folder (overrides the file)")
    la.add_argument("--log-dir", type=Path, metavar="DIR", help="one log per process (default MAP_DIR/logs)")
    la.add_argument("--json", action="store_true", help="no status table; print the final summary as JSON")
    la.set_defaults(func=_cmd_launch)

    st = sub.add_parser("status", help="the live status table of a running system (every service's ServiceStatus reports)")
    st.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s) (default: the config's)")
    st.add_argument("--robot", metavar="ID", help="robot id (default: the config's)")
    st.add_argument("--config", type=Path, metavar="FILE", help="take transport and robot id from this system config")
    st.add_argument("--once", action="store_true", help="print the table once and exit")
    st.add_argument("--timeout", type=float, default=5.0, metavar="S", help="fail if no service reports within S seconds")
    st.add_argument("--json", action="store_true", help='JSON instead of the table: {"robot", "services": {NAME: {ServiceStatus fields..., "age_s", "summary"}}}, one line per second (once with --once)')
    st.set_defaults(func=_cmd_status)
