"""Load and validate a capture session (``session.yaml``, SPEC section 1).

:func:`load_session` reads the manifest with ``yaml.safe_load`` semantics (plain data
only: a tag that would construct a Python object is refused), validates it with typed
pydantic models that forbid unknown fields (a misspelled field is reported with its
dotted path and a "did you mean" suggestion), resolves paths inside the session folder,
checks the geometry (orthonormal rotations, background planes in front of the cameras, a
volume that the cameras see and that fits in memory) and, unless ``check_files=False``,
the frame and reference files (existence, decodability, sizes, equal frame counts).

Every problem raises :class:`~schlieren.storage.errors.SessionError` with a one-line
message naming the file, the camera and the field (``cameras[2].R``), before any work
is scheduled.

The package holds one step of that reading per module: :mod:`.yaml_safe` (the YAML as
plain data), :mod:`.models` (the typed pydantic models of the manifest and their one-line
errors), :mod:`.paths` (paths resolved and contained in the session folder),
:mod:`.checks` (frame ranges, the volume and the camera geometry), :mod:`.files` (the
frame and reference files), :mod:`.types` (:class:`Session`, :class:`CameraSource`) and
:mod:`.load` (:func:`load_session`, the sequence of those steps).
"""

from schlieren.storage.session.checks import BYTES_PER_VOXEL, parse_frame_range
from schlieren.storage.session.load import load_session
from schlieren.storage.session.types import MANIFEST_NAME, SESSION_FORMAT, CameraSource, Session

__all__ = [
    "SESSION_FORMAT",
    "MANIFEST_NAME",
    "BYTES_PER_VOXEL",
    "CameraSource",
    "Session",
    "load_session",
    "parse_frame_range",
]
