"""What a test or benchmark reads of a process it started, from /proc."""
from __future__ import annotations


def rss_mb(pid: int) -> float:
    """Process ``pid``'s resident set (VmRSS), MB; NaN when it has none (a zombie's)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")
