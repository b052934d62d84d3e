"""The one exception type for problems the user can fix (bad input, bad options).

The command line prints its message without a traceback and exits with status 2; library
callers catch it like any ``ValueError``.
"""


class TwinFocusError(ValueError):
    """A user-facing error: the message names the argument or file and what is wrong."""
