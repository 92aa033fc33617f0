"""Errors shared by everything that loads model files from disk."""
from __future__ import annotations


class ModelFileError(FileNotFoundError):
    """A model file or directory is missing, unreadable or does not match the expected model.

    Subclasses ``FileNotFoundError`` so the ``rayfronts`` CLI prints it as one clear line.
    The message always names the path(s) involved and, for mismatched checkpoints, the
    missing / unexpected / wrongly shaped keys.
    """
