"""The ``trackgraph`` command: one entry point, one subcommand per job.

Every subcommand exits non-zero on failure with a one-line reason on stderr
(docs/architecture.md, "Command-line contract").

One module per command group (``router``, ``synth``, ``source``, ``mapping`` for ``map``,
``evaluate`` for ``eval``, ``models`` with ``export-onnx``, ``serve``, ``view``, ``demo``,
``bench``, ``ros2``, ``launch`` with ``status``, ``query``, ``config``), each with an
``add_parser(sub)`` that adds its subcommand(s); the helpers they share are in ``common``.
Heavy imports (torch, open3d, zenoh) stay inside the command functions, so importing this
package stays light (tests/test_imports.py).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from services.cli import (
    bench,
    config,
    demo,
    evaluate,
    launch,
    mapping,
    models,
    query,
    ros2,
    router,
    serve,
    source,
    synth,
    view,
)
from services.cli.common import CommandError, add_set

__all__ = ["CommandError", "build_parser", "main"]

# In `trackgraph --help` order.
_GROUPS = (router, synth, source, mapping, evaluate, models, serve, view, demo, bench, ros2, launch, query, config)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="trackgraph", description=__doc__.splitlines()[0])
    p.add_argument("-v", "--verbose", action="count", default=0, help="debug logging")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in _GROUPS:
        group.add_parser(sub)
    _add_set_where_a_config_is_taken(p)
    return p


def _add_set_where_a_config_is_taken(parser: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` on every command that takes a config (a ``--config`` option, or the
    config file of ``config show``/``check`` and the launch file of ``launch``), so the one way
    to override a config is everywhere."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                takes = any("--config" in a.option_strings for a in child._actions)
                takes |= child.prog.endswith(("config show", "config check", "trackgraph launch"))
                if takes:
                    add_set(child)
                _add_set_where_a_config_is_taken(child)


def main(argv: list[str] | None = None) -> int:
    from shared.config import ConfigError
    from shared.datasets.base import DatasetError
    from shared.eval.errors import EvalInputError
    from shared.logs import setup_logging
    from shared.transport import TransportError

    args = build_parser().parse_args(argv)
    setup_logging(args.verbose)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (ConfigError, CommandError, DatasetError, EvalInputError, TransportError) as exc:
        print(f"trackgraph: error: {'; '.join(str(exc).splitlines())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # noqa: BLE001 - a one-line reason beats a traceback for users
        if args.verbose:
            raise
        print(f"trackgraph: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1

