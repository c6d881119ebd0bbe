"""The exception hierarchy: one root, one subclass per concern."""

from __future__ import annotations


class RelocError(Exception):
    """Root of every error raised by reloc on purpose."""


class ConfigError(RelocError, ValueError):
    """A configuration (plugin name, option, TOML file) is not what was expected."""


class GeometryError(RelocError, ValueError):
    """A pose, rotation or point array has the wrong shape or is not valid."""


class CameraError(RelocError, ValueError):
    """A camera model or its parameters are not valid."""


class MapError(RelocError):
    """A keyframe map operation is not possible (unknown id, inconsistent data)."""


class DatasetError(RelocError, ValueError):
    """A dataset file is malformed; the message names the file and line."""


class StorageError(RelocError):
    """A saved map is missing, damaged, or written by a newer format version."""


class Cancelled(RelocError):
    """A long computation stopped between its units because its result is no longer wanted
    (the cancel check it was given turned true); nothing it made is kept."""


class NotTrainedError(RelocError):
    """A relocalizer that needs `train()` was asked to relocalize before training."""
