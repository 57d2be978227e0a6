"""``NAME=VALUE`` command-line items (``--checkpoint NAME=PATH``, ``--option KEY=VALUE``): the one parser."""

from __future__ import annotations

from collections.abc import Iterable

from pcc_ros.errors import ConfigError


def parse_assignments(
    items: Iterable[str], flag: str, form: str = "NAME=VALUE", require_value: bool = True
) -> dict[str, str]:
    """``["a=1", "b=x"]`` -> ``{"a": "1", "b": "x"}`` (names stripped; the last of a repeated name wins).

    An item without ``=``, with an empty name or (``require_value``) an empty value raises
    :class:`ConfigError` naming ``flag`` and the expected ``form``.
    """
    out: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or (require_value and not value):
            raise ConfigError(f"{flag} expects {form}, got {item!r}")
        out[name.strip()] = value
    return out
