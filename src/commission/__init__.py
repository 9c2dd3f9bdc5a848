"""drive-commission: commission servo axes with elastic couplings and gear backlash."""

from importlib.metadata import PackageNotFoundError, version
from typing import Any

from .jitcache import ensure_writable_cache

ensure_writable_cache()  # before any module that compiles with numba is imported

from .exceptions import CommissionError  # noqa: E402

try:
    __version__ = version("drive-commission")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = ["CommissionError", "DriveInfo", "Recording", "__version__"]


def __getattr__(name: str) -> Any:
    # Recording and DriveInfo bring numpy: loaded on first use, so that the command starts, and
    # takes Ctrl-C (commission.interrupt), before any heavy import
    if name in ("DriveInfo", "Recording"):
        from . import recording

        return getattr(recording, name)
    raise AttributeError(f"module 'commission' has no attribute {name!r}")
