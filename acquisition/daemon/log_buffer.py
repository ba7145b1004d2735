"""The daemon's recent log lines, kept in memory for the page's log panel (``GET /log``)."""

from __future__ import annotations

import logging
import threading
from collections import deque
from datetime import UTC, datetime

#: The lines kept: the oldest go first.
LOG_LINES = 500


class LogBuffer(logging.Handler):
    """A ring buffer of formatted log records, each numbered (``seq``) so that a reader asks
    only for the lines after the last it saw."""

    def __init__(self, capacity: int = LOG_LINES, level: int = logging.INFO):
        super().__init__(level)
        self._lines: deque[dict] = deque(maxlen=capacity)
        self._seq = 0
        self._guard = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
            if record.exc_info and record.exc_info[1] is not None:
                message += f": {type(record.exc_info[1]).__name__}: {record.exc_info[1]}"
            with self._guard:
                self._seq += 1
                self._lines.append(
                    {
                        "seq": self._seq,
                        "time_utc": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
                        "level": record.levelname,
                        "logger": record.name,
                        "message": message.replace("\n", " ⏎ "),
                    }
                )
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)

    def lines(self, after: int = 0, limit: int = LOG_LINES) -> list[dict]:
        """The lines numbered above ``after``, oldest first, the latest ``limit`` of them."""
        with self._guard:
            newer = [line for line in self._lines if line["seq"] > after]
        return newer[-limit:] if limit > 0 else []

    def attach(self, logger_name: str = "mirrorgonio") -> None:
        """Collect the records of ``logger_name`` and its children; a logger left at its
        parent's level (WARNING from the root) passes INFO on to this handler."""
        logger = logging.getLogger(logger_name)
        if logger.level == logging.NOTSET:
            logger.setLevel(logging.INFO)
        logger.addHandler(self)

    def detach(self, logger_name: str = "mirrorgonio") -> None:
        logging.getLogger(logger_name).removeHandler(self)
