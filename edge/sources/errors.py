"""The one exception type frame sources raise."""


class SourceError(RuntimeError):
    """A frame source cannot be opened or read; the message names the path, file or topic."""
