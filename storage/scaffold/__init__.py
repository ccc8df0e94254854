"""Scaffold a capture session (``schlieren init``): frames + calibration -> ``session.yaml``.

:func:`scaffold_session` checks every camera's frames (a video, an image sequence given
by a printf pattern, a glob pattern or a folder, or a multi-page TIFF: frame count, size,
frame rate must agree, and the size must be the calibration's ``image_size``), extracts
each camera's reference (no-flow) frames, and writes a ``schlieren-session/1`` manifest
(docs/session.md) that ``schlieren run`` accepts. The manifest is loaded back with the
session reader before it is put in place; if anything fails, whatever this call created
is removed again (a failed init leaves nothing behind, so the retry is not refused).

* ``frames:`` the source itself; relative to the session folder when it lies inside it,
  else copied into ``<camera>/`` (``copy_videos=True``) or referenced by absolute path
  with ``allow_external_paths: true``.
* ``reference:`` the frames ``[A, B)`` of the same source, written losslessly as
  ``<camera>/reference/%05d.png`` (the very pixels the decoder returns, renumbered from
  0; 16-bit stays 16-bit, float frames become ``.tif``); the session reader averages them. A printf pattern rather than one averaged
  image keeps the grey-level scale of the video frames exactly (an averaged 8-bit image
  would be re-quantised, a 16-bit one would be on another scale).
* camera geometry (``image_size, K, dist, R, t, background``) copied from the
  calibration file (``schlieren calibrate``); ``background: {distance: D}`` for cameras
  whose calibration has none when ``background_distance`` is given.
* ``volume``, ``frame_rate`` (from the videos unless given), ``frames``,
  ``sync.strobe.search_frames`` or per-camera ``time_offset``, ``rolling_shutter``.

:mod:`.sources` finds and probes the capture sources (``schlieren init``'s arguments) and
writes reference frames; :mod:`.build` is :func:`scaffold_session`, a sequence of named steps.
"""

from schlieren.storage.scaffold.build import MANIFEST_NAME, SESSION_FORMAT, scaffold_session
from schlieren.storage.scaffold.sources import (
    VideoInfo,
    find_sources,
    find_videos,
    probe_source,
    probe_video,
    source_kind,
    write_reference_frames,
)

__all__ = ["VideoInfo", "probe_video", "probe_source", "source_kind", "find_sources", "find_videos", "write_reference_frames",
           "scaffold_session", "SESSION_FORMAT", "MANIFEST_NAME"]
