"""Device id lists as the mock commands and world files write them."""

from __future__ import annotations


def parse_id_list(ids) -> list[int]:
    """``[11, 12]``, ``"11-14"`` or ``"11,12,14"`` -> list of ints (ValueError on anything else)."""
    if not isinstance(ids, str):
        return [int(i) for i in ids]
    out: list[int] = []
    for part in (p.strip() for p in ids.split(",")):
        if "-" in part:
            lo, hi = (int(x) for x in part.split("-", 1))
            if hi < lo:
                raise ValueError(f"bad id range {part!r}")
            out.extend(range(lo, hi + 1))
        elif part:
            out.append(int(part))
    return out
