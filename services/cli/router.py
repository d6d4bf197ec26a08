"""``trackgraph router``: a Zenoh router in this process."""

from __future__ import annotations

import argparse


def _cmd_router(args: argparse.Namespace) -> int:
    from services.router import run_router
    from shared.config import TransportConfig, load_config

    if args.config:
        cfg = load_config(args.config, args.set).transport.model_copy(update={"mode": "router"})
    else:
        cfg = TransportConfig(mode="router", connect=[], listen=args.listen or ["tcp/127.0.0.1:7447"])
    if args.listen:
        cfg = cfg.model_copy(update={"listen": args.listen})
    if args.zenoh_config:
        cfg = cfg.model_copy(update={"zenoh_config_file": args.zenoh_config})
    cfg = TransportConfig.model_validate(cfg.model_dump())
    run_router(cfg)
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add 'router' to the top parser's subcommands."""
    r = sub.add_parser("router", help="run a Zenoh router (no separate binary needed)")
    r.add_argument("--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447 (repeatable; default tcp/127.0.0.1:7447)")
    r.add_argument("--config", metavar="FILE", help="take the transport section of this system config")
    r.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 file (TLS, users, access control)")
    r.set_defaults(func=_cmd_router)
