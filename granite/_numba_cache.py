"""A numba on-disk cache that is always valid for granite's kernels.

numba keys a cached kernel by its own source file only (modification time and size): a kernel
that calls a kernel of another module, or reads a constant of another module, is not recompiled
when that other file changes, and stale machine code runs. So before any kernel is compiled
(this runs from ``granite/__init__.py``), granite points numba's cache (``NUMBA_CACHE_DIR``) at a
directory named after a hash of every ``.py`` file of the package: any change of any granite
source starts a fresh cache, and a cache found on disk always belongs to exactly these sources
(numba itself invalidates entries of another numba or Python version). Nothing has to be
deleted by hand.

Where: ``$GRANITE_NUMBA_CACHE_ROOT/<hash>`` if that variable is set, else ``.numba_cache/<hash>``
beside the package in a source checkout (a folder with ``pyproject.toml``), else
``$XDG_CACHE_HOME/granite-py/numba/<hash>`` (``~/.cache/...``); a temporary folder if none is
writable. Caches of older sources are removed once they are a day old and not among the
``_KEEP`` most recent. ``NUMBA_CACHE_DIR`` is process-wide: numba caches of other packages
imported in the same process land there too (still valid: numba's own per-file check applies).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
_KEEP = 3  # caches of other source versions kept (switching branches back and forth)
_MIN_AGE_S = 86400.0  # a cache is removed only when it has not been used for a day


def source_digest(package_dir: Path = PACKAGE_DIR) -> str:
    """Hex digest of the package's Python sources (path and bytes of every ``.py`` file)."""
    h = hashlib.sha256()
    for path in sorted(package_dir.rglob("*.py")):
        h.update(path.relative_to(package_dir).as_posix().encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()


def cache_root(package_dir: Path = PACKAGE_DIR) -> Path:
    """The folder holding one numba cache per source version (see the module docstring)."""
    env = os.environ.get("GRANITE_NUMBA_CACHE_ROOT")
    if env:
        return Path(env)
    checkout = package_dir.parent
    if (checkout / "pyproject.toml").is_file():
        return checkout / ".numba_cache"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "granite-py" / "numba"


def configure_numba_cache(package_dir: Path = PACKAGE_DIR) -> Path:
    """Set ``NUMBA_CACHE_DIR`` (and numba's config, if numba is already imported) to the cache
    of the current sources of ``package_dir``; returns that folder."""
    digest = source_digest(package_dir)[:16]
    cache_dir = cache_root(package_dir) / digest
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        os.utime(cache_dir)
    except OSError:
        cache_dir = Path(tempfile.gettempdir()) / "granite-py-numba" / digest
        cache_dir.mkdir(parents=True, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = str(cache_dir)
    if "numba" in sys.modules:  # numba read its environment already: set its config too
        from numba.core import config

        config.CACHE_DIR = str(cache_dir)
    _prune(cache_dir)
    return cache_dir


def has_cached_kernels(cache_dir: Path | None = None, kernels=()) -> bool:
    """Whether numba's cache holds compiled kernels: with ``kernels`` (numba dispatchers with
    ``cache=True``), whether each of them has an index file (``*.nbi``) there; without, whether
    the cache folder (default: the one :func:`configure_numba_cache` set) holds any."""
    if kernels:
        try:
            return all(Path(k._cache._cache_file._index_path).is_file() for k in kernels)
        except (AttributeError, OSError):  # not numba's cached dispatchers as expected
            pass
    folder = cache_dir or os.environ.get("NUMBA_CACHE_DIR")
    if not folder:
        return False
    try:
        return next(Path(folder).rglob("*.nbi"), None) is not None
    except OSError:
        return False


def compile_notice(command: str, kernels=()) -> str | None:
    """A one-line note for the user when numba has not cached ``kernels`` (the command's
    largest; any kernel if none given) for these sources yet: the command's first frames then
    wait for the compilation (the first run after an install or an update; cached for the
    following runs). None when they are cached."""
    if has_cached_kernels(kernels=kernels):
        return None
    return (f"{command}: first run of this granite version: numba compiles the kernels first "
            f"(1-2 minutes on two cores, the first frames wait for it), cached in "
            f"{os.environ.get('NUMBA_CACHE_DIR')} for the following runs")


def _prune(current: Path) -> None:
    """Remove caches of other source versions beyond the ``_KEEP`` most recently used ones,
    once they are ``_MIN_AGE_S`` old (another process may still use a recent one)."""
    try:
        others = [p for p in current.parent.iterdir() if p.is_dir() and p != current]
        others.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return
    now = time.time()
    for old in others[_KEEP:]:
        try:
            if now - old.stat().st_mtime > _MIN_AGE_S:
                shutil.rmtree(old, ignore_errors=True)
        except OSError:
            pass
