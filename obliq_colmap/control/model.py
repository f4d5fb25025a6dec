"""Control points as the rest of the package sees them, whatever file they came from.

Coordinates are metric and projected (a geographic file is sent to its UTM
zone on reading); observations are in COLMAP's pixel convention (the
top-left pixel's centre at (0.5, 0.5)), so that readers convert once and
nothing downstream knows the file's convention.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: default stated accuracy of a control point (m), as MetropoGIS's GIS points
DEFAULT_SIGMA_HORIZONTAL_M = 0.1
DEFAULT_SIGMA_VERTICAL_M = 0.2


@dataclass(frozen=True)
class ControlObservation:
    """One image measurement of a control point."""

    image_name: str
    xy: np.ndarray  # (2,) pixels, COLMAP convention


@dataclass
class ControlPoint:
    """One ground point with its measurements.

    ``xyz`` is (3,) in :attr:`ControlPoints.crs`; ``xyz[2]`` is NaN for a
    2D point (position known in plan only).
    """

    name: str
    xyz: np.ndarray
    observations: list[ControlObservation] = field(default_factory=list)
    sigma_horizontal_m: float = DEFAULT_SIGMA_HORIZONTAL_M
    sigma_vertical_m: float = DEFAULT_SIGMA_VERTICAL_M

    @property
    def has_height(self) -> bool:
        return bool(np.isfinite(self.xyz[2]))


@dataclass
class ControlPoints:
    """The points of one file, in one metric CRS."""

    points: list[ControlPoint]
    crs: str | None  # e.g. "EPSG:32633"; None for a local metric frame
    source: Path | None = None

    def __len__(self) -> int:
        return len(self.points)

    def names(self) -> list[str]:
        return [p.name for p in self.points]

    def xyz(self) -> np.ndarray:
        """(N, 3) coordinates, NaN heights for 2D points."""
        return np.array([p.xyz for p in self.points], float).reshape(-1, 3)

    def without(self, names: set[str]) -> ControlPoints:
        """The points not named in ``names`` (check points withheld)."""
        keep = [p for p in self.points if p.name not in names]
        return ControlPoints(keep, self.crs, self.source)
