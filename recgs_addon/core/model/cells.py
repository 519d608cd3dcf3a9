"""A cell of the seabed: a rectangle in the survey's seabed plane, for a survey trained in blocks.

The seabed plane has an ``origin`` and two unit ``axes`` (the first along the survey's longest
spread); a cell is ``u0 <= u < u1, v0 <= v < v1`` in those coordinates, and holds every point
above or below it (a seabed survey is close to 2.5D, so the height is not cut). The outer cells of a
split reach to :data:`EDGE` (the edge of the world, finite so that the bounds stay plain JSON),
so every point belongs to exactly one cell.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Where the outer cells of a split end: beyond any survey, and a number JSON writes.
EDGE = 1e30


@dataclass(frozen=True)
class Cell:
    origin: tuple        # (3,) a point of the seabed plane
    axes: tuple          # ((3,), (3,)) unit vectors spanning it
    bounds: tuple        # (u0, u1, v0, v1), the outer ones +-EDGE

    def plane_coords(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) coordinates of ``points`` (N, 3) in the seabed plane."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3) - np.asarray(self.origin, dtype=np.float64)
        return p @ np.asarray(self.axes, dtype=np.float64).T

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which ``points`` lie in the cell (lower bounds inclusive, upper exclusive)."""
        return self.contains_plane(self.plane_coords(points))

    def contains_plane(self, uv: np.ndarray) -> np.ndarray:
        """(N,) bool: which plane coordinates ``uv`` (N, 2) lie in the cell."""
        uv = np.asarray(uv).reshape(-1, 2)
        u0, u1, v0, v1 = self.bounds
        return (uv[:, 0] >= u0) & (uv[:, 0] < u1) & (uv[:, 1] >= v0) & (uv[:, 1] < v1)

    def grown(self, margin: float) -> "Cell":
        """The cell with ``margin`` added on every side."""
        u0, u1, v0, v1 = self.bounds
        return Cell(self.origin, self.axes, (u0 - margin, u1 + margin, v0 - margin, v1 + margin))

    def to_dict(self) -> dict:
        return {"origin": [float(x) for x in self.origin], "axes": [[float(x) for x in a] for a in self.axes],
                "bounds": [float(x) for x in self.bounds]}

    @classmethod
    def from_dict(cls, d: dict) -> "Cell":
        return cls(tuple(float(x) for x in d["origin"]), tuple(tuple(float(x) for x in a) for a in d["axes"]),
                   tuple(float(x) for x in d["bounds"]))
