"""The two fields of interlaced frames as frames of their own (:class:`InterlacedFields`)."""

from __future__ import annotations

import numpy as np

from schlieren.storage.readers.base import FrameSource


class InterlacedFields(FrameSource):
    """The two fields of every interlaced frame, as frames of their own (twice as many).

    Field ``2 f + k`` of frame ``f`` holds the rows of parity ``k`` (``top_first``: even
    rows first, ``bottom_first``: odd rows first); the missing rows are the mean of the
    field rows above and below (linear "bob" deinterlacing), so every field keeps the
    full image size and the camera's calibration. Rows of a field are exposed one field
    line time apart, as the session's rolling-shutter model expects (docs/session.md).
    """

    def __init__(self, frames: FrameSource, order: str = "top_first"):
        if order not in ("top_first", "bottom_first"):
            raise ValueError(f"order must be top_first or bottom_first, got {order!r}")
        self.frames = frames
        self.order = order
        self.path = frames.path
        self.camera_name = frames.camera_name
        self._size = None
        self._raw_dtype = None

    def __len__(self) -> int:
        return 2 * len(self.frames)

    @property
    def dropped(self) -> tuple[int, ...]:
        """Both fields of every frame the camera dropped."""
        return tuple(2 * d + k for d in getattr(self.frames, "dropped", ()) for k in (0, 1))

    def file_of(self, i: int) -> str:
        return self.frames.file_of(int(i) // 2)

    @property
    def size(self) -> tuple[int, int]:
        return self.frames.size

    @property
    def raw_dtype(self) -> np.dtype:
        return self.frames.raw_dtype

    def parity(self, i: int) -> int:
        """Row parity (0 = even rows) held by field ``i``."""
        return (int(i) % 2) ^ (self.order == "bottom_first")

    def read(self, i: int) -> np.ndarray:
        i = self._check_index(i)
        return bob_field(self.frames.read(i // 2), self.parity(i))

    def close(self) -> None:
        if hasattr(self.frames, "close"):
            self.frames.close()

    def __repr__(self) -> str:
        return f"InterlacedFields({self.frames!r}, {self.order})"


def bob_field(frame: np.ndarray, parity: int) -> np.ndarray:
    """The field of rows ``parity, parity + 2, ...`` of ``frame`` at full height: missing
    rows are the mean of their neighbours in the field (the edge row repeats its neighbour)."""
    img = np.asarray(frame, dtype=np.float32)
    out = img.copy()
    h = img.shape[0]
    for r in range(1 - parity, h, 2):
        up, down = r - 1, r + 1
        if up < 0:
            out[r] = img[down]
        elif down >= h:
            out[r] = img[up]
        else:
            out[r] = 0.5 * (img[up] + img[down])
    return out
