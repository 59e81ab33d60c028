"""Errors in what a user gave the toolkit (a file, a folder, a model), as the project's
readers raise them: each message starts with the path it is about and says what is wrong
and the fix ("<path>[:<line>]: ..."). The recipe runner shows them without the class name,
and a bug's error (numpy's ValueError, a KeyError) with it, for the bug report
(``toolkit.recipe.runner._is_input_error``). Each subclasses the built-in error the readers
raised before, so callers' ``except ValueError`` / ``except OSError`` still catch it.

An area's own error class for bad input (SequenceFormatError, BagError,
CalibrationFileError, ...) subclasses one of these, which is how the runner knows it; an
error class for the project's internal use (NotATransformError, caught and re-raised
naming the topic) subclasses a built-in error, so that escaping it shows as a bug."""

from __future__ import annotations

__all__ = ["InputError", "MissingInputError", "WriteError"]


class InputError(ValueError):
    """A file or folder holds what the toolkit cannot use."""


class MissingInputError(FileNotFoundError):
    """A file or folder the toolkit needs is not there (or holds none of what it needs)."""


class WriteError(OSError):
    """A file could not be written where the writer says so without an OSError of its own
    (``cv2.imwrite`` and Open3D's writers return False)."""
