"""Generate the published wire contract: ``docs/wire.md`` and ``docs/schema/<Type>.json``.

    python -m shared.messages.wiredoc           # write both (``make wire-docs``)
    python -m shared.messages.wiredoc --check   # exit 1 if the committed files differ

Everything comes from code: the keys and their QoS from :mod:`shared.messages.contract`, the
fields from the message models (type annotations, :class:`~shared.arrays.ArraySpec`,
:class:`~shared.messages.base.Units`, pydantic constraints and the docstring under each
field), the envelope and array encodings from :mod:`shared.codec`, the decoder's limits from
:class:`~shared.config.transport.CodecConfig`. The output is deterministic: the same code
gives the same bytes.

The package: :mod:`~shared.messages.wiredoc.models` reads the models,
:mod:`~shared.messages.wiredoc.schema` writes the JSON Schemas,
:mod:`~shared.messages.wiredoc.markdown` writes docs/wire.md; here, the files and the command.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from shared.messages.wiredoc.markdown import wire_md
from shared.messages.wiredoc.schema import schemas

ROOT = Path(__file__).resolve().parents[3]
WIRE_MD = Path("docs") / "wire.md"
SCHEMA_DIR = Path("docs") / "schema"


def generated() -> dict[Path, str]:
    """Repository path -> contents of every generated file."""
    out = {WIRE_MD: wire_md()}
    out.update({SCHEMA_DIR / name: text for name, text in schemas().items()})
    return out


def differences(root: Path = ROOT) -> list[str]:
    """What differs between the files under ``root`` and what the code generates."""
    want = generated()
    out = []
    for rel, text in want.items():
        path = root / rel
        if not path.is_file():
            out.append(f"{rel}: missing")
        elif path.read_text(encoding="utf-8") != text:
            out.append(f"{rel}: differs")
    schema_dir = root / SCHEMA_DIR
    if schema_dir.is_dir():
        for path in sorted(schema_dir.glob("*.json")):
            if SCHEMA_DIR / path.name not in want:
                out.append(f"{SCHEMA_DIR / path.name}: no such message (stale)")
    return out


def write(root: Path = ROOT) -> list[Path]:
    """Write every generated file under ``root`` and remove stale schemas; returns the paths written."""
    want = generated()
    (root / SCHEMA_DIR).mkdir(parents=True, exist_ok=True)
    for path in sorted((root / SCHEMA_DIR).glob("*.json")):
        if SCHEMA_DIR / path.name not in want:
            path.unlink()
    written = []
    for rel, text in want.items():
        path = root / rel
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
            written.append(rel)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m shared.messages.wiredoc", description="generate docs/wire.md and docs/schema/*.json")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if the committed files differ")
    ap.add_argument("--root", type=Path, default=ROOT, help="repository root (default: this checkout)")
    args = ap.parse_args(argv)
    if args.check:
        diff = differences(args.root)
        for d in diff:
            print(d, file=sys.stderr)
        if diff:
            print("the wire docs are out of date: run `make wire-docs`", file=sys.stderr)
        return 1 if diff else 0
    for rel in write(args.root):
        print(f"wrote {rel}")
    return 0
