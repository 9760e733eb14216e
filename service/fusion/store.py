"""The measurements of every body of a live stream in one set of preallocated arrays (the storage
of :class:`~dqpose.fusion.Tracker`): rows in arrival order tagged with their body, each body's
rows found through its own index, memory bounded by the largest live window.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from dqpose._dqcore import StoreIndex
from dqpose.fusion.results import DOF


class Store:
    """Every body's measurements in one set of preallocated arrays, in arrival order, each row
    tagged with its body. A message's rows are checked and written by one C call
    (``_index.ingest``: service/csrc/store.h's ``dq_store_ingest``) whatever the number of bodies
    in it, after :meth:`reserve` made room; rows that fell out of their body's window are dropped
    when the arrays are full
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
        self.arrays = self._ARRAYS + (("wcovs",) if world_covs else ())
        self.n = 0
        # body -> its rows, ascending, with the running maximum of their taken times (C)
        self.index = StoreIndex()
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
        covs = self.wcovs if "wcovs" in self.arrays else self.covs
        return self.wposes[rows], covs[rows]

    def live(self, newest: np.ndarray, window: float, cap: Optional[int] = None) -> np.ndarray:
        """The rows in their body's window: taken within ``window`` of its newest, and among
        the last ``cap`` of those (arrival order) when a cap is given."""
        return self.index.live(self.taken, newest, window, -1 if cap is None else cap, self.n)

    def spans(self, newest: np.ndarray, window: float, cap: Optional[int],
              recent: float) -> tuple[np.ndarray, np.ndarray]:
        """Per body code, over its rows of :meth:`live`: the oldest taken (inf: none) and how
        many were taken within ``recent`` of its newest."""
        return self.index.live(self.taken, newest, window, -1 if cap is None else cap, self.n,
                                float(recent))

    def rows(self, b: int, newest: np.ndarray, window: float,
             cap: Optional[int] = None) -> np.ndarray:
        """Body ``b``'s rows in its window, in arrival order (the last ``cap`` of them)."""
        return self.index.since(b, newest[b] - window, self.taken, -1 if cap is None else cap)

    def since(self, b: int, lo: float) -> np.ndarray:
        """Body ``b``'s rows taken at ``lo`` or later, in arrival order."""
        return self.index.since(b, lo, self.taken)

    def after(self, b: int, lo: float) -> np.ndarray:
        """Body ``b``'s rows from its first one whose running maximum of taken reaches ``lo``
        (every earlier row was taken before ``lo``), in arrival order."""
        return self.index.after(b, lo)

    def count(self, b: int) -> int:
        """How many rows body ``b`` has in the store (in its window or not)."""
        return self.index.count(b)

    def keep(self, mask: np.ndarray) -> None:
        """The rows ``mask`` kept, in order, the others dropped (``_index.keep``, C)."""
        self.index.keep(self, np.asarray(mask, bool))

    def reserve(self, m: int, newest: np.ndarray, window: float,
                cap: Optional[int] = None) -> None:
        """Room for ``m`` more rows: when full, the rows out of their window (``live``) are
        dropped, and the arrays grown when the live rows fill half."""
        if self.n + m <= len(self.ids):
            return
        self.keep(self.live(newest, window, cap))
        if 2 * (self.n + m) > len(self.ids):
            size = max(2 * len(self.ids), 2 * (self.n + m))
            for a in self.arrays:
                old = getattr(self, a)
                new = np.empty((size,) + old.shape[1:], old.dtype)
                new[:self.n] = old[:self.n]
                setattr(self, a, new)
