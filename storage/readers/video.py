"""Frames of a video file decoded with OpenCV (:class:`VideoFrames`), and dropped frames
found in its presentation timestamps (:func:`slots_of_timestamps`)."""

from __future__ import annotations

import logging
import os

import cv2
import numpy as np

from schlieren.storage import location
from schlieren.storage.errors import SessionError
from schlieren.storage.readers.base import FrameSource, format_ranges
from schlieren.storage.readers.decoding import _grey_of_raw

log = logging.getLogger(__name__)

#: Largest jump ahead that a video reader decodes through instead of seeking.
FORWARD_GRAB_LIMIT = 16


def slots_of_timestamps(ms, *, gap: float = 1.5) -> np.ndarray:
    """The time slot of every decoded frame of a video, from its presentation timestamps.

    A step between consecutive timestamps of more than ``gap`` frame intervals means the
    camera dropped frames there: ``round(step / interval) - 1`` of them. The interval is
    the mean of the steps below ``gap`` times their median (robust to containers that
    round timestamps to milliseconds, such as Matroska at 29.97 frames/s).

    Parameters
    ----------
    ms : sequence of float
        Presentation time of each decoded frame, milliseconds, in decoding order.

    Returns
    -------
    ndarray of int64
        Slot of each frame (``arange(n)`` without gaps, or when the timestamps are not
        increasing, so carry no timing).
    """
    t = np.asarray(ms, dtype=np.float64)
    n = t.size
    if n < 3:
        return np.arange(n, dtype=np.int64)
    step = np.diff(t)
    if not np.all(np.isfinite(step)) or np.any(step <= 0):
        return np.arange(n, dtype=np.int64)
    med = float(np.median(step))
    period = float(np.mean(step[step <= gap * med]))
    inc = np.where(step > gap * period, np.maximum(np.rint(step / period), 1), 1).astype(np.int64)
    return np.concatenate([[0], np.cumsum(inc)]).astype(np.int64)


