"""The measurements of every body of a live stream in one set of preallocated arrays (the storage
of :class:`~dqpose.fusion.Tracker`): rows in arrival order tagged with their body, each body's
rows found through its own index, memory bounded by the largest live window.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dqpose.fusion.results import DOF


class _Store:
    """Every body's measurements in one set of preallocated arrays, in arrival order, each row
    tagged with its body. A message costs a few NumPy operations whatever the number of bodies
    in it; rows that fell out of their body's window are dropped when the arrays are full
    (compacted in place, grown only when the live rows fill half), so memory follows the largest
    live window, flat over a long stream. Each body's rows are listed in an index of its own, so
    finding them costs what the body holds, not what the stream holds (a world of 1000 bodies
    with 10 s of history holds hundreds of thousands of rows); beside it the running maximum of
    their taken times, so rows taken from a time on are found from the first index entry whose
    running maximum reaches it: what the window holds and rows that came late, not the body's
    whole buffer."""

    # as they came (``poses``, ``covs``) and in the world frame (``wposes``, and ``wcovs`` when a
    # source's body offset moves them): each row brought there once, not at every fit
    _ARRAYS = ("ids", "body", "codes", "times", "taken", "poses", "covs", "wposes")

    def __init__(self, capacity: int = 256, world_covs: bool = False):
        self._arrays = self._ARRAYS + (("wcovs",) if world_covs else ())
        self.n = 0
        self._index: dict[int, np.ndarray] = {}     # body -> its rows, ascending (a prefix)
        self._count: dict[int, int] = {}            # body -> how much of its index is used
        self._reach: dict[int, np.ndarray] = {}     # body -> running max of its rows' taken
        self.ids = np.empty(capacity, np.int64)
        self.body = np.empty(capacity, np.int64)
        self.codes = np.empty(capacity, np.int64)
        self.times = np.empty(capacity)
        self.taken = np.empty(capacity)
        self.poses = np.empty((capacity, 8))
        self.covs = np.empty((capacity, DOF, DOF))
        self.wposes = np.empty((capacity, 8))
        if world_covs:
            self.wcovs = np.empty((capacity, DOF, DOF))

    def world(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows' poses and covariances in the world frame."""
        covs = self.wcovs if "wcovs" in self._arrays else self.covs
        return self.wposes[rows], covs[rows]

    def live(self, newest: np.ndarray, window: float, cap: Optional[int] = None) -> np.ndarray:
        """The rows in their body's window: taken within ``window`` of its newest, and among
        the last ``cap`` of those (arrival order) when a cap is given."""
        body = self.body[:self.n]
        live = self.taken[:self.n] >= newest[body] - window
        if cap is not None:
            idx = np.flatnonzero(live)
            b = body[idx]
            order = np.lexsort((-idx, b))              # by body, newest arrival first
            start = np.flatnonzero(np.r_[True, b[order][1:] != b[order][:-1]])
            rank = np.arange(len(order)) - np.repeat(start, np.diff(np.r_[start, len(order)]))
            live[idx[order[rank >= cap]]] = False
        return live

    def rows(self, b: int, newest: np.ndarray, window: float,
             cap: Optional[int] = None) -> np.ndarray:
        """Body ``b``'s rows in its window, in arrival order (the last ``cap`` of them)."""
        rows = self.since(b, newest[b] - window)
        return rows if cap is None or len(rows) <= cap else rows[len(rows) - cap:]

    def since(self, b: int, lo: float) -> np.ndarray:
        """Body ``b``'s rows taken at ``lo`` or later, in arrival order."""
        mine = self.after(b, lo)
        return mine[self.taken[mine] >= lo]

    def after(self, b: int, lo: float) -> np.ndarray:
        """Body ``b``'s rows from its first one whose running maximum of taken reaches ``lo``
        (every earlier row was taken before ``lo``), in arrival order."""
        mine = self._index.get(b)
        if mine is None:
            return np.empty(0, np.intp)
        used = self._count[b]
        return mine[int(np.searchsorted(self._reach[b][:used], lo)):used]

    def count(self, b: int) -> int:
        """How many rows body ``b`` has in the store (in its window or not)."""
        return self._count.get(b, 0)

    def keep(self, mask: np.ndarray) -> None:
        k = int(np.count_nonzero(mask))
        for a in self._arrays:
            arr = getattr(self, a)
            arr[:k] = arr[:self.n][mask]
        self.n = k
        self._index.clear()
        self._count.clear()
        self._reach.clear()
        self._add_to_index(0, self.body[:k])

    def _add_to_index(self, first: int, body: np.ndarray) -> None:
        """Rows ``first, first + 1, ...`` of bodies ``body`` appended to the bodies' indices."""
        if len(body) <= 16:     # a message of a few bodies: plain look-ups
            taken = self.taken[first:first + len(body)].tolist()
            for row, (b, t) in enumerate(zip(body.tolist(), taken), first):
                self._push_one(b, row, t)
            return
        order = np.argsort(body, kind="stable")
        sorted_body = body[order]
        cuts = np.flatnonzero(np.r_[True, sorted_body[1:] != sorted_body[:-1], True])
        for lo, hi in zip(cuts[:-1].tolist(), cuts[1:].tolist()):
            self._push(int(sorted_body[lo]), (order[lo:hi] + first).astype(np.intp))

    def _push_one(self, b: int, row: int, taken: float) -> None:
        mine = self._index.get(b)
        used = self._count.get(b, 0)
        if mine is None or used == len(mine):
            self._grow(b, used, 1)
            mine = self._index[b]
        mine[used] = row
        reach = self._reach[b]
        reach[used] = taken if not used or taken > reach[used - 1] else reach[used - 1]
        self._count[b] = used + 1

    def _grow(self, b: int, used: int, more: int) -> None:
        """Body ``b``'s index (``used`` entries) made room for ``more``."""
        mine = self._index.get(b)
        size = max(16, 2 * (used + more))
        grown, reach = np.empty(size, np.intp), np.empty(size)
        if mine is not None:
            grown[:used] = mine[:used]
            reach[:used] = self._reach[b][:used]
        self._index[b], self._reach[b] = grown, reach

    def _push(self, b: int, rows: np.ndarray) -> None:
        mine = self._index.get(b)
        used = self._count.get(b, 0)
        if mine is None or used + len(rows) > len(mine):
            self._grow(b, used, len(rows))
            mine = self._index[b]
        mine[used:used + len(rows)] = rows
        reach = self._reach[b]
        taken = self.taken[rows]
        if used:
            taken = np.maximum(taken, reach[used - 1])
        np.maximum.accumulate(taken, out=reach[used:used + len(rows)])
        self._count[b] = used + len(rows)

    def append(self, newest: np.ndarray, window: float, cap: Optional[int] = None,
               **rows) -> None:
        m = len(rows["ids"])
        if self.n + m > len(self.ids):
            self.keep(self.live(newest, window, cap))
            if 2 * (self.n + m) > len(self.ids):
                size = max(2 * len(self.ids), 2 * (self.n + m))
                for a in self._arrays:
                    old = getattr(self, a)
                    new = np.empty((size,) + old.shape[1:], old.dtype)
                    new[:self.n] = old[:self.n]
                    setattr(self, a, new)
        for a in self._arrays:
            getattr(self, a)[self.n:self.n + m] = rows[a]
        self._add_to_index(self.n, np.asarray(rows["body"], np.int64).reshape(-1))
        self.n += m
