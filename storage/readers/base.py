"""The interface every camera frame reader has (:class:`FrameSource`).

A source's index is the time slot: frame ``i`` was exposed at ``i / frame_rate`` after
frame 0, and :attr:`FrameSource.dropped` lists the slots that hold no frame (the camera
dropped it). Reading a dropped slot raises :class:`~schlieren.storage.errors.DroppedFrame`.
"""

from __future__ import annotations

import numpy as np

from schlieren.storage.errors import DroppedFrame, SessionError


def format_ranges(indices) -> str:
    """``"5, 9-11"`` for indices 5, 9, 10, 11 (sorted)."""
    out: list[list[int]] = []
    for k in sorted(int(i) for i in indices):
        if out and k == out[-1][1] + 1:
            out[-1][1] = k
        else:
            out.append([k, k])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in out)


class FrameSource:
    """Random access to the frames of one camera.

    Attributes
    ----------
    path : str
        The pattern or video file.
    camera_name : str or None
    """

    path: str
    camera_name: str | None

    def __len__(self) -> int:  # pragma: no cover - abstract
        raise TypeError("FrameSource is abstract")

    def read(self, i: int) -> np.ndarray:  # pragma: no cover - abstract
        """Frame ``i`` (0-based) as float32 grey levels, shape (H, W)."""
        raise TypeError("FrameSource is abstract")

    def file_of(self, i: int) -> str:
        """The file holding frame ``i`` (the video file for videos)."""
        return self.path

    def prefetch(self, indices) -> None:
        """Frames about to be read (a hint: image files at a URL are fetched together)."""

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels (from frame 0)."""
        self._ensure_info()
        return self._size

    @property
    def raw_dtype(self) -> np.dtype:
        """Sample type of the stored frames (uint8, uint16, ...)."""
        self._ensure_info()
        return self._raw_dtype

    @property
    def one_channel(self) -> bool:
        """Whether every frame read so far was stored as one grey channel of :attr:`raw_dtype`,
        so that its grey levels (:meth:`read`) are its samples themselves, converted to
        float32 (not weighted colour); False when unknown."""
        return False

    def _ensure_info(self) -> None:
        if getattr(self, "_size", None) is None:
            self.read(0)

    @property
    def dropped(self) -> tuple[int, ...]:
        """Time slots (frame indices) the camera dropped: no frame was stored for them."""
        return getattr(self, "_dropped", ())

    def present(self) -> list[int]:
        """The indices that hold a frame (every index but the :attr:`dropped` ones)."""
        gone = set(self.dropped)
        return [i for i in range(len(self)) if i not in gone]

    def _check_index(self, i: int) -> int:
        i = int(i)
        n = len(self)
        if not 0 <= i < n:
            raise SessionError(f"frame index {i} is outside the {n} frames available",
                               file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        if i in self.dropped:
            raise DroppedFrame("the camera dropped this frame (a gap in the numbered files or the video's "
                               "timestamps); it is excluded from the reconstruction",
                               file=self.file_of(i), camera=self.camera_name, field=f"frames[{i}]")
        return i

    def __iter__(self):
        for i in range(len(self)):
            yield self.read(i)
