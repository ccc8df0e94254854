"""Errors for bad input: one line for the user, naming the file, camera and field."""

from __future__ import annotations


class SchlierenInputError(Exception):
    """Bad input (manifest, frames, calibration, store), reported as one line.

    Parameters
    ----------
    message : str
        What is wrong, in plain words.
    file : str, optional
        The file at fault (manifest, frame, video, store path).
    camera : str, optional
        The camera's name, where one is concerned.
    field : str, optional
        The manifest field (dotted path, e.g. ``cameras[3].R``) or frame index.
    """

    def __init__(self, message: str, *, file: str | None = None, camera: str | None = None,
                 field: str | None = None):
        self.message = message
        self.file = file
        self.camera = camera
        self.field = field
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = []
        if self.file:
            where.append(f"file {self.file}")
        if self.camera:
            where.append(f"camera {self.camera}")
        if self.field:
            where.append(f"field {self.field}")
        prefix = (", ".join(where) + ": ") if where else ""
        return prefix + " ".join(str(self.message).split())


class SessionError(SchlierenInputError):
    """The capture session (manifest or its files) is invalid."""


class DroppedFrame(SessionError):
    """The camera dropped this frame: its time slot holds no frame (a gap in the numbered
    file names or in a video's timestamps). Readers skip it; the run excludes it."""


class StoreError(SchlierenInputError):
    """The result store cannot be created, opened or resumed."""


class ResourceError(SchlierenInputError):
    """The run would not fit in the memory of its workers or on the store's disk."""


class ChunkError(StoreError):
    """A chunk of the result store is corrupt, or missing although its stage is marked done.

    Readers raise it instead of returning data; the message names the store, the array
    and the chunk, and says how to repair it. ``array`` and ``chunk`` (grid coordinates)
    are kept as attributes.
    """

    def __init__(self, message: str, *, file: str | None = None, array: str | None = None,
                 chunk: tuple[int, ...] | None = None, reason: str | None = None):
        self.array = array
        self.chunk = tuple(chunk) if chunk is not None else None
        self.reason = reason if reason is not None else message
        super().__init__(message, file=file, field=array)

    def __reduce__(self):  # keep the attributes across processes (Dask workers)
        return (_rebuild_chunk_error, (self.message, self.file, self.array, self.chunk, self.reason))


def _rebuild_chunk_error(message, file, array, chunk, reason=None):
    return ChunkError(message, file=file, array=array, chunk=chunk, reason=reason)
