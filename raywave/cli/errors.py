"""The CLI's user-facing error."""


class CommandError(Exception):
    """An error to report to the user as one line, without a traceback."""
