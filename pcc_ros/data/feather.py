"""Apache Arrow feather tables (the Argoverse 2 files) read into numpy columns, with named errors.

One place for the pyarrow calls, so every reader of a feather file gets the same errors:
a missing file, bytes that are not an Arrow IPC file (truncated, corrupt), a table without
a column the reader needs, or nulls in one are :class:`~pcc_ros.errors.DataError` naming
the file. pyarrow is imported here on first use, so the rest of the package (and
``pcc --help``) does not need it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pcc_ros.errors import DataError


def _pyarrow():
    try:
        import pyarrow
        import pyarrow.feather
        import pyarrow.ipc
    except ImportError as exc:  # pragma: no cover - pinned in requirements.txt
        raise DataError("pyarrow is not installed; Argoverse 2 tables are Arrow feather files",
                        hint="pip install pyarrow (requirements.txt pins the tested version)") from exc
    return pyarrow


def read_columns(
    path: str | Path, columns: Sequence[str], what: str = "table", text: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    """The ``columns`` of the feather file ``path`` as numpy arrays; the ``text`` ones as object
    arrays of str (plain or dictionary-encoded strings), every other one must be numeric.

    Raises :class:`DataError` naming the file when it is missing or unreadable, lacks a column,
    has nulls in one (a damaged export; a null would otherwise become NaN or ``None``) or a
    column of the wrong kind."""
    pa = _pyarrow()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: missing {what}", hint="check the dataset layout with `pcc check-data`")
    try:
        table = pa.feather.read_table(path, memory_map=False)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable {what} ({type(exc).__name__}: {exc})",
                        hint="the file is truncated or not an Arrow feather file; re-download it") from exc
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise DataError(f"{path}: {what} lacks column(s) {missing} (has {table.column_names})")
    out = {}
    for name in columns:
        column = table.column(name)
        if column.null_count:
            raise DataError(f"{path}: {what} column {name!r} has {column.null_count} null value(s)")
        kind = column.type
        numeric = pa.types.is_integer(kind) or pa.types.is_floating(kind)
        if name in text:  # strings, large strings, dictionary-encoded ones (a pandas Categorical)
            values = np.empty(len(column), dtype=object)
            values[:] = [str(v) for v in column.to_pylist()]
            out[name] = values
        elif not numeric:
            raise DataError(f"{path}: {what} column {name!r} has type {kind}, expected numbers")
        else:
            out[name] = column.to_numpy()
    return out


def schema_columns(path: str | Path) -> list[str]:
    """Column names of a feather file from its footer, without reading the data (``pcc check-data``);
    :class:`DataError` naming the file when it is not a readable Arrow file."""
    pa = _pyarrow()
    path = Path(path)
    try:
        try:
            with pa.ipc.open_file(path) as reader:  # feather v2 = an Arrow IPC file: the footer holds the schema
                return list(reader.schema.names)
        except pa.ArrowInvalid:  # feather v1 (legacy): only a full read knows its columns
            return list(pa.feather.read_table(path, memory_map=False).column_names)
    except (pa.ArrowException, OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable Arrow feather file ({type(exc).__name__}: {exc})") from exc
