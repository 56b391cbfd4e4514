"""User-facing errors.

Library code raises :class:`DynslamError` for anything a user can fix (a missing file, a bad
config key, a corrupt image).  The CLI prints its message as one line and exits with code 2;
no traceback.  The message must say *what* is wrong and *where* (file, key, frame).
"""


class DynslamError(Exception):
    """An error caused by user input; its message is shown to the user as one line."""

    exit_code = 2

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))
