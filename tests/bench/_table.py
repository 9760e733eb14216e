"""The one table every benchmark prints: Markdown, columns padded to their widest cell."""
from __future__ import annotations


def markdown(head: list[str], lines: list[list[str]]) -> str:
    """``head`` and the rows ``lines`` (strings) as a Markdown table."""
    w = [max(len(h), *(len(line[i]) for line in lines)) for i, h in enumerate(head)]
    out = ["| " + " | ".join(h.ljust(w[i]) for i, h in enumerate(head)) + " |",
           "|" + "|".join("-" * (x + 2) for x in w) + "|"]
    out += ["| " + " | ".join(c.ljust(w[i]) for i, c in enumerate(line)) + " |"
            for line in lines]
    return "\n".join(out)
