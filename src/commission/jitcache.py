"""Where numba keeps its compiled kernels, so that ``cache=True`` never fails a command.

numba caches beside the sources (``__pycache__``) or, when that is not writable, in the
user's cache folder; when neither is, decorating a ``cache=True`` function raises at
import. An installed package is often read-only for the user who runs it (a Docker image,
a system-wide install), and a service account may have no home: then the cache goes to a
folder of the system's temporary directory. ``$NUMBA_CACHE_DIR``, when set, is left alone.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

CACHE_ENV = "NUMBA_CACHE_DIR"


def writable(folder: Path) -> bool:
    """True when ``folder`` exists or can be created, and a file can be written in it (numba's own test)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def user_cache_dir() -> Path:
    """numba's user-wide cache folder (``$XDG_CACHE_HOME/numba``, else ``~/.cache/numba``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "numba"


def fallback_cache_dir() -> Path:
    """A per-user folder under the system's temporary directory."""
    user = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
    return Path(tempfile.gettempdir()) / f"numba-cache-{user}"


def choose_cache_dir(in_tree: Path, user: Path, fallback: Path) -> Path | None:
    """The folder to point ``$NUMBA_CACHE_DIR`` at, or None when numba finds a writable one itself."""
    if writable(in_tree / "__pycache__") or writable(user):
        return None
    return fallback if writable(fallback) else None


def ensure_writable_cache() -> None:
    """Set ``$NUMBA_CACHE_DIR`` (and numba's config, if numba is already imported) to a writable
    folder when numba would find none; never raises."""
    if os.environ.get(CACHE_ENV):
        return
    try:
        chosen = choose_cache_dir(Path(__file__).resolve().parent, user_cache_dir(), fallback_cache_dir())
    except Exception:  # noqa: BLE001 - a cache location must never stop the tool
        return
    if chosen is None:
        return
    os.environ[CACHE_ENV] = str(chosen)
    config = sys.modules.get("numba.core.config")
    if config is not None:
        config.CACHE_DIR = str(chosen)
