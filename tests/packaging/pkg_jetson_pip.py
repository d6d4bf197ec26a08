"""pip as a Jetson (JetPack 6: aarch64, CPython 3.10, glibc 2.35) would run it, from any host.

    python tests/packaging/pkg_jetson_pip.py install --dry-run ... | download ...

pip's ``--platform`` and ``--python-version`` pick wheel tags, but environment markers
(``platform_machine``, ``python_version``) are still evaluated against the host, so on an x86
host torch's x86-only ``nvidia-*`` requirements come in and the resolution is not the Jetson's.
This patches ``platform`` before pip starts, so markers read as on the Jetson. Pass the
wheel tags with ``PLATFORM_ARGS``.
"""

from __future__ import annotations

import platform
import sys

PYTHON_VERSION = "3.10"
# pip (23.2 at least) takes `--platform manylinux_2_28_aarch64` as that one tag only, not as
# "glibc 2.28 or older", so every manylinux tag a glibc-2.35 aarch64 system runs is listed:
# manylinux2014 (= 2_17) and manylinux_2_17 ... manylinux_2_35.
PLATFORMS = ["manylinux2014_aarch64", *(f"manylinux_2_{minor}_aarch64" for minor in range(17, 36))]
PLATFORM_ARGS = [arg for p in PLATFORMS for arg in ("--platform", p)] + ["--python-version", PYTHON_VERSION]


def patch_platform() -> None:
    platform.machine = lambda: "aarch64"
    platform.python_version = lambda: "3.10.12"
    platform.python_version_tuple = lambda: ("3", "10", "12")


if __name__ == "__main__":
    patch_platform()
    from pip._internal.cli.main import main

    sys.exit(main())
