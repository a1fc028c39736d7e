"""The error hierarchy: every error a user can cause or fix is a ``CubelocError``.

The CLI entry point turns a ``CubelocError`` into one line on stderr and exit code 2;
anything else is a bug and keeps its traceback. Messages say what was expected and what
to try, and name the file or value at fault.
"""


class CubelocError(Exception):
    """An expected error with a message a user can act on."""


class InputFileError(CubelocError):
    """A file given by the user is missing, unreadable or malformed."""


class ConfigError(CubelocError):
    """The configuration is invalid (file, environment override or command line)."""
