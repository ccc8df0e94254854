"""Camera frame readers: one module per kind of source, a shared base, and the decoding helpers.

* :mod:`.kinds`: what a frames specification is (printf pattern, glob, folder, video,
  multi-page TIFF, image) and the one list of video and image extensions every reader uses;
* :mod:`.base`: :class:`~.base.FrameSource`, the random-access interface every reader has;
* :mod:`.decoding`: decoding one image file to float32 grey levels, and reading image
  headers and checking files for truncation without decoding their pixels;
* one reader per source: :mod:`.sequence` (:class:`ImageSequence`, printf-numbered files),
  :mod:`.files` (:class:`ImageFiles`, a glob or a folder), :mod:`.tiff`
  (:class:`MultiPageTiff`), :mod:`.video` (:class:`VideoFrames`), :mod:`.interlaced`
  (:class:`InterlacedFields`, the two fields of interlaced frames);
* :mod:`.opening`: :func:`open_frames` (the reader for a specification) and
  :func:`read_reference` (a camera's averaged no-flow background; its frames one by one,
  :func:`reference_frames`, and their :class:`ReferenceMean`).

:mod:`schlieren.storage.frames` re-exports the public names (the module users import).
"""
