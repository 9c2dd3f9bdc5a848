"""drive-commission: commission servo axes with elastic couplings and gear backlash."""

from importlib.metadata import PackageNotFoundError, version

from .jitcache import ensure_writable_cache

ensure_writable_cache()  # before any module that compiles with numba is imported

from .exceptions import CommissionError  # noqa: E402
from .recording import DriveInfo, Recording  # noqa: E402

try:
    __version__ = version("drive-commission")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = ["CommissionError", "DriveInfo", "Recording", "__version__"]
