"""Synthetic car shapes shared by the tests (canonical frame: length 1 along +x, centred).

A plain module, imported as ``from shapes import ...`` (pytest puts ``test/`` on the path,
as for ``fuzz_support``), because a conftest is not meant to be imported.
"""

from __future__ import annotations

import numpy as np


def box_surface(rng: np.random.Generator, n: int, half) -> np.ndarray:
    """``n`` points on the faces of the box ``[-half, half]`` (float64): a uniform point in
    the box pushed onto one of its faces (random axis, random side)."""
    pts = rng.uniform(-1, 1, (n, 3))
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = rng.choice([-1.0, 1.0], n)
    return pts * np.asarray(half, dtype=np.float64)


def car_with_cabin(rng: np.random.Generator, n: int = 4096) -> np.ndarray:
    """A box body (70 % of the points) and a smaller cabin on top, symmetric in y; float32."""
    pts = box_surface(rng, n, 1.0)
    body = pts * [0.5, 0.2, 0.1] + [0, 0, -0.05]
    cabin = pts * [0.25, 0.18, 0.07] + [-0.05, 0, 0.12]
    return np.where((rng.random(n) < 0.7)[:, None], body, cabin).astype(np.float32)
