"""Files a client names in a request: a run's ``light_results``, a job's ``layout``.

They are paths on the daemon's or the worker's machine, given over HTTP, so they are read as
:mod:`drivers.config_files` reads every input file (regular files only, checked before they
are opened, opened without blocking, at most :data:`CLIENT_FILE_LIMIT` bytes) and within
:data:`CLIENT_READ_TIMEOUT_S`, in the request's worker thread, never on the event loop. What
goes wrong is said to the client in words that do not tell what the machine's filesystem
holds (whether a path exists, is a directory, a device, or cannot be read): the reason is in
the log, and in the answer to a client that holds the daemon's token.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

from drivers.config_files import MAX_TEXT_BYTES, read_input_text

log = logging.getLogger("mirrorgonio.client_files")

#: The largest file a client may name, in bytes (a light model is about 0.2 MB, a layout 1 KB).
CLIENT_FILE_LIMIT = MAX_TEXT_BYTES
#: How long reading a file a client named may take, in seconds (a hung network filesystem).
CLIENT_READ_TIMEOUT_S = 5.0

T = TypeVar("T")


class ClientFileError(ValueError):
    """A file a client named cannot be used.

    ``str(error)`` is the answer for any client: it names the field and nothing of the
    machine; :attr:`detail` is the one-line reason, for the log and for token holders.
    """

    def __init__(self, field: str, what: str, detail: str):
        super().__init__(f"{field}: the {what} cannot be used (the daemon's or worker's log says why)")
        self.field = field
        self.detail = detail


class _Unusable(ValueError):
    pass


@contextmanager
def client_file(field: str, what: str) -> Iterator[None]:
    """Any ``ValueError`` or ``OSError`` raised inside, as a :class:`ClientFileError`, logged."""
    try:
        yield
    except (ValueError, OSError) as exc:
        detail = " ".join(str(exc).split())
        log.warning("%s (a client's %s): %s", field, what, detail)
        raise ClientFileError(field, what, detail) from None


def load_client_file(value: str, field: str, what: str, parse: Callable[[str], T]) -> tuple[T, str]:
    """The file a client named in ``field``, read as UTF-8 text and parsed by ``parse``, with
    the SHA-256 of its bytes.

    Raises
    ------
    ClientFileError
        The file cannot be read (:func:`drivers.config_files.read_input_text`), or ``parse``
        raised a ``ValueError`` on its text.
    """
    with client_file(field, what):
        path = Path(value).expanduser()
        text = read_input_text(
            path, what, _Unusable, field=field, limit=CLIENT_FILE_LIMIT, timeout_s=CLIENT_READ_TIMEOUT_S
        )
        return parse(text), hashlib.sha256(text.encode("utf-8")).hexdigest()
