"""Where numba keeps its compiled kernels, so that ``cache=True`` never fails a command.

numba caches beside the sources (``__pycache__``) or, when that is not writable, in the
user's cache folder; when neither is, decorating a ``cache=True`` function raises at
import. An installed package is often read-only for the user who runs it (a Docker image,
a system-wide install), and a service account may have no home: then the cache goes to a
folder of the system's temporary directory, or of ``/dev/shm``. When not even those take a
file, the kernels are compiled in memory on every run (slower to start, never failing):
numba's ``cache=True`` is switched off for this process (numba has no setting for that; its
``Dispatcher.enable_caching`` is replaced by a no-op). ``$NUMBA_CACHE_DIR``, when set to a
writable folder, is left alone (numba skips it by itself when it is not writable).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

CACHE_ENV = "NUMBA_CACHE_DIR"
#: Why the kernels are compiled without a cache in this process (None: they are cached).
uncached_reason: str | None = None


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


def shm_cache_dir() -> Path:
    """A per-user folder in the shared-memory file system (Linux), the last place tried."""
    user = os.getuid() if hasattr(os, "getuid") else "user"
    return Path("/dev/shm") / f"numba-cache-{user}"


def choose_cache_dir(in_tree: Path, user: Path, *fallbacks: Path) -> Path | None:
    """The folder to point ``$NUMBA_CACHE_DIR`` at, or None when numba finds a writable one itself
    (or when nothing is writable: see :func:`ensure_writable_cache`)."""
    if writable(in_tree / "__pycache__") or writable(user):
        return None
    return next((f for f in fallbacks if writable(f)), None)


def compile_without_cache(reason: str) -> None:
    """Make numba's ``cache=True`` a no-op in this process: decorating then never fails, and
    every kernel is compiled in memory when first called."""
    global uncached_reason
    from numba.core.dispatcher import Dispatcher

    Dispatcher.enable_caching = lambda self: None  # type: ignore[method-assign]
    uncached_reason = reason


def ensure_writable_cache() -> None:
    """Set ``$NUMBA_CACHE_DIR`` (and numba's config, if numba is already imported) to a writable
    folder when numba would find none, or switch the cache off when no folder takes a file;
    never raises."""
    current = os.environ.get(CACHE_ENV)
    try:
        if current and writable(Path(current)):
            return
        in_tree, user = Path(__file__).resolve().parent, user_cache_dir()
        try:
            fallbacks = [fallback_cache_dir(), shm_cache_dir()]
        except OSError:  # tempfile finds no usable temporary directory at all
            fallbacks = [shm_cache_dir()]
        chosen = choose_cache_dir(in_tree, user, *fallbacks)
        if chosen is None:
            if not (writable(in_tree / "__pycache__") or writable(user)):
                compile_without_cache("no writable folder for numba's compile cache (beside the package, "
                                      "~/.cache, the temporary directory, /dev/shm)")
            return
    except Exception:  # noqa: BLE001 - a cache location must never stop the tool
        return
    os.environ[CACHE_ENV] = str(chosen)
    config = sys.modules.get("numba.core.config")
    if config is not None:
        config.CACHE_DIR = str(chosen)
