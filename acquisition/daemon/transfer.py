"""Run files and results between a daemon and a worker that does not share its disk.

The worker fetches a run file with ``GET /runs/{id}/file``, resuming a cut transfer with
``Range`` (``If-Range`` on the file's ``ETag``, so that a changed file starts over), and
checks it against the SHA-256 the daemon sends (``Repr-Digest``, RFC 9530): the bytes that
arrived are the daemon's. The frames' own checksums are then checked by the processing's
first step (``checksums``), before any work, as for a run on the worker's disk. It sends its
results back as one tar archive, ``PUT /jobs/{id}/results``; the daemon unpacks it beside the
run file, where a worker on its own disk would have written them, refusing any member that
would land elsewhere.
"""

from __future__ import annotations

import base64
import contextlib
import os
import shutil
import tarfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NoReturn, TypeVar

import httpx

from acquisition.daemon.catalog import RunRecord
from drivers.contracts.runfile import file_sha256

T = TypeVar("T")
#: Bytes read at a time, hashing or streaming.
BLOCK = 1 << 20
DIGEST_HEADER = "Repr-Digest"


class TransferError(RuntimeError):
    """A run file or results that cannot be moved, or are not what was sent (one line)."""


def repr_digest(hex_digest: str) -> str:
    """A ``Repr-Digest`` header's value: ``sha-256=:BASE64:``."""
    return f"sha-256=:{base64.b64encode(bytes.fromhex(hex_digest)).decode()}:"


def digest_from_header(value: str | None) -> str | None:
    """The hex SHA-256 of a ``Repr-Digest`` header, None if it has none."""
    for part in (value or "").split(","):
        name, _, rest = part.strip().partition("=")
        if name.strip().lower() == "sha-256" and rest.startswith(":") and rest.endswith(":"):
            with contextlib.suppress(ValueError):
                return base64.b64decode(rest[1:-1], validate=True).hex()
    return None


class DigestCache:
    """Files' SHA-256 by (path, size, mtime): a finished run file is hashed once, not per fetch."""

    def __init__(self) -> None:
        self._digests: dict[tuple[str, int, int], str] = {}
        self._lock = threading.Lock()

    def get(self, path: Path) -> str:
        stat = path.stat()
        key = (str(path), stat.st_size, stat.st_mtime_ns)
        with self._lock:
            known = self._digests.get(key)
        if known is None:
            known = file_sha256(path)
            with self._lock:
                self._digests[key] = known
        return known


def pack_results(folder: Path, exclude: set[str]) -> Iterator[bytes]:
    """The files under ``folder`` (but those named in ``exclude`` at its top) as a tar stream."""
    reader, writer = os.pipe()

    def write() -> None:
        with os.fdopen(writer, "wb") as out, tarfile.open(fileobj=out, mode="w|") as tar:
            for entry in sorted(folder.iterdir()):
                if entry.name not in exclude:
                    tar.add(entry, arcname=entry.name)

    thread = threading.Thread(target=write, name="pack-results", daemon=True)
    thread.start()
    with os.fdopen(reader, "rb") as source:
        while block := source.read(BLOCK):
            yield block
    thread.join()


