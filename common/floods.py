"""Which occurrence of a count that a flood can drive (refused tokens, rejected messages, fenced
commands, refused missions) is worth a log line: the first, so the operator learns it happens, and
every `EVERY`th after, so a flood shows it goes on without filling the disk. The count itself is in
the health line and the metrics. Pure."""

from __future__ import annotations

EVERY = 1000


def worth_logging(count: int, every: int = EVERY) -> bool:
    """The first occurrence and every `every`th (count is how many so far, this one included)."""
    return count == 1 or (count > 0 and count % every == 0)
