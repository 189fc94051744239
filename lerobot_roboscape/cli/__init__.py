"""The command lines: each parses its config and calls its stage.

User errors (`roboscape_core.errors.UserError`, a bad flag, a full disk or a read-only output directory) print
one line on stderr and exit with status 2. Set ROBOSCAPE_DEBUG=1 for the traceback. Any other exception is a bug
and keeps its traceback.
"""

import errno
import functools
import os
import sys
from collections.abc import Callable

from draccus.utils import ParsingError

from roboscape_core.errors import UserError

DEBUG_ENV = "ROBOSCAPE_DEBUG"
USER_ERROR_EXIT = 2
# Operating-system errors that the user fixes where the files live, not in the code.
_DISK_ERRORS = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EROFS: "the file system is read-only",
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.ENOENT: "no such file or directory",
}


def user_message(error: BaseException) -> str | None:
    """The one-line report of a user error; None for a bug."""
    if isinstance(error, ParsingError):
        chain = [error]
        while chain[-1].__cause__ is not None:
            chain.append(chain[-1].__cause__)
        # draccus names a flag it cannot decode; a config's __post_init__ error arrives wrapped in its generic
        # "Couldn't instantiate", and names the bad value itself.
        named = [e for e in chain if isinstance(e, UserError)] + [e for e in chain if "instantiate" not in str(e)]
        return str(named[0] if named else error)
    if isinstance(error, UserError):
        return str(error)
    if isinstance(error, OSError) and error.errno in _DISK_ERRORS and error.filename:
        return f"{error.filename}: {_DISK_ERRORS[error.errno]} ({error.strerror})"
    return None


def one_line_errors(command: str) -> Callable[[Callable], Callable]:
    """Decorate the `main` of `command` so that user errors print one line instead of a traceback."""

    def decorate(main: Callable) -> Callable:
        @functools.wraps(main)
        def wrapped(argv: list[str] | None = None):
            try:
                return main(argv)
            except Exception as error:
                message = user_message(error)
                if message is None or os.environ.get(DEBUG_ENV, "") not in ("", "0"):
                    raise
                print(f"{command}: error: {' '.join(message.split())}", file=sys.stderr)
                sys.exit(USER_ERROR_EXIT)

        return wrapped

    return decorate
