"""The key selection shared by the readers that map a source's arrays onto our keys."""

from __future__ import annotations

from nostra.data.errors import DataError


def select_keys(mapping: dict, keys, where, what: str) -> dict:
    """``mapping`` (our key -> source entry) cut to ``keys`` plus actions; every asked key must map.

    ``where`` is the file named in the error, ``what`` the source's word for an entry ("array", "feature")."""
    if keys is None:
        return mapping
    missing = [k for k in keys if k not in mapping]
    if missing:
        raise DataError(where, f"no {what} maps to {missing}; mapped keys: {sorted(mapping)}", key=missing[0])
    return {k: v for k, v in mapping.items() if k in keys or k == "actions"}
