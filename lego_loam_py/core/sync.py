"""Matching messages of several topics by header stamp (featureAssociation's 3 inputs, mapping's 4).

The original polls "is each input new and are their stamps within a tolerance"; here every message is
filed under the first pending set whose reference stamp is within the tolerance, and a set is released as
soon as it is complete. Older incomplete sets are then discarded (their messages lost a partner), and at
most ``keep`` sets wait at any time, so memory stays bounded whatever arrives.
"""
from __future__ import annotations

from typing import Any, Sequence

__all__ = ['StampSynchronizer']


class StampSynchronizer:
    def __init__(self, names: Sequence[str], tolerance_ns: int, keep: int = 4):
        self.names = tuple(names)
        self.tolerance_ns = int(tolerance_ns)
        self.keep = int(keep)
        self._pending: list[tuple[int, dict[str, Any]]] = []   # (reference stamp, parts), oldest first
        self.dropped = 0   # messages discarded since the caller last reset this counter

    def add(self, name: str, stamp_ns: int, item: Any) -> dict[str, Any] | None:
        """File a message; returns {name: item} for a complete set, else None."""
        if name not in self.names:
            raise KeyError(f'unknown input {name!r}')
        target = None
        for index, (reference, parts) in enumerate(self._pending):
            if abs(stamp_ns - reference) <= self.tolerance_ns:
                if name in parts:             # a newer message of the same topic replaces the old one
                    self.dropped += 1
                target = index
                parts[name] = item
                break
        if target is None:
            self._pending.append((stamp_ns, {name: item}))
            self._pending.sort(key=lambda entry: entry[0])
            target = next(i for i, entry in enumerate(self._pending) if entry[0] == stamp_ns)
            while len(self._pending) > self.keep:
                _, parts = self._pending.pop(0)
                self.dropped += len(parts)
                target -= 1
            if target < 0:
                return None
        reference, parts = self._pending[target]
        if len(parts) < len(self.names):
            return None
        for _, older in self._pending[:target]:
            self.dropped += len(older)
        del self._pending[:target + 1]
        return parts

    def clear(self) -> None:
        self._pending.clear()
