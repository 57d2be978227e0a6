"""numba compilation of the package's compiled loops (the filter's and the networks' CPU kernels).

Every kernel is compiled on first use without the GIL (``nogil``: the node's threads run them
side by side), with numpy's error model (a division by zero is an infinity, as in numpy) and a
disk cache, so a process after the first loads it instead of compiling (about 40 s of compiling
on a 2-core machine against well under a second of loading).

Where the cache lives (:func:`cache_root`): ``$PCC_KERNEL_CACHE`` when set, else the user's
cache (``$NUMBA_CACHE_DIR/pcc_ros``, ``$XDG_CACHE_HOME/pcc_ros/kernels`` or
``~/.cache/pcc_ros/kernels``), else a folder in the temporary directory. Its layout is relative to
the package, one folder per version of a module's source
(``pcc_ros/pipeline/evidence_kernels-<hash>``: two checkouts or installs share what they have in
common and never overwrite each other's entries), and numba keys every entry by the CPU and
numba's version, so a cache compiled at build time (``setup.py`` compiles the shipped nodes'
kernels into ``pcc_ros/_kernel_cache``: :mod:`pcc_ros.runtime.kernel_cache`) is valid wherever
the package is installed on the same machine. A fresh process copies that shipped cache into
its writable one (a few MB, milliseconds), so a read-only install prefix starts in seconds too;
an entry that does not fit (another CPU, another numba) is compiled and written there.

Where no cache folder can be written at all, numba raises at decoration ("cannot cache function
...: no locator available"): the kernel is then compiled without a cache, in every process, and a
warning says so once, instead of the import failing.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from numba import njit
from numba.core import caching

log = logging.getLogger(__name__)

#: The kernels compiled without a disk cache (no writable cache directory), by name.
uncached: list[str] = []

#: The package folder; cache entries are laid out relative to its parent.
PACKAGE_DIR = Path(__file__).resolve().parent
#: The cache compiled at build time and installed with the package (may be read-only).
SHIPPED_CACHE = PACKAGE_DIR / "_kernel_cache"
#: Names the cache folder exactly (the build writes the shipped cache through it).
CACHE_ENV = "PCC_KERNEL_CACHE"


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _candidates() -> list[Path]:
    """The cache folders to try, best first."""
    if os.environ.get(CACHE_ENV):
        return [Path(os.environ[CACHE_ENV])]
    folders = [Path(os.environ["NUMBA_CACHE_DIR"]) / "pcc_ros"] if os.environ.get("NUMBA_CACHE_DIR") else []
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    folders.append(Path(xdg) / "pcc_ros" / "kernels")
    uid = os.getuid() if hasattr(os, "getuid") else 0
    folders.append(Path(tempfile.gettempdir()) / f"pcc_ros-kernels-{uid}")
    return folders


#: A module's global naming the other source files, relative to its folder, that its kernels
#: compile code from (numba overloads defined elsewhere): they key its cache folder too, since
#: numba checks only the kernel's own file.
CACHE_DEPENDS = "CACHE_DEPENDS"


@functools.cache
def _source_key(py_file: str, depends: tuple[str, ...] = ()) -> str:
    """The cache folder of one version of a module: its name and a hash of its source and of
    the ``depends`` files beside it."""
    path = Path(py_file)
    digest = hashlib.sha256(path.read_bytes())
    for name in depends:
        digest.update((path.parent / name).read_bytes())
    return f"{path.stem}-{digest.hexdigest()[:16]}"


@functools.cache
def cache_root() -> Path | None:
    """The writable kernel cache of this process (None: none can be written), seeded once from
    the shipped cache."""
    for folder in _candidates():
        if _writable(folder):
            _seed(folder)
            return folder
    return None


def _seed(root: Path) -> None:
    """Copy the shipped cache's entries that ``root`` lacks or holds older copies of."""
    if not SHIPPED_CACHE.is_dir() or root.resolve() == SHIPPED_CACHE.resolve():
        return
    for source in SHIPPED_CACHE.rglob("*"):
        if not source.is_file():
            continue
        target = root / source.relative_to(SHIPPED_CACHE)
        try:
            if target.exists() and target.stat().st_mtime >= source.stat().st_mtime:
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
        except OSError as exc:  # a missing entry is compiled instead: slower, never wrong
            log.debug("kernel cache: could not copy %s: %s", source, exc)


class PackageCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """numba's cache locator for the package's own kernels: ``cache_root()/pcc_ros/<dir>/<module>-<hash>``
    (numba's own locators key the folder by the absolute source path, so a cache compiled at
    build time would not be found after installation)."""

    def __init__(self, py_func, py_file: str, root: Path) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        path = Path(py_file).resolve()
        depends = tuple(py_func.__globals__.get(CACHE_DEPENDS, ()))
        self._cache_path = str(root / path.parent.relative_to(PACKAGE_DIR.parent) / _source_key(str(path), depends))

    def get_cache_path(self) -> str:
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        path = Path(py_file).resolve()
        if PACKAGE_DIR not in path.parents or not path.is_file():
            return None  # not one of ours: numba's own locators
        root = cache_root()
        if root is None:
            return None
        locator = cls(py_func, py_file, root)
        try:
            locator.ensure_cache_path()
        except OSError:
            return None
        return locator


if PackageCacheLocator not in caching.CacheImpl._locator_classes:
    caching.CacheImpl._locator_classes.insert(0, PackageCacheLocator)


def compiled(**options) -> Callable:
    """``numba.njit(nogil=True, cache=True, error_model="numpy", **options)``, without the disk
    cache where none can be written."""
    settings = {"nogil": True, "cache": True, "error_model": "numpy", **options}

    def decorate(func):
        try:
            return njit(**settings)(func)
        except RuntimeError as exc:
            if "no locator available" not in str(exc):
                raise
        if not uncached:
            log.warning("no writable cache directory for pcc_ros's compiled kernels (PCC_KERNEL_CACHE, the "
                        "user's cache, the temporary directory): they compile in every process (about 40 s at "
                        "start-up)")
        uncached.append(func.__name__)
        return njit(**{**settings, "cache": False})(func)

    return decorate
