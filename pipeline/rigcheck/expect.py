"""The in-plume accuracy to expect: the benchmark family's case nearest to this rig.

The realistic family (docs/realistic.md) renders CFD flows through rigs of 8 and 16
cameras at 640x480 and 960x720, PNG or H.264, and records what the run reached and
what its tomography could reach at best (its bounds). A session's rig is matched to the
nearest case by camera count, pixel count and whether its frames are compressed video;
the case's numbers are what to expect for 0.25-0.4 px deflections at sensor noise 1.5
grey levels. Reading the results files is storage's (:mod:`schlieren.storage.rigcheck`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["FamilyCase", "expected_accuracy"]


@dataclass(frozen=True)
class FamilyCase:
    """One case of the benchmark family and what it reached.

    Attributes
    ----------
    name : str
    cameras : int
    size : (int, int)
        Image width, height.
    video : bool
        Frames compressed as video (H.264).
    whole, plume : float
        The run's whole-box and in-plume PSNR, dB.
    plume_bound : float or None
        The best in-plume PSNR its tomography could reach (consistent deflections through
        the run's hull), dB.
    noise : float
        The sensor noise the case was rendered with, grey levels.
    """

    name: str
    cameras: int
    size: tuple[int, int]
    video: bool
    whole: float
    plume: float
    plume_bound: float | None = None
    noise: float = 1.5


def expected_accuracy(cases, *, cameras: int, size: tuple[int, int], video: bool) -> FamilyCase | None:
    """The case of ``cases`` nearest to a rig of ``cameras`` cameras of ``size`` pixels
    (compressed ``video`` or not): same kind of frames first, then the smallest
    ``|log(cameras ratio)| + |log(pixel count ratio)|``; None without cases."""
    cases = list(cases)
    if not cases:
        return None

    def distance(c: FamilyCase) -> tuple[bool, float]:
        px = (size[0] * size[1]) / float(c.size[0] * c.size[1])
        return (c.video != video, abs(math.log(cameras / c.cameras)) + abs(math.log(px)))

    return min(cases, key=distance)
