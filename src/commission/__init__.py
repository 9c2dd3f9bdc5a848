"""drive-commission: commission servo axes with elastic couplings and gear backlash."""

from importlib.metadata import PackageNotFoundError, version

from .exceptions import CommissionError
from .recording import DriveInfo, Recording

try:
    __version__ = version("drive-commission")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = ["CommissionError", "DriveInfo", "Recording", "__version__"]
