"""Standard normal draws taken from a generator in blocks, handed out a few at a time.

The simulated sensors draw 2 or 3 normals per robot at every physics step (50 per simulated
second per robot); one ``Generator.normal`` call per step cost more than the arithmetic it
feeds. numpy's generators produce the same sequence whether drawn one value or a block at a
time, so a block hands out exactly the values the single draws gave.
"""
from __future__ import annotations

import numpy as np

__all__ = ["NormalBlock"]


class NormalBlock:
    """Standard normal draws from ``rng``, ``width`` at a time, drawn ``rows`` x ``width`` at
    once: ``next()`` returns what ``rng.normal(0.0, 1.0, width).tolist()`` would have."""

    def __init__(self, rng: np.random.Generator, width: int, rows: int = 256) -> None:
        self.rng, self.width, self.rows = rng, int(width), int(rows)
        self._block: list[list[float]] = []
        self._i = 0

    def next(self) -> list[float]:
        """The next ``width`` standard normal draws (a list the caller may keep)."""
        if self._i >= len(self._block):
            self._block = self.rng.normal(0.0, 1.0, (self.rows, self.width)).tolist()
            self._i = 0
        self._i += 1
        return self._block[self._i - 1]
