"""What a live stream's tracker holds and answers at most (:class:`TrackerBounds`): the domain's
own bounds, which a server fills from its :class:`dqpose.limits.Limits`
(:meth:`TrackerBounds.of`) and a world from its own bounds besides."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class TrackerBounds:
    """A tracker's bounds; each field is the :class:`dqpose.limits.Limits` field of that name
    (whose default, meaning and unit are stated there, the one place), except ``max_rows``: the
    measurements all of the tracker's windows hold (``Limits.max_stream_measurements`` for a
    stream)."""
    max_window: int
    max_robust: int
    max_correlated: int
    max_rows: int
    max_time: float
    max_time_jump: float
    max_fused_per_request: int

    @classmethod
    def of(cls, limits, **bounds) -> "TrackerBounds":
        """A stream's bounds under ``limits`` (a :class:`dqpose.limits.Limits`: read by field
        name, so this module needs no import of it); ``bounds`` replace fields (a world's: its
        own per body and in all)."""
        fields = {f: getattr(limits, f) for f in ("max_window", "max_robust", "max_correlated",
                                                  "max_time", "max_time_jump",
                                                  "max_fused_per_request")}
        return cls(**{**fields, "max_rows": limits.max_stream_measurements, **bounds})

    def holding(self, per_body: int, rows: int) -> "TrackerBounds":
        """These bounds for a tracker whose bodies hold ``per_body`` measurements each (a world's
        buffer, not a stream's ``max_window``) and ``rows`` in all."""
        return dataclasses.replace(self, max_window=per_body, max_rows=rows)

    def cap(self, robust: bool, correlated: bool) -> int:
        """Measurements one body's fit takes at most (its window's latest)."""
        return min(self.max_window, self.max_robust if robust else self.max_window,
                   self.max_correlated if correlated else self.max_window)
