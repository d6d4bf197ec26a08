"""Import Open3D on machines without a system libusb.

Open3D's wheels link ``libusb-1.0.so.0`` at import. Where the system lacks it, the one
shipped in the ``libusb-package`` wheel is preloaded first, so no apt step is needed.
"""

from __future__ import annotations

import ctypes
import importlib
from types import ModuleType

_o3d: ModuleType | None = None


def import_open3d() -> ModuleType:
    """Return the ``open3d`` module, preloading libusb when the system has none."""
    global _o3d
    if _o3d is not None:
        return _o3d
    try:
        ctypes.CDLL("libusb-1.0.so.0", mode=ctypes.RTLD_GLOBAL)
    except OSError:
        try:
            import libusb_package
        except ImportError as exc:
            raise ImportError(
                "open3d needs libusb-1.0: install the system package (apt install libusb-1.0-0) "
                "or `pip install libusb-package` (part of the `fusion` extra)"
            ) from exc
        ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
    _o3d = importlib.import_module("open3d")
    return _o3d
