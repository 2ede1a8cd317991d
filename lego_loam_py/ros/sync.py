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

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = ['StampSynchronizer', 'StampOrder', 'Decision']


class StampSynchronizer:
    def __init__(self, names: Sequence[str], tolerance_ns: int, keep: int = 4, horizon_ns: int | None = 1_000_000_000):
        self.names = tuple(names)
        self.tolerance_ns = int(tolerance_ns)
        self.keep = int(keep)
        self.horizon_ns = None if horizon_ns is None else max(int(horizon_ns), self.tolerance_ns)
        self._pending: list[tuple[int, dict[str, Any]]] = []  # (reference stamp, parts), oldest first
        self._arrival: dict[int, int] = {}  # reference stamp -> when its set was opened (a counter)
        self._opened = 0
        self.dropped = 0  # messages discarded since the caller last reset this counter

    def add(self, name: str, stamp_ns: int, item: Any) -> dict[str, Any] | None:
        """File a message; returns {name: item} for a complete set, else None."""
        if name not in self.names:
            raise KeyError(f'unknown input {name!r}')
        stamp_ns = int(stamp_ns)
        if self.horizon_ns is not None and self._pending:
            kept = [entry for entry in self._pending if abs(entry[0] - stamp_ns) <= self.horizon_ns]
            if len(kept) < len(self._pending):
                self.dropped += sum(
                    len(parts) for reference, parts in self._pending if abs(reference - stamp_ns) > self.horizon_ns
                )
                self._pending = kept
                self._arrival = {
                    reference: self._arrival[reference] for reference, _ in kept if reference in self._arrival
                }
        target = None
        for index, (reference, parts) in enumerate(self._pending):
            if abs(stamp_ns - reference) < self.tolerance_ns:  # strictly, as the original's |Δstamp| < 0.05 s
                if name in parts:  # a newer message of the same topic replaces the old one
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
        for released, _ in self._pending[: target + 1]:
            self._arrival.pop(released, None)
        del self._pending[: target + 1]
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

    ``action``: 'process'; 'drop' (``reason`` says why); 'hold' (a jump in time, kept until the next inputs
    confirm or refute it); 'reset' (time jumped back, confirmed: reset, then process ``held`` and this input);
    'jump' (time jumped forward, confirmed: process ``held`` and this input, no reset); 'resync' (the inputs
    ahead of this one had wrong stamps: process ``held`` and this input, nothing reset). ``held`` lists the
    items kept by earlier 'hold's, oldest first, ``jump_ns`` is the size of a confirmed jump (signed) and
    ``discarded`` lists held items refuted by this input (they had wrong stamps).
    """

    action: str
    reason: str = ''
    held: list = field(default_factory=list)
    jump_ns: int = 0
    discarded: list = field(default_factory=list)


class StampOrder:
    """The stamp policy of a node's inputs: time moves forward; a jump is believed once later inputs confirm it.

    * newer than the last processed input (by at most ``jump_ns``): process;
    * not newer, by at most ``jump_ns``: drop (out of order or duplicate); after ``resync_after`` such inputs in
      a row (each newer than the one before), the last processed one had a wrong stamp: 'resync';
    * more than ``jump_ns`` away (either way): hold it. A jump forward is confirmed by the next input newer than
      it ('jump': both processed; inputs may simply be sparse). A jump back is confirmed by ``restart_after``
      inputs in a row on the new timeline (each newer than the one before, all before the old timeline): back
      to the start of the current timeline or before it, a restart ('reset', then all processed: a bag played
      again); to a point after that start, the inputs ahead of it had wrong stamps ('resync', all processed,
      nothing reset). An input on the old timeline refutes what is held: those inputs had wrong stamps and are
      dropped. So a single wrong stamp costs that input only, and a restart needs more than a couple of them.

    Call :meth:`processed` after an input was processed, :meth:`reset` after the node reset.
    """

    def __init__(self, jump_ns: int = 1_000_000_000, resync_after: int = 3, restart_after: int = 3):
        self.jump_ns = int(jump_ns)
        self.resync_after = int(resync_after)
        self.restart_after = int(restart_after)
        self.last_ns: int | None = None
        self.first_ns: int | None = None  # the first input processed since the last reset: the timeline's start
        self._held: list[tuple[int, Any]] = []
        self._behind: list[int] = []  # stamps of the inputs dropped in a row as out of order

    @property
    def holding(self) -> bool:
        return bool(self._held)

    @property
    def newest_ns(self) -> int | None:
        """The newest stamp seen: a held one when it is newer than the last processed one."""
        held = self._held[-1][0] if self._held else None
        if held is None or (self.last_ns is not None and held < self.last_ns):
            return self.last_ns
        return held

    def check(self, stamp_ns: int, item: Any = None) -> Decision:
        stamp_ns = int(stamp_ns)
        if self._held:
            first_held_ns, newest_held_ns = self._held[0][0], self._held[-1][0]
            last = self.last_ns if self.last_ns is not None else first_held_ns
            if stamp_ns == newest_held_ns:  # a duplicate of a held input
                return Decision('drop', 'duplicate stamp')
            items = [held_item for _, held_item in self._held]
            if first_held_ns > last and stamp_ns > newest_held_ns:  # forward, and time goes on from there
                self._held = []
                return Decision('jump', held=items, jump_ns=first_held_ns - last)
            if first_held_ns < last and newest_held_ns < stamp_ns < last - self.jump_ns:  # back, and goes on
                if len(self._held) + 1 < self.restart_after:
                    self._held.append((stamp_ns, item))
                    return Decision('hold')
                self._held = []
                if self.first_ns is not None and first_held_ns > self.first_ns:
                    # Back, but not to before this timeline began: no restart, the inputs ahead had wrong stamps.
                    return Decision('resync', held=items, jump_ns=first_held_ns - last)
                return Decision('reset', held=items, jump_ns=first_held_ns - last)
            self._held = []
            decision = self._check_without_held(stamp_ns, item)  # refuted (or yet another jump: held)
            decision.discarded = items
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
        self._held = [(stamp_ns, item)]
        return Decision('hold')

    def processed(self, stamp_ns: int) -> None:
        self.last_ns = int(stamp_ns)
        if self.first_ns is None:
            self.first_ns = self.last_ns

    def reset(self) -> None:
        self.last_ns = None
        self.first_ns = None
        self._behind.clear()
