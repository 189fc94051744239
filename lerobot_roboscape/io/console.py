"""A quiet console: a library's warning that a user can do nothing about is said once per process, not at every
env made or checkpoint saved."""

import logging


class _Once(logging.Filter):
    def __init__(self, prefix: str):
        super().__init__()
        self.prefix, self.seen = prefix, False

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.getMessage().startswith(self.prefix):
            return True
        seen, self.seen = self.seen, True
        return not seen


def say_once(logger_name: str, prefix: str) -> None:
    """Let the records of `logger_name` whose message starts with `prefix` through the first time only."""
    logger = logging.getLogger(logger_name)
    if not any(isinstance(f, _Once) and f.prefix == prefix for f in logger.filters):
        logger.addFilter(_Once(prefix))
