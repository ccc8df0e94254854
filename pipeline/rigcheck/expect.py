"""The in-plume accuracy to expect: the benchmark family's case nearest to this rig.

The realistic family (docs/realistic.md) renders CFD flows through rigs of 8 and 16
cameras at 640x480 and 960x720, PNG or H.264, and records what the run reached and
what its tomography could reach at best (its bounds). A session's rig is matched to the
nearest case by camera count, pixel count and whether its frames are compressed video;
the case's numbers are what to expect for 0.25-0.4 px deflections at sensor noise 1.5
grey levels, with the family's in-focus backgrounds.

A rig's own cameras then move that expectation by their predicted flow noise
(:func:`~schlieren.pipeline.rigcheck.noise.predicted_flow_noise`: the reference's
texture, focus included, and the sensor noise), against the flow noise the family's
in-focus background gives at the same LK window (:attr:`FamilyCase.flow_noise`): the
reconstruction's squared error is the family case's, of which the flow noise makes the
share :data:`FLOW_NOISE_SHARE`, with that share scaled by the cameras' mean squared
flow-noise ratio (:func:`expected_psnr`), never above the case's tomography bound.
Reading the results files is storage's (:mod:`schlieren.storage.rigcheck`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FamilyCase", "expected_accuracy", "expected_psnr", "FLOW_NOISE_SHARE"]

#: The share of the family case's squared in-plume error its flow noise makes: in-focus
#: copies of the tune case with the sensor noise raised until the flow noise was 1.39 and
#: 1.69 times the clean capture's both lost ``10 log10(1 - s + s r^2)`` dB with this ``s``
#: (benchmarks/results/realistic_lab.md, "What the tune case's remaining ... is").
FLOW_NOISE_SHARE = 0.17


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
    flow_noise : tuple of (int, float)
        ``(window, pixels)``: the predicted flow noise of the case's cameras for LK windows
        of that many pixels, at sensor noise ``noise`` (empty when not measured).
    n_reference : int
        The reference frames the case's runs average.
    """

    name: str
    cameras: int
    size: tuple[int, int]
    video: bool
    whole: float
    plume: float
    plume_bound: float | None = None
    noise: float = 1.5
    flow_noise: tuple = ()
    n_reference: int = 16

    def flow_noise_at(self, window: int, noise: float | None = None, n_reference: int | None = None) -> float | None:
        """The flow noise the case's in-focus background gives for an LK window of ``window``
        pixels (log-log interpolation between the measured windows, the nearest beyond them),
        at sensor noise ``noise`` with a reference of ``n_reference`` frames (defaults: the
        case's; the flow noise is proportional to ``noise sqrt(1 + 1 / n_reference)``,
        :func:`~schlieren.pipeline.rigcheck.noise.predicted_flow_noise`); None when not measured."""
        if not self.flow_noise:
            return None
        w, f = (np.array(v, float) for v in zip(*sorted(self.flow_noise)))
        at = float(np.exp(np.interp(np.log(float(window)), np.log(w), np.log(f))))
        if noise is not None:
            at *= float(noise) / self.noise
        if n_reference is not None:
            at *= math.sqrt((1.0 + 1.0 / max(int(n_reference), 1)) / (1.0 + 1.0 / max(int(self.n_reference), 1)))
        return at


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


def expected_psnr(psnr: float, ratios, *, bound: float | None = None, share: float = FLOW_NOISE_SHARE) -> float:
    """The PSNR (dB) a rig reaches where the family case reached ``psnr``, its cameras'
    flow noise being ``ratios`` times the case's: ``psnr - 10 log10(1 - share + share
    mean(ratios^2))`` (the flow noise's part of the squared error scales with its variance,
    averaged over the cameras the tomography combines), at most ``bound``."""
    r2 = float(np.mean(np.square(np.asarray(ratios, float))))
    out = psnr - 10.0 * math.log10(max(1.0 - share + share * r2, 1e-12))
    return min(out, bound) if bound is not None else out
