"""What several command groups share: the error a command raises for a one-line reason, the
config a ``--config FILE`` names (or the defaults), the command-line overrides of shared
sections, and a command of several actions."""

from __future__ import annotations

import argparse
from pathlib import Path


class CommandError(Exception):
    """A command failed for a reason the user can act on; printed as one line."""


def _load_or_default(path: Path | str | None, sets: list[str] | None = None):
    """The config ``--config`` names (a file or a preset's name), or the defaults, with the
    ``--set KEY=VALUE`` items on top (shared/config/overrides.py)."""
    from shared.config import TrackGraphConfig, load_config
    from shared.config.base import validate
    from shared.config.overrides import apply_sets

    if path:
        return load_config(path, sets or [])
    if not sets:
        return TrackGraphConfig()
    return validate(TrackGraphConfig, apply_sets({}, sets, TrackGraphConfig), f"--set {' '.join(sets)}")


def add_actions(sub: argparse._SubParsersAction, name: str, help: str, metavar: str = "ACTION") -> argparse._SubParsersAction:
    """Add ``trackgraph NAME ACTION``, a command of several actions; add them to what it returns."""
    return sub.add_parser(name, help=help).add_subparsers(dest=f"{name}_command", required=True, metavar=metavar)


def add_set(parser: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (repeatable) on a command that takes a config."""
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="override one config key, e.g. fusion.tsdf.voxel_size=0.05 (repeatable; checked against the config)",
    )  # fmt: skip


def config_arg_help(text: str = "") -> str:
    """Help of a ``--config`` option: a preset's name or a file."""
    from shared.presets import PRESETS

    names = ", ".join(PRESETS.names())
    return f"a preset ({names}) or a config file" + (f"; {text}" if text else "")


def _corrections_file(path: Path) -> Path:
    """A corrections file that reads (every line a valid PoseCorrection), or a one-line reason."""
    from shared.messages.poses import CorrectionsFileError, read_corrections

    try:
        read_corrections(path)
    except CorrectionsFileError as e:
        raise CommandError(str(e)) from None
    return path.resolve()


def _with_ros2(cfg, args: argparse.Namespace):
    """``cfg`` with the ROS 2 command-line overrides (--connect, --convention, --domain)."""
    data = cfg.model_dump()
    if args.connect:
        data["transport"]["connect"] = args.connect
    if getattr(args, "convention", None):
        data["ros2"]["link"]["convention"] = args.convention
    if getattr(args, "domain", None) is not None:
        data["ros2"]["link"]["domain_id"] = args.domain
    from shared.config.base import validate

    return validate(type(cfg), data, "command line")
