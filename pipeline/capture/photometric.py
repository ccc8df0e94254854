"""A frame's gain and offset against its reference, as smooth profiles over the image
rows, and the frame with them removed.

Lamp flicker changes a frame's gain and offset; where a rolling shutter meets
mains-frequency light, they also change with the row (each row is exposed at its own
time: banding). Optical flow assumes ``frame(p) = reference(p + delta)`` (paper sec. 4);
a 2 % gain or an offset of one grey level against a background of 40 grey levels'
contrast moves Lucas-Kanade's deflections by several hundredths of a pixel, as much as a
weak plume. The profiles here are piecewise linear in the row, with knots every
``banding_rows`` rows: a frame is modelled as ``gain(row) * reference + offset(row)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["row_knots", "row_basis", "row_profile", "Photometric", "normalise_frame", "identity_photometric",
           "MIN_GAIN"]

#: The smallest gain a frame can be normalised by: below it the frame keeps less than a
#: tenth of the reference's contrast (a lens cap, a lamp off, a frame clipped black or
#: white, where the fitted gain is 0), and dividing by it would amplify the frame's noise
#: tenfold or more.
MIN_GAIN = 0.1


def row_knots(height: int, banding_rows: int) -> np.ndarray:
    """Image rows of the profile knots: evenly spaced from the first row to the last, at
    most ``banding_rows`` apart (two knots at least; one for a one-row image)."""
    height = int(height)
    if height <= 1:
        return np.zeros(1)
    n = max(2, int(np.ceil((height - 1) / max(int(banding_rows), 1))) + 1)
    return np.linspace(0.0, height - 1.0, n)


def row_basis(rows, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hat functions of the knots at image rows ``rows``: each row's left knot index and
    the weight of the next knot (the left one gets ``1 - weight``; rows outside the knots
    take the end knot's value)."""
    rows = np.asarray(rows, np.float64)
    if len(knots) == 1:
        return np.zeros(rows.shape, np.int64), np.zeros(rows.shape)
    step = float(knots[1] - knots[0])
    t = np.clip((rows - knots[0]) / step, 0.0, len(knots) - 1.0)
    k = np.minimum(t.astype(np.int64), len(knots) - 2)
    return k, t - k


def row_profile(values, knots: np.ndarray, rows) -> np.ndarray:
    """A profile (values at the knots) at image rows ``rows``."""
    values = np.asarray(values, np.float64)
    if len(knots) == 1:
        return np.full(np.shape(rows), float(values[0]))
    k, w = row_basis(rows, knots)
    return (1.0 - w) * values[k] + w * values[np.minimum(k + 1, len(knots) - 1)]


@dataclass(frozen=True)
class Photometric:
    """A frame's gain and offset profiles against its reference.

    ``frame(row, col) ~= gain(row) * reference(row, col) + offset(row)`` in grey levels.

    Attributes
    ----------
    knots : ndarray, shape (K,)
        Image rows of the knots.
    gain : ndarray, shape (K,)
        Gain at the knots (1 = unchanged).
    offset : ndarray, shape (K,)
        Offset at the knots, grey levels.
    """

    knots: np.ndarray
    gain: np.ndarray
    offset: np.ndarray

    def profiles(self, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Gain and offset of every image row, shape (height,) each."""
        rows = np.arange(int(height), dtype=np.float64)
        return row_profile(self.gain, self.knots, rows), row_profile(self.offset, self.knots, rows)

    def estimable(self) -> bool:
        """Whether the frame can be normalised: every knot's gain and offset finite, every
        gain at least :data:`MIN_GAIN`."""
        return bool(np.all(np.isfinite(self.gain)) and np.all(np.isfinite(self.offset))
                    and np.all(self.gain >= MIN_GAIN))

    def departs(self, *, gain_tolerance: float, offset_tolerance: float, mean: float = 0.0,
                gain_sigma=0.0, level_sigma=0.0, significance: float) -> bool:
        """Whether, at some knot, the gain departs from 1 by more than ``gain_tolerance``,
        or the grey level ``mean`` (the reference's mean) moves by more than
        ``offset_tolerance`` grey levels, and by more than ``significance`` times its
        standard deviation (``gain_sigma``, ``level_sigma``: per knot or one for all).
        Gain and offset are measured together: a gain error comes with the opposite
        offset error at the mean grey level, which this test does not count twice."""
        dg = np.abs(self.gain - 1.0)
        dl = np.abs(self.offset + (self.gain - 1.0) * float(mean))
        with np.errstate(invalid="ignore"):
            g = (dg > gain_tolerance) & (dg > significance * np.nan_to_num(gain_sigma, nan=np.inf))
            lv = (dl > offset_tolerance) & (dl > significance * np.nan_to_num(level_sigma, nan=np.inf))
        return bool(np.any(g) or np.any(lv))


def identity_photometric(height: int, banding_rows: int) -> Photometric:
    """Gain 1 and offset 0 at every knot."""
    knots = row_knots(height, banding_rows)
    return Photometric(knots, np.ones(len(knots)), np.zeros(len(knots)))


def normalise_frame(frame: np.ndarray, photometric: Photometric, *, first_row: int = 0,
                    image_rows: int | None = None) -> np.ndarray:
    """The frame with its gain and offset removed: ``(frame - offset(row)) / gain(row)``.

    Parameters
    ----------
    frame : ndarray, shape (H, W)
        Grey levels.
    first_row, image_rows : int, optional
        ``frame`` is rows ``first_row ..`` of an image of ``image_rows`` rows (a crop; the
        profiles are the whole image's). Default: the whole image.

    Returns
    -------
    ndarray, shape (H, W), float32

    Raises
    ------
    ValueError
        The profiles cannot normalise a frame (:meth:`Photometric.estimable` is false).
    """
    if not photometric.estimable():
        raise ValueError(f"a frame with gain {np.min(photometric.gain):.3g} at some row cannot be normalised "
                         f"(the gain must be finite and at least {MIN_GAIN})")
    img = np.asarray(frame, np.float32)
    rows = slice(first_row, first_row + img.shape[0])
    gain, offset = photometric.profiles(img.shape[0] if image_rows is None else image_rows)
    inv = (1.0 / gain[rows]).astype(np.float32)[:, None]
    return (img - offset[rows].astype(np.float32)[:, None]) * inv
