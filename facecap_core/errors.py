"""User-facing errors.

A :class:`FacecapError` is a problem with the input or the environment that the user can
fix; its message is one line saying what is wrong and what to do. The CLI prints it without
a traceback and exits non-zero. Anything else that escapes is a bug and keeps its traceback.
"""


class FacecapError(Exception):
    """Bad input or environment, explained in one line for the user."""


class InputError(FacecapError):
    """An input file, folder or parameter is missing, unreadable or invalid."""
