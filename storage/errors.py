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


class StoreError(SchlierenInputError):
    """The result store cannot be created, opened or resumed."""
