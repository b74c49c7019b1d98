"""Old public names kept for one release: each use warns (DeprecationWarning) and names the new one."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """Warn that ``old`` is now ``new``; ``stacklevel`` 3 points at the caller of the function that calls this."""
    warnings.warn(f"{old}: renamed to {new}; the old name goes in the next release", DeprecationWarning,
                  stacklevel=stacklevel)


class RenamedKeys(dict):
    """A dict that still answers to renamed keys' old names (``d[old]`` warns and returns ``d[new]``)."""

    def __init__(self, data: Mapping, renamed: Mapping[str, str]):
        super().__init__(data)
        self._renamed = dict(renamed)  # old -> new

    def __missing__(self, key: Any):
        new = self._renamed.get(key)
        if new is None or new not in self:
            raise KeyError(key)
        warn_renamed(f"[{key!r}]", f"[{new!r}]")
        return self[new]


def get_renamed(mapping: Mapping, new: str, old: str) -> Any:
    """``mapping[new]``, or ``mapping[old]`` with a warning when only the old name is there."""
    if new not in mapping and old in mapping:
        warn_renamed(f"[{old!r}]", f"[{new!r}]")
        return mapping[old]
    return mapping[new]
