"""Deployment files shipped with TrackGraph: config presets (``configs/*.yaml``), launch files
(``*.yaml``), Zenoh profiles (``zenoh/``), systemd units and Dockerfiles. Importing this package
registers every preset and launch file under its file name's stem (shared/presets.py)."""

from pathlib import Path

from shared.presets import LAUNCH_FILES, PRESETS

HERE = Path(__file__).resolve().parent
"""This folder: the checkout's ``deploy/`` or the installed package's."""

for _file in sorted((HERE / "configs").glob("*.yaml")):
    PRESETS.register(_file.stem, _file)
for _file in sorted(HERE.glob("*.yaml")):
    LAUNCH_FILES.register(_file.stem, _file)
