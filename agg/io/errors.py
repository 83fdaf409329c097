"""Specific exceptions (and the truncation warning) of ingest, the scene bundle and the importers.

Every error for bad input is a ``ValueError`` so that callers (the CLI, the service) can map the whole family to
a client error, and catch a specific class when they want to react to one case.
"""

from __future__ import annotations

from typing import Any


class IngestError(ValueError):
    """Base class of the errors raised while reading a video file or an image folder."""


class NotAVideoError(IngestError):
    """The file is not a video (or an image folder) that the decoder can open."""


class NoDecodableFramesError(IngestError):
    """The file opened as a video (or the folder has images) but no frame could be decoded."""


class TooManyPixelsError(IngestError):
    """A source frame has more pixels than the configured limit (``IngestConfig.max_source_pixels``)."""


class TooFewFramesError(IngestError):
    """Fewer usable frames than required (at least 2 by default) after sampling."""


class TruncatedVideoError(IngestError):
    """Decoding stopped before the end of the stream (strict mode only).

    ``partial`` carries the ``IngestResult`` with the frames decoded before the break (or ``None`` when fewer than
    the minimum were usable); ``frame_index`` / ``time_us`` say where it stopped (source frame index and
    microseconds of the first frame that is missing).
    """

    def __init__(self, message: str, *, frame_index: int, time_us: int | None, partial: Any = None):
        super().__init__(message)
        self.frame_index = frame_index
        self.time_us = time_us
        self.partial = partial


class TruncatedVideoWarning(UserWarning):
    """Emitted (non-strict mode) when a video ends early; the result's ``truncated_at`` says where."""


class CalibrationError(IngestError):
    """Intrinsics or distortion coefficients are malformed (wrong shape, non-finite, non-positive focal)."""


class BundleError(ValueError):
    """Base class of scene-bundle errors."""


class BundleNotFoundError(BundleError):
    """The folder does not exist or has no ``manifest.json``."""


class BundleVersionError(BundleError):
    """The manifest's ``format`` is not ``agg-bundle`` or its ``version`` is not supported."""


class BundleValidationError(BundleError):
    """A bundle part disagrees with the manifest or the conventions (shape, dtype, range, missing file)."""


class BundleExistsError(BundleError):
    """``SceneBundle.create`` was asked to write into a non-empty folder without ``overwrite=True``."""


class ImporterError(ValueError):
    """A dataset folder given to an importer is missing files or has malformed content."""
