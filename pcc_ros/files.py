"""Atomic file outputs: the one helper every writer of the package uses.

A file is written to a temporary sibling (``.<name>.tmp<pid>``, same directory so the
rename stays on one file system), flushed and ``fsync``-ed, then renamed over the target
with :func:`os.replace`. A reader therefore sees either the old file or the complete new
one, never a partial file — also after an exception, a Ctrl-C or a crash of the process
(a crash leaves at most a hidden ``.tmp<pid>`` sibling, which :func:`remove_stale_temporaries`
clears). Two processes writing the same target never share a temporary.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

TMP_MARK = ".tmp"


def temporary_sibling(path: str | Path) -> Path:
    """``dir/.<name>.tmp<pid>``: where :func:`atomic_write` writes before the rename."""
    path = Path(path)
    return path.with_name(f".{path.name}{TMP_MARK}{os.getpid()}")


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # not supported on this platform / file system: the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_write(path: str | Path, mode: str = "wb", encoding: str | None = None) -> Iterator[IO[Any]]:
    """Open a temporary sibling of ``path`` for writing; it replaces ``path`` only if the block completes.

    ``mode`` is ``"wb"`` (default) or ``"w"`` (text, UTF-8 unless ``encoding``). Any
    exception, including ``KeyboardInterrupt``, removes the temporary and leaves an
    existing ``path`` untouched.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    tmp = temporary_sibling(path)
    if "b" not in mode and encoding is None:
        encoding = "utf-8"
    try:
        with open(tmp, mode, encoding=encoding) as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_write(path, "wb") as stream:
        stream.write(data)


def write_text(path: str | Path, text: str) -> None:
    with atomic_write(path, "w") as stream:
        stream.write(text)


def nonfinite_as_none(value: Any) -> Any:
    """``value`` for JSON with every NaN / inf float replaced by ``None`` (``null``), looked at
    structurally (a string that says "NaN" stays): dicts and lists walked, tuples as lists, numpy
    scalars and arrays as Python numbers and lists. Anything else is returned as it is."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: nonfinite_as_none(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [nonfinite_as_none(item) for item in value]
    return value


def write_json(path: str | Path, value: Any, *, nonfinite_null: bool = False, **dumps_options: Any) -> None:
    """``json.dumps(value, **dumps_options)`` plus a newline, atomically.

    ``nonfinite_null``: NaN / inf written as ``null`` (:func:`nonfinite_as_none`; any left after
    ``default`` is refused) instead of ``json``'s non-standard ``NaN`` / ``Infinity``."""
    if nonfinite_null:
        value = nonfinite_as_none(value)
        dumps_options.setdefault("allow_nan", False)
    write_text(path, json.dumps(value, **dumps_options) + "\n")


def save_npy(path: str | Path, array) -> None:
    """``np.save`` (never pickled) atomically; ``path`` is used exactly as given."""
    with atomic_write(path, "wb") as stream:
        np.save(stream, np.asarray(array), allow_pickle=False)


def save_npz(path: str | Path, **arrays) -> None:
    """``np.savez`` (uncompressed, never pickled) atomically; ``path`` is used exactly as given."""
    with atomic_write(path, "wb") as stream:
        np.savez(stream, **arrays)


def remove_stale_temporaries(directory: str | Path) -> int:
    """Delete ``.*.tmp<pid>`` files in ``directory`` whose writing process is gone; how many."""
    removed = 0
    directory = Path(directory)
    if not directory.is_dir():
        return 0
    for tmp in directory.glob(f".*{TMP_MARK}*"):
        pid = tmp.name.rpartition(TMP_MARK)[2]
        if not pid.isdigit() or not tmp.is_file():
            continue
        if _alive(int(pid)):
            continue
        tmp.unlink(missing_ok=True)
        removed += 1
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
