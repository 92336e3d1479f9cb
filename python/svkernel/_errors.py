"""The exceptions svkernel raises (re-exported by ``svkernel``).

Every error carries the library's message, which names the parameter, or the
file and the key, that was refused.
"""

from __future__ import annotations

from typing import Optional


class Error(Exception):
    """Base class of every svkernel error.

    Attributes:
        key: the parameter or document key that was refused, if any.
        path: the file the error is about, if any.
    """

    def __init__(self, message: str, key: Optional[str] = None, path: Optional[str] = None):
        super().__init__(message)
        self.key = key
        self.path = path


class InvalidParameter(Error, ValueError):
    """A parameter outside its domain (the message says what is allowed)."""


class FormatError(Error, ValueError):
    """A document, scene or image that cannot be read: names the file and key."""


class FileError(Error, OSError):
    """A file that cannot be read or written."""


class FitError(Error, RuntimeError):
    """A fit that could not be carried out."""
