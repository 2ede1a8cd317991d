"""Matching messages of several topics by header stamp (featureAssociation's 3 inputs, mapping's 4), and the
order of stamps a node accepts.

The original polls "is each input new and are their stamps within a tolerance"; here every message is
filed under the first pending set whose reference stamp is within the tolerance, and a set is released as
soon as it is complete. Older incomplete sets are then discarded (their messages lost a partner), and at
most ``keep`` sets wait at any time, so memory stays bounded whatever arrives: beyond that, the set that has
waited longest goes (not the one with the oldest stamp, so that stray messages stamped ahead of the data
cannot crowd out every set that the data would complete). Sets whose stamp is more than
``horizon_ns`` away from a new message's are discarded too: after a jump in time (a bag restarted) they would
otherwise wait forever for partners from the old timeline.

:class:`StampOrder` decides, for the stamp of each synchronised input, whether a node processes it, drops it
(out of order or duplicate) or resets first (time jumped back: a bag restarted or looped). A jump of more
than ``jump_ns`` in either direction is only believed once the next input continues the new timeline: a
single message with a wrong stamp costs that message, never the odometry or the map built so far, and a
sparse stream (inputs more than ``jump_ns`` apart, e.g. from an overloaded node) costs only latency. A wrong
stamp less than ``jump_ns`` ahead is caught the other way round: once ``resync_after`` inputs in a row come
stamped before it (and after each other), it was the wrong one, and the node carries on from them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

__all__ = ['StampSynchronizer', 'StampOrder', 'Decision']


class StampSynchronizer:
    def __init__(self, names: Sequence[str], tolerance_ns: int, keep: int = 4,
                 horizon_ns: int | None = 1_000_000_000):
        self.names = tuple(names)
        self.tolerance_ns = int(tolerance_ns)
        self.keep = int(keep)
        self.horizon_ns = None if horizon_ns is None else max(int(horizon_ns), self.tolerance_ns)
        self._pending: list[tuple[int, dict[str, Any]]] = []   # (reference stamp, parts), oldest first
        self._arrival: dict[int, int] = {}   # reference stamp -> when its set was opened (a counter)
        self._opened = 0
        self.dropped = 0   # messages discarded since the caller last reset this counter

    def add(self, name: str, stamp_ns: int, item: Any) -> dict[str, Any] | None:
        """File a message; returns {name: item} for a complete set, else None."""
        if name not in self.names:
            raise KeyError(f'unknown input {name!r}')
        stamp_ns = int(stamp_ns)
        if self.horizon_ns is not None and self._pending:
            kept = [entry for entry in self._pending if abs(entry[0] - stamp_ns) <= self.horizon_ns]
            if len(kept) < len(self._pending):
                self.dropped += sum(len(parts) for reference, parts in self._pending
                                    if abs(reference - stamp_ns) > self.horizon_ns)
                self._pending = kept
                self._arrival = {reference: self._arrival[reference] for reference, _ in kept
                                 if reference in self._arrival}
        target = None
        for index, (reference, parts) in enumerate(self._pending):
            if abs(stamp_ns - reference) <= self.tolerance_ns:
                if name in parts:             # a newer message of the same topic replaces the old one
                    self.dropped += 1
                target = index
                parts[name] = item
                break
        if target is None:
            self._opened += 1
            self._arrival[stamp_ns] = self._opened
            self._pending.append((stamp_ns, {name: item}))
            self._pending.sort(key=lambda entry: entry[0])
            while len(self._pending) > self.keep:
                waited_longest = min(range(len(self._pending)), key=lambda i: self._arrival.get(self._pending[i][0], 0))
                reference, parts = self._pending.pop(waited_longest)
                self._arrival.pop(reference, None)
                self.dropped += len(parts)
            target = next(i for i, entry in enumerate(self._pending) if entry[0] == stamp_ns)
        reference, parts = self._pending[target]
        if len(parts) < len(self.names):
            return None
        for _, older in self._pending[:target]:
            self.dropped += len(older)
        for released, _ in self._pending[:target + 1]:
            self._arrival.pop(released, None)
        del self._pending[:target + 1]
        return parts

    def clear(self) -> None:
        self._pending.clear()
        self._arrival.clear()

    def __len__(self) -> int:
        """Number of messages waiting for partners."""
        return sum(len(parts) for _, parts in self._pending)


@dataclass
class Decision:
    """What to do with an input (see :meth:`StampOrder.check`).

    ``action``: 'process'; 'drop' (``reason`` says why); 'hold' (a jump in time, kept until the next input
    confirms or refutes it); 'reset' (time jumped back, confirmed: reset, then process ``held`` and this
    input); 'jump' (time jumped forward, confirmed: process ``held`` and this input, no reset); 'resync'
    (inputs keep coming stamped a little before the last processed one: that one had a wrong stamp; process
    this input, ``jump_ns`` says by how much time went back).
    ``held`` is the item kept by the previous 'hold', ``jump_ns`` the size of a confirmed jump (signed) and
    ``discarded`` a held item refuted by this input (it was a single wrong stamp).
    """

    action: str
    reason: str = ''
    held: Any = None
    jump_ns: int = 0
    discarded: Any = None


class StampOrder:
    """The stamp policy of a node's inputs: time moves forward; a jump is confirmed by the next input.

    * newer than the last processed input (by at most ``jump_ns``): process;
    * not newer, by at most ``jump_ns``: drop (out of order or duplicate);
    * more than ``jump_ns`` away (either way): hold it. The next input decides. After a jump forward, an input
      newer than the held one confirms it ('jump': both are processed; inputs may simply be sparse); one back
      on the old timeline refutes it. After a jump back, an input newer than the held one but still before the
      old timeline confirms it ('reset', then both are processed); one on the old timeline refutes it. A
      refuted input is dropped: it was a single wrong stamp.

    Call :meth:`processed` after an input was processed, :meth:`reset` after the node reset.
    """

    def __init__(self, jump_ns: int = 1_000_000_000, resync_after: int = 3):
        self.jump_ns = int(jump_ns)
        self.resync_after = int(resync_after)
        self.last_ns: int | None = None
        self._held: tuple[int, Any] | None = None
        self._behind: list[int] = []   # stamps of the inputs dropped in a row as out of order

    @property
    def holding(self) -> bool:
        return self._held is not None

    @property
    def newest_ns(self) -> int | None:
        """The newest stamp seen: the held one when it is newer than the last processed one."""
        held = self._held[0] if self._held is not None else None
        if held is None or (self.last_ns is not None and held < self.last_ns):
            return self.last_ns
        return held

    def check(self, stamp_ns: int, item: Any = None) -> Decision:
        stamp_ns = int(stamp_ns)
        held, self._held = self._held, None
        if held is not None:
            held_ns, held_item = held
            last = self.last_ns if self.last_ns is not None else held_ns
            if stamp_ns == held_ns:                                 # a duplicate of the held input
                self._held = held
                return Decision('drop', 'duplicate stamp')
            if held_ns > last and stamp_ns > held_ns:               # forward, and time goes on from there
                return Decision('jump', held=held_item, jump_ns=held_ns - last)
            if held_ns < last and held_ns < stamp_ns < last - self.jump_ns:   # back, and goes on from there
                return Decision('reset', held=held_item, jump_ns=held_ns - last)
            decision = self._check_without_held(stamp_ns, item)   # refuted (or yet another jump: held)
            decision.discarded = held_item
            return decision
        return self._check_without_held(stamp_ns, item)

    def _check_without_held(self, stamp_ns: int, item: Any) -> Decision:
        last = self.last_ns
        if last is None or last < stamp_ns <= last + self.jump_ns:
            self._behind.clear()
            return Decision('process')
        if last - self.jump_ns <= stamp_ns <= last:
            if stamp_ns == last:
                return Decision('drop', 'duplicate stamp')
            if self._behind and stamp_ns <= self._behind[-1]:
                self._behind.clear()
            self._behind.append(stamp_ns)
            if len(self._behind) >= self.resync_after:
                self._behind.clear()
                return Decision('resync', jump_ns=stamp_ns - last)
            return Decision('drop', 'out of order')
        self._behind.clear()
        self._held = (stamp_ns, item)
        return Decision('hold')

    def processed(self, stamp_ns: int) -> None:
        self.last_ns = int(stamp_ns)

    def reset(self) -> None:
        self.last_ns = None
        self._behind.clear()
