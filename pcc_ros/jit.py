"""numba compilation of the package's compiled loops (the filter's and the networks' CPU kernels).

Every kernel is compiled on first use without the GIL (``nogil``: the node's threads run them
side by side), with numpy's error model (a division by zero is an infinity, as in numpy) and a
disk cache, so a process after the first loads it instead of compiling (seconds). Where numba
finds no writable place for that cache (a read-only install run by a user without a writable
home; ``NUMBA_CACHE_DIR`` names one) it raises at decoration ("cannot cache function ...: no
locator available"): the kernel is then compiled without a cache, in every process, and a
warning says so once, instead of the import failing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from numba import njit

log = logging.getLogger(__name__)

#: The kernels compiled without a disk cache (no writable cache directory), by name.
uncached: list[str] = []


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
            log.warning("no writable cache directory for pcc_ros's compiled kernels (the package's __pycache__, "
                        "the user's cache; NUMBA_CACHE_DIR names one): they compile in every process (seconds at "
                        "start-up)")
        uncached.append(func.__name__)
        return njit(**{**settings, "cache": False})(func)

    return decorate
