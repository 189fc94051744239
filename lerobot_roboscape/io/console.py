"""A quiet console: a warning is said once per process, not at every env made, checkpoint saved or episode read."""

import logging


class _Once(logging.Filter):
    def __init__(self, marker: str | None):
        super().__init__()
        self.marker, self.seen = marker, set()

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if self.marker is not None and self.marker not in message:
            return True
        key = message if self.marker is None else self.marker
        if key in self.seen:
            return False
        self.seen.add(key)
        return True


def say_once(logger_name: str, marker: str | None = None) -> None:
    """Let the records of `logger_name` that contain `marker` through the first time only (Accelerate prefixes its
    own with "[RANK 0] "); without a marker, each distinct message once."""
    logger = logging.getLogger(logger_name)
    if not any(isinstance(f, _Once) and f.marker == marker for f in logger.filters):
        logger.addFilter(_Once(marker))