def unpack_results(archive: Path, folder: Path, protected: set[str]) -> dict[str, str]:
    """Unpack a results archive into ``folder``: every member a plain file or folder inside it,
    none named as one of ``protected`` (the run file and its lock). Files already there are
    replaced (a job processed again), each only once all of the archive has unpacked.

    Returns
    -------
    dict
        Each file's path in the archive -> its path in ``folder``.

    Raises
    ------
    TransferError
        The archive cannot be read, or a member would leave ``folder`` or replace a protected file.
    OSError
        ``folder``'s disk refused a write (full, read-only).
    """
    staging = folder / f".results-{archive.stem}"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        with tarfile.open(archive, mode="r:") as tar:
            members = tar.getmembers()
            for member in members:
                top = Path(member.name).parts[0] if member.name else ""
                if not (member.isfile() or member.isdir()) or top in protected:
                    raise TransferError(f"results archive: {member.name!r} is not a results file it may write")
            tar.extractall(staging, filter="data")  # refuses absolute names, '..' and links out
        files = {member.name: str(folder / member.name) for member in members if member.isfile()}
        for entry in staging.iterdir():
            target = folder / entry.name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            os.replace(entry, target)
        return files
    except tarfile.TarError as exc:  # not its disk's failures: those are the caller's 507 or 503
        raise TransferError(f"results archive: {exc}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


# --- the worker's side ---------------------------------------------------------------------
class DaemonUnreachableError(TransferError):
    """The daemon did not answer within the time given: the job waits and is tried again."""


class RunFetcher:
    """A worker's copies of the run files it cannot see at their paths, fetched from the daemon
    of each run's rig, and its results sent back there.

    Parameters
    ----------
    daemon_url : callable
        ``daemon_url(rig)``: where that rig's daemon answers (the catalog's record), or None.
    folder : Path
        Where the copies are kept while their job runs (``FOLDER/RIG/RUN/``).
    token : str, optional
        The daemons' API token (a lab gives its daemons and workers one).
    fetch_patience_s : float
        How long a fetch goes on retrying a daemon that does not answer (its network cut, it
        restarts, it answers 5xx) before the job is put back to wait: short, so that a rig
        that is away does not hold the worker from the other rigs' jobs.
    send_patience_s : float
        The same for sending results back: long, since giving up means processing again.
    """

    def __init__(
        self,
        daemon_url: Callable[[str], str | None],
        folder: Path,
        token: str | None = None,
        *,
        fetch_patience_s: float = 30.0,
        send_patience_s: float = 300.0,
        timeout_s: float = 30.0,
    ):
        self.daemon_url = daemon_url
        self.folder = Path(folder)
        self.fetch_patience_s = float(fetch_patience_s)
        self.send_patience_s = float(send_patience_s)
        self._headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._timeout = httpx.Timeout(timeout_s)

    @staticmethod
    def is_remote(run: RunRecord) -> bool:
        """Whether the run's file is not to be seen at its path here."""
        return bool(run.path) and not Path(str(run.path)).is_file()

    def _base(self, rig: str) -> str:
        url = self.daemon_url(rig)
        if url is None:
            raise DaemonUnreachableError(f"rig {rig!r}'s daemon has not recorded where it answers (its public_url)")
        return url

    def run_folder(self, run: RunRecord) -> Path:
        return self.folder / run.rig / run.id

    def fetch(self, run: RunRecord, on_progress: Callable[[int, int], None] | None = None) -> Path:
        """The run's file, fetched into :meth:`run_folder` (resuming a cut transfer) and checked
        against the daemon's SHA-256 (the processing's first step checks the frames' checksums).

        Raises
        ------
        DaemonUnreachableError
            The daemon did not answer for ``fetch_patience_s``.
        TransferError
            The daemon refused, or what arrived is not the file it sent.
        """
        url = f"{self._base(run.rig)}/runs/{run.id}/file"
        local = self.run_folder(run) / Path(str(run.path)).name
        local.parent.mkdir(parents=True, exist_ok=True)
        part, tag_file = local.with_name(local.name + ".part"), local.with_name(local.name + ".etag")
        digest = _retried(
            lambda: self._download(url, part, tag_file, on_progress),
            f"fetching run {run.id} from {url}",
            self.fetch_patience_s,
        )
        if digest is None:
            raise TransferError(f"run {run.id} from {url}: the daemon sent no SHA-256 ({DIGEST_HEADER}) to check it")
        if file_sha256(part) != digest:
            part.unlink(missing_ok=True)
            tag_file.unlink(missing_ok=True)
            raise DaemonUnreachableError(
                f"run {run.id} from {url}: the file that arrived is not the daemon's (its SHA-256 differs)"
            )
        os.replace(part, local)
        tag_file.unlink(missing_ok=True)
        return local

    def _download(
        self, url: str, part: Path, tag_file: Path, on_progress: Callable[[int, int], None] | None
    ) -> str | None:
        """Download ``url`` into ``part``, from where it stopped if it can; the daemon's SHA-256."""
        have = part.stat().st_size if part.exists() else 0
        tag = tag_file.read_text() if tag_file.exists() else None
        headers = dict(self._headers)
        if have and tag:
            headers.update({"Range": f"bytes={have}-", "If-Range": tag})
        with httpx.stream("GET", url, headers=headers, timeout=self._timeout) as answer:
            if answer.status_code not in (200, 206):
                answer.read()
                _refused(answer, f"GET {url}")
            digest = digest_from_header(answer.headers.get(DIGEST_HEADER))
            resumed = answer.status_code == 206
            total = int(answer.headers.get("content-length", 0)) + (have if resumed else 0)
            if "etag" in answer.headers:
                tag_file.write_text(answer.headers["etag"])
            with part.open("ab" if resumed else "wb") as out:
                done = have if resumed else 0
                for block in answer.iter_bytes(BLOCK):
                    out.write(block)
                    done += len(block)
                    if on_progress is not None:
                        on_progress(done, total)
        return digest

    def send_results(
        self, job_id: str, worker_id: str, run: RunRecord, local_run: Path, artifacts: dict[str, str]
    ) -> tuple[str, dict[str, str]]:
        """Send the results written beside ``local_run`` to the run's daemon; where it keeps them:
        (its result folder, the artifacts as its paths). The local copies are deleted then.

        Raises
        ------
        DaemonUnreachableError, TransferError
            As :meth:`fetch`.
        """
        url = f"{self._base(run.rig)}/jobs/{job_id}/results"
        folder = local_run.parent
        exclude = {local_run.name, local_run.name + ".lock"}

        def send() -> dict:
            answer = httpx.put(
                url,
                params={"worker_id": worker_id},
                content=pack_results(folder, exclude),  # packed afresh at each try
                headers={**self._headers, "Content-Type": "application/x-tar"},
                timeout=self._timeout,
            )
            if answer.status_code != 200:
                _refused(answer, f"PUT {url}")
            return answer.json()

        kept = _retried(send, f"sending job {job_id}'s results to {url}", self.send_patience_s)
        files: dict[str, str] = kept["files"]
        mapped = {}
        for kind, path in artifacts.items():
            name = Path(path).resolve().relative_to(folder.resolve()).as_posix()
            if name not in files:
                raise TransferError(f"job {job_id}: the daemon did not keep its {kind} ({name})")
            mapped[kind] = files[name]
        shutil.rmtree(folder, ignore_errors=True)
        return kept["result_dir"], mapped

    def forget(self, run: RunRecord) -> None:
        """Delete the local copy of a run and whatever was written beside it."""
        shutil.rmtree(self.run_folder(run), ignore_errors=True)


class _DaemonBusy(Exception):
    """An answer worth trying again: the daemon's own storage or catalog is away (5xx), or it
    asks to wait (429)."""


def _refused(answer: httpx.Response, what: str) -> NoReturn:
    """Raise for an answer that is not the one asked for: retried where it is the daemon's
    passing trouble (5xx, 429), a TransferError naming the status otherwise."""
    text = f"{what}: {answer.status_code} {_detail(answer)}"
    if answer.status_code >= 500 or answer.status_code == 429:
        raise _DaemonBusy(text)
    raise TransferError(text)


def _retried(action: Callable[[], T], what: str, patience_s: float) -> T:
    """``action()``, tried again with a growing pause while the daemon does not answer or
    answers that it cannot now, for ``patience_s``; then a DaemonUnreachableError."""
    deadline = time.monotonic() + patience_s
    pause = 0.5
    while True:
        try:
            return action()
        except (httpx.TransportError, _DaemonBusy) as exc:
            if time.monotonic() > deadline:
                raise DaemonUnreachableError(f"{what}: {str(exc) or type(exc).__name__}") from None
            time.sleep(pause)
            pause = min(2 * pause, 10.0)


def _detail(answer: httpx.Response) -> str:
    try:
        return str(answer.json().get("detail", answer.text))
    except ValueError:
        return answer.text[:200]