class VideoFrames(FrameSource):
    """Frames of a video file, decoded with ``cv2.VideoCapture``.

    Random access seeks with ``CAP_PROP_POS_FRAMES``; reads in increasing order (or short
    jumps ahead, up to ``FORWARD_GRAB_LIMIT`` frames) reuse the open decoder. If a seek is
    refused or lands elsewhere, the reader reopens the file and decodes sequentially up to
    the frame. A frame that cannot be decoded raises
    :class:`SessionError` naming the file, the camera and the frame index. A video at a
    URL is decoded from a local copy staged once per machine.

    Indices are time slots: the first use of the length, :attr:`dropped` or a frame
    decodes the whole video once (:meth:`scan`) to read every frame's presentation
    timestamp, and a gap in them is a dropped frame (:func:`slots_of_timestamps`). A run
    scans each video once before scheduling and hands the result (``slots``) to its
    workers, which then decode only the frames they use.

    Parameters
    ----------
    slots : (int, tuple of int), optional
        ``(number of slots, dropped slots)`` from an earlier :meth:`scan` of this file.
    """

    def __init__(self, path: str | os.PathLike, *, camera_name: str | None = None,
                 slots: tuple[int, tuple[int, ...]] | None = None):
        self.path = os.fspath(path)
        self.camera_name = camera_name
        self._file = None  # the local file OpenCV reads (a staged copy for a URL)
        if not location.isfile(self.path):
            raise SessionError("video file not found", file=self.path, camera=camera_name)
        self._cap = None
        self._next = 0  # index of the decoded frame the open decoder returns next
        self._size = None
        self._raw_dtype = None
        cap = self._open()
        #: Frames the container's header announces (its duration times its rate).
        self.header_count = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        self._slots: tuple[int, tuple[int, ...]] | None = None
        if slots is not None:
            self._set_slots(int(slots[0]), tuple(int(k) for k in slots[1]))

    def _set_slots(self, n: int, dropped: tuple[int, ...]) -> None:
        self._slots = (n, dropped)
        self._count = n
        self._dropped_sorted = np.asarray(dropped, dtype=np.int64)

    def scan(self) -> tuple[int, tuple[int, ...]]:
        """Decode every frame once for its timestamp: ``(number of slots, dropped slots)``.

        If decoding stops before the frames the header announces (a corrupt or truncated
        video), drops are looked for among the frames that decode, and the slots after
        them are taken as present: reading one raises the decoding error naming it.
        """
        if self._slots is None:
            self.close()
            cap = self._open()
            ms = []
            while cap.grab():
                ms.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
            self.close()
            self._finish_scan(ms)
        return self._slots

    def _finish_scan(self, ms: list[float]) -> None:
        slot = slots_of_timestamps(ms)
        n = int(slot[-1]) + 1 if len(ms) else 0
        have = set(int(k) for k in slot)
        dropped = tuple(k for k in range(n) if k not in have)
        if n < self.header_count:
            log.warning("camera %s: %s: decoding stops after %d of the %d frames its header announces",
                        self.camera_name, self.path, len(ms), self.header_count)
            n = self.header_count
        if dropped:
            log.warning("camera %s: the timestamps of %s skip frame(s) %s: taken as frames the camera "
                        "dropped", self.camera_name, self.path, format_ranges(dropped))
        self._set_slots(n, dropped)

    @property
    def dropped(self) -> tuple[int, ...]:
        return self.scan()[1]

    def _check_index(self, i: int) -> int:
        if int(i) == 0 and self._slots is None and self.header_count > 0:
            return 0  # slot 0 holds the first decoded frame: no scan needed (a reference's size)
        return super()._check_index(i)

    def _decoded_index(self, i: int) -> int:
        """The decoding-order index of the frame in slot ``i`` (not a dropped one)."""
        if i == 0:
            return 0
        self.scan()
        return i - int(np.searchsorted(self._dropped_sorted, i))

    # -- handle management ------------------------------------------------------
    def _local(self) -> str:
        if self._file is None or not os.path.isfile(self._file):  # unpickled on another machine
            try:
                self._file = location.stage(self.path)
            except OSError as exc:
                raise SessionError(f"cannot fetch the video ({exc})", file=self.path,
                                   camera=self.camera_name) from None
        return self._file

    def _open(self) -> cv2.VideoCapture:
        if self._cap is None:
            cap = cv2.VideoCapture(self._local())
            if not cap.isOpened():
                raise SessionError("cannot open the video (corrupt or unsupported codec)",
                                   file=self.path, camera=self.camera_name)
            self._cap = cap
            self._next = 0
        return self._cap

    def close(self) -> None:
        """Release the decoder (reopened on the next read)."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None
            self._next = 0

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_cap"] = None
        state["_next"] = 0
        return state

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def __len__(self) -> int:
        return self.scan()[0]

    # -- reading --------------------------------------------------------------
    def _decode_error(self, i: int, wanted: int | None = None) -> SessionError:
        self.close()
        extra = f" while seeking to frame {wanted}" if wanted is not None and wanted != i else ""
        return SessionError(f"cannot decode frame {i} of the video (corrupt or truncated){extra}",
                            file=self.path, camera=self.camera_name, field=f"frames[{i}]")

    def _seek(self, i: int) -> bool:
        cap = self._open()
        if self._next == i:
            return True
        if self._next < i <= self._next + FORWARD_GRAB_LIMIT:
            # a short jump ahead: decoding forward is cheaper than OpenCV's seek, which
            # re-decodes from a keyframe (or the start) every time
            for k in range(self._next, i):
                if not cap.grab():
                    raise self._decode_error(k, i)
            self._next = i
            return True
        if cap.set(cv2.CAP_PROP_POS_FRAMES, float(i)):
            pos = int(round(cap.get(cv2.CAP_PROP_POS_FRAMES)))
            if pos == i:
                self._next = i
                return True
        # sequential fallback: reopen and skip forward
        log.debug("seek to frame %d of %s failed; decoding sequentially", i, self.path)
        self.close()
        cap = self._open()
        for k in range(i):
            if not cap.grab():
                raise self._decode_error(k, i)
        self._next = i
        return True

    def read(self, i: int) -> np.ndarray:
        i = self._check_index(i)
        img = self.read_raw(i)
        grey = _grey_of_raw(img, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        size = (grey.shape[1], grey.shape[0])
        if self._size is None:
            self._size, self._raw_dtype = size, np.dtype(img.dtype)
        return grey

    def read_raw(self, i: int) -> np.ndarray:
        """Frame ``i`` as decoded (BGR or grey, 8/16-bit), for lossless copies."""
        i = self._check_index(i)
        j = self._decoded_index(i)
        self._seek(j)
        ok, img = self._cap.read()
        if not ok or img is None or img.size == 0:
            raise self._decode_error(i)
        self._next = j + 1
        return img

    def iter_sequential(self):
        """Decode every frame in order (faster than random access), as float32 grey: the
        frames of :meth:`present`, one per slot that holds a frame. Not yet scanned, the
        pass also reads the timestamps (:meth:`scan`), so the video is decoded once."""
        known = self._slots is not None
        present = self.present() if known else None
        self.close()
        cap = self._open()
        ms: list[float] = []
        j = 0
        while present is None or j < len(present):
            ok, img = cap.read()
            if not ok or img is None:
                if present is None:
                    break
                raise self._decode_error(present[j])
            ms.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
            i = present[j] if present is not None else j
            j += 1
            self._next = j
            yield _grey_of_raw(img, file=self.path, camera=self.camera_name, field=f"frames[{i}]")
        self.close()
        if not known:
            self._finish_scan(ms)
            present = self.present()
            if len(ms) < len(present):
                raise self._decode_error(present[len(ms)])

    def __repr__(self) -> str:
        n = self._slots[0] if self._slots is not None else self.header_count
        return f"VideoFrames({self.path!r}, n={n})"
