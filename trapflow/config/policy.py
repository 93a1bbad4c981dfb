"""Queueing policies: the grammar of `latest`, `fifo:N` and `ordered[:N]` (the broker's policy
module applies them)."""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_ORDERED_BOUND = 16


@dataclass(frozen=True)
class Policy:
    """A parsed policy string."""

    kind: str  # "latest" | "fifo" | "ordered"
    bound: int

    def __str__(self) -> str:
        return "latest" if self.kind == "latest" else f"{self.kind}:{self.bound}"


def parse_policy(text: str) -> Policy:
    """Parse `latest`, `fifo:N` or `ordered[:N]`; ValueError says what was expected."""
    expected = f"expected latest, fifo:N or ordered[:N] with N >= 1, got {text!r}"
    kind, sep, num = text.strip().partition(":")
    if kind == "latest" and not sep:
        return Policy("latest", 1)
    if kind == "ordered" and not sep:
        return Policy("ordered", DEFAULT_ORDERED_BOUND)
    if kind in ("fifo", "ordered") and sep:
        try:
            bound = int(num)
        except ValueError:
            raise ValueError(expected) from None
        if bound >= 1:
            return Policy(kind, bound)
    raise ValueError(expected)
