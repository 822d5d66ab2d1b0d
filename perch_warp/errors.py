"""The one exception type users see: a clear, one-line message that says what to fix."""


class PerchError(Exception):
    """Bad input or an unusable environment; the CLI prints the message and exits non-zero."""
