"""Moved to :mod:`common.encoders.naclip` (the mapper needs it for image queries); this name is
the same module object, kept for the edge and existing imports."""
import sys

from common.encoders import naclip as _impl

sys.modules[__name__] = _impl
