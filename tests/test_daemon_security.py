"""The daemon's HTTP security (docs/daemon.md, "Security") with raw HTTP against real daemon
processes: a forged Host (DNS rebinding), cross-site simple requests, tokens guarding reads,
the body size limit; and the settings that configure them, in process.
"""

from __future__ import annotations

import http.client
import json
import select
import socket
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from conftest import DaemonProcess, free_port, wait_for, write_config

from acquisition.daemon.api.guard import RequestGuard
from acquisition.daemon.settings import DEFAULT_MAX_BODY_BYTES, SettingsError, load_settings

TOKEN = "security-test-token-0123"
JSON = {"Content-Type": "application/json"}
EVIL = "rebound.example"


@pytest.fixture(scope="module")
def daemons(tmp_path_factory):
    """Two real daemons for the module: the default (loopback, no token) with one finished
    run, and one with a token."""
    root = tmp_path_factory.mktemp("security")
    open_one = DaemonProcess(write_config(root / "open.toml", root / "open"), free_port(), root / "open.log")
    guarded = DaemonProcess(write_config(root / "token.toml", root / "token"), free_port(), root / "token.log", TOKEN)
    try:
        with ThreadPoolExecutor(2) as pool:  # started side by side: most of a start is imports
            list(pool.map(DaemonProcess.start, (open_one, guarded)))
        with open_one.client() as client:
            bracket = {"mode": "fixed", "exposures_s": [0.001]}
            run = client.post("/runs", json={"count": 1, "bracket": bracket, "calibration": {"before": False}}).json()
            assert wait_for(client, run["id"], {"complete", "failed"}, timeout=60)["state"] == "complete"
        yield open_one, guarded, run["id"]
    finally:
        open_one.stop()
        guarded.stop()


def send(daemon, method, path, headers=(), body=None, host=None):
    """One request as sent by hand: exactly these headers (Host too), nothing added."""
    conn = http.client.HTTPConnection("127.0.0.1", daemon.port, timeout=30)
    try:
        conn.putrequest(method, path, skip_host=True, skip_accept_encoding=True)
        conn.putheader("Host", f"127.0.0.1:{daemon.port}" if host is None else host)
        for name, value in dict(headers).items():
            conn.putheader(name, value)
        if body is not None:
            conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        answer = conn.getresponse()
        return answer.status, answer.read()
    finally:
        conn.close()


def detail(raw: bytes) -> str:
    text = json.loads(raw)["detail"]
    assert isinstance(text, str) and "\n" not in text
    return text


def rss_mb(daemon) -> float:
    with open(f"/proc/{daemon.proc.pid}/status") as status:
        kb = next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))
    return kb / 1024


def runs_of(daemon) -> list[str]:
    return [run["id"] for run in json.loads(send(daemon, "GET", "/runs")[1])]


def test_a_forged_host_is_refused_before_anything_happens(daemons):
    daemon, _, run_id = daemons
    before = runs_of(daemon)
    rebound = f"{EVIL}:{daemon.port}"  # what a page of a rebound name sends
    cases = [
        ("POST", "/arm/stop", JSON, b""),
        ("POST", "/runs", JSON, b'{"count": 1}'),
        ("GET", f"/runs/{run_id}/file", {}, None),
        ("GET", "/devices", {}, None),
    ]
    for method, path, headers, body in cases:
        status, raw = send(daemon, method, path, headers, body, host=rebound)
        assert status == 400, (path, raw)
        assert detail(raw) == (
            f"host: '{rebound}' is not a host this daemon answers to (its setting allowed_hosts, MG_ALLOWED_HOSTS)"
        )
    for host in ("", "127.0.0.1.evil.example", "127.0.0.1@evil.example", f"[::2]:{daemon.port}"):
        assert send(daemon, "GET", "/runs", host=host)[0] == 400, host
    assert runs_of(daemon) == before  # no run was started
    # The daemon's own names, on any port (an SSH tunnel, a published port).
    for host in (f"127.0.0.1:{daemon.port}", "localhost:9999", "LOCALHOST", f"[::1]:{daemon.port}"):
        assert send(daemon, "GET", "/runs", host=host)[0] == 200, host
    status, raw = send(daemon, "GET", f"/runs/{run_id}/file")
    assert status == 200 and raw[:8] == b"\x89HDF\r\n\x1a\n"


def test_a_cross_site_simple_request_is_refused(daemons):
    daemon, _, run_id = daemons
    evil_origin = {"Origin": "http://attacker.example"}
    refused = [
        # A page on another site: its Origin.
        (403, "POST", "/arm/stop", {**evil_origin, "Content-Type": "text/plain"}, b"x"),
        (403, "POST", f"/runs/{run_id}/process", {**evil_origin, "Content-Type": "text/plain"}, b'{"steps":"hdr"}'),
        (403, "POST", "/runs", {**evil_origin, **JSON}, b'{"count": 1}'),  # it could not send this, but still
        (403, "POST", "/arm/stop", {"Origin": "null", **JSON}, b""),  # a sandboxed page, a no-referrer policy
        (403, "POST", "/arm/stop", {"Origin": f"http://localhost.attacker.example:{daemon.port}", **JSON}, b""),
        # Without an Origin: what a simple request can carry (text, a form) or no type at all.
        (415, "POST", "/arm/stop", {"Content-Type": "text/plain"}, b"x"),
        (415, "POST", f"/runs/{run_id}/process", {"Content-Type": "text/plain;charset=UTF-8"}, b'{"steps":"hdr"}'),
        (415, "POST", "/runs", {"Content-Type": "application/x-www-form-urlencoded"}, b"count=1"),
        (415, "POST", "/runs", {"Content-Type": "multipart/form-data; boundary=x"}, b"--x--"),
        (415, "POST", "/runs", {}, b'{"count": 1}'),
        (415, "POST", "/arm/stop", {}, None),  # bodyless: still JSON, or refused
        (415, "POST", f"/runs/{run_id}/abort", {}, b""),
        (415, "DELETE", "/session", {}, None),
    ]
    for status, method, path, headers, body in refused:
        got, raw = send(daemon, method, path, headers, body)
        assert got == status, (path, headers, raw)
        assert ("origin: " if status == 403 else "content-type: ") in detail(raw)
    assert runs_of(daemon) == [run_id]
    jobs = json.loads(send(daemon, "GET", "/jobs")[1])
    assert jobs == []


def test_an_allowed_origin_with_json_is_accepted(daemons):
    daemon, _, run_id = daemons
    own = {"Origin": f"http://127.0.0.1:{daemon.port}", **JSON}
    status, raw = send(daemon, "POST", f"/runs/{run_id}/process", own, b'{"steps": "hdr"}')
    assert status == 201, raw
    assert json.loads(raw)["run_id"] == run_id
    status, raw = send(daemon, "POST", "/arm/stop", {"Origin": f"http://localhost:{daemon.port}", **JSON}, b"")
    assert (status, json.loads(raw)) == (202, {"stopped": True})
    assert send(daemon, "POST", "/arm/stop", {"Content-Type": "application/json; charset=utf-8"})[0] == 202


def test_the_token_guards_reads_too(daemons):
    _, daemon, _ = daemons
    bearer = {"Authorization": f"Bearer {TOKEN}"}
    guarded = ["/runs", "/runs/nope", "/runs/nope/file", "/runs/nope/events", "/jobs", "/jobs/nope/artifacts/ies"]
    guarded += ["/devices", "/presets", "/preview.png", "/preview/frame", "/preview/frame.png", "/log"]
    guarded += ["/jobs/nope/figures", "/jobs/nope/figures/0.png", "/jobs/nope/photometry"]
    for path in guarded:
        assert send(daemon, "GET", path)[0] == 401, path
        assert send(daemon, "GET", path, {"Authorization": "Bearer wrong-token-0123456789"})[0] == 403, path
        assert send(daemon, "GET", path, bearer)[0] in (200, 404), path
    # The health, and the page's shell (the page then asks for the token), are open.
    for path in ("/health", "/", "/app.js", "/align.js", "/app.css"):
        assert send(daemon, "GET", path)[0] == 200, path
    # The page's session: a cookie for the browser's own reads, never for a change.
    conn = http.client.HTTPConnection("127.0.0.1", daemon.port, timeout=30)
    conn.request("POST", "/session", headers={**bearer, **JSON})
    answer = conn.getresponse()
    answer.read()
    cookie = answer.getheader("Set-Cookie")
    assert answer.status == 204 and "HttpOnly" in cookie and "SameSite=strict" in cookie and TOKEN not in cookie
    session = {"Cookie": cookie.split(";")[0]}
    assert send(daemon, "GET", "/runs", session)[0] == 200
    assert send(daemon, "POST", "/arm/stop", {**session, **JSON})[0] == 401
    # The bench's moves and test shot: the token itself, and JSON.
    jog = json.dumps({"axis": "z", "step": -1.0}).encode()
    for path, body in (("/arm/jog", jog), ("/arm/home", None), ("/preview/shot", None)):
        assert send(daemon, "POST", path, JSON, body)[0] == 401, path
        assert send(daemon, "POST", path, {**session, **JSON}, body)[0] == 401, path
        assert send(daemon, "POST", path, {**bearer, "Content-Type": "text/plain"}, body)[0] == 415, path
    assert send(daemon, "POST", "/arm/jog", {**bearer, **JSON}, jog)[0] == 200
    assert send(daemon, "GET", "/runs", {"Cookie": "mirrorgonio_session=forged"})[0] == 401
    assert send(daemon, "POST", "/session", {**JSON, "Authorization": "Bearer wrong-token-0123456789"})[0] == 403


def test_an_oversized_body_is_refused_unread(daemons):
    """A Content-Length over the limit is a 413 before any of the body is read; a chunked body
    is cut where it passes the limit. The daemon's memory does not grow by the body."""
    daemon, _, _ = daemons
    before = rss_mb(daemon)
    announced = 400 * 1024 * 1024
    with socket.create_connection(("127.0.0.1", daemon.port), timeout=10) as sock:
        head = f"POST /runs HTTP/1.1\r\nHost: 127.0.0.1:{daemon.port}\r\nContent-Type: application/json\r\n"
        sock.sendall((head + f"Content-Length: {announced}\r\n\r\n").encode() + b'{"notes": "')
        status_line, sent = _answer_while_sending(sock, lambda: b"n" * 65536, limit=64 * 1024 * 1024)
    assert status_line.startswith(b"HTTP/1.1 413"), status_line
    assert sent < 16 * 1024 * 1024, sent  # answered at once: what went was only what the buffers took

    with socket.create_connection(("127.0.0.1", daemon.port), timeout=10) as sock:
        head = f"POST /runs HTTP/1.1\r\nHost: 127.0.0.1:{daemon.port}\r\nContent-Type: application/json\r\n"
        sock.sendall((head + "Transfer-Encoding: chunked\r\n\r\n").encode())
        chunk = b"10000\r\n" + b"n" * 65536 + b"\r\n"
        status_line, sent = _answer_while_sending(sock, lambda: chunk, limit=64 * 1024 * 1024)
    assert status_line.startswith(b"HTTP/1.1 413"), status_line
    assert DEFAULT_MAX_BODY_BYTES < sent < DEFAULT_MAX_BODY_BYTES + 16 * 1024 * 1024, sent
    assert rss_mb(daemon) - before < 30, (before, rss_mb(daemon))
    assert send(daemon, "GET", "/health")[0] == 200


def _answer_while_sending(sock, block, limit):
    """Send ``block()`` after block until the daemon answers (or ``limit`` bytes went):
    the answer's status line and the bytes sent."""
    sock.setblocking(False)
    sent, pending = 0, b""
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        readable, writable, _ = select.select([sock], [sock] if sent < limit else [], [], 1.0)
        if readable:
            sock.setblocking(True)
            return sock.recv(4096).split(b"\r\n", 1)[0], sent
        if writable:
            pending = pending or block()
            try:
                n = sock.send(pending)
            except (BrokenPipeError, ConnectionResetError):
                sock.setblocking(True)
                return sock.recv(4096).split(b"\r\n", 1)[0], sent
            sent, pending = sent + n, pending[n:]
    raise AssertionError(f"no answer after {sent} bytes")


# --- the settings, in process ------------------------------------------------------------------
@pytest.mark.parametrize("token", ["Q", "short-token", " \t", "0123456789abcde", "  0123456789abcde \n"])
def test_a_token_shorter_than_16_characters_is_refused_at_start(token, monkeypatch):
    if not token.strip():  # only whitespace: no token (loopback only), as an empty one
        assert load_settings(None, token=token).token is None
        return
    with pytest.raises(SettingsError) as refused:
        load_settings(None, token=token)
    message = str(refused.value)
    n = len(token.strip())
    assert message.startswith(f"<settings>: token: too short ({n} character{'s' * (n > 1)}): at least 16 are needed")
    assert "MG_TOKEN" in message and token.strip() not in message and "\n" not in message
    monkeypatch.setenv("MG_TOKEN", token)
    with pytest.raises(SettingsError, match="token: too short"):
        load_settings(None)


def test_a_token_of_16_characters_is_taken_without_its_whitespace():
    assert load_settings(None, token=" 0123456789abcdef\n").token.get_secret_value() == "0123456789abcdef"


def guard(**settings) -> RequestGuard:
    return RequestGuard(None, load_settings(None, **settings))


def test_allowed_hosts_default_and_setting(monkeypatch):
    default = guard()
    for host in ("localhost", "localhost:8000", "127.0.0.1:1", "[::1]:8000", "LocalHost.:8000"):
        assert default.allowed(host), host
    for host in ("", "evil.example", "0.0.0.0:8000", "127.0.0.2", "localhost:0", "localhost:x", "::1", "a b"):
        assert not default.allowed(host), host
    # The listening address, on its port; a wildcard address is no name.
    assert guard(host="192.168.4.2", port=8000, token=TOKEN).allowed("192.168.4.2:8000")
    assert not guard(host="192.168.4.2", port=8000, token=TOKEN).allowed("192.168.4.2:8001")
    assert not guard(host="0.0.0.0", token=TOKEN).allowed("0.0.0.0:8000")
    # Set: those too; with MG_ALLOWED_HOSTS, names separated by commas (or a JSON list).
    monkeypatch.setenv("MG_ALLOWED_HOSTS", "daemon:8000, lab.example.org")
    named = guard()
    assert named.allowed("daemon:8000") and named.allowed("lab.example.org") and named.allowed("lab.example.org:443")
    assert not named.allowed("daemon:8001") and not named.allowed("evil.example")
    assert named.allowed("localhost:8000")  # a healthcheck on the machine itself
    monkeypatch.setenv("MG_ALLOWED_HOSTS", " ")
    assert guard().hosts == default.hosts
    monkeypatch.setenv("MG_ALLOWED_HOSTS", '["*"]')
    assert guard().allowed("anything.example:1")
    monkeypatch.setenv("MG_ALLOWED_HOSTS", "lab.example.org, http://x/")
    with pytest.raises(SettingsError, match=r"^<settings>: allowed_hosts: 'http://x/' is not HOST or HOST:PORT$"):
        load_settings(None)


def test_the_guard_refuses_from_the_headers_alone():
    refusal = guard(max_body_bytes=2048).refusal

    def scope(method="POST", **headers):
        pairs = [(b"host", b"localhost:8000")] + [
            (k.replace("_", "-").encode(), v.encode()) for k, v in headers.items()
        ]
        return {"type": "http", "method": method, "headers": pairs}

    assert refusal(scope(content_type="application/json")) is None
    assert refusal(scope("GET")) is None
    assert refusal(scope("PUT", content_type="text/plain"))[0] == 415
    assert refusal(scope("PATCH"))[0] == 415
    assert refusal(scope("BREW", content_type="text/plain"))[0] == 415  # any method but GET, HEAD, OPTIONS
    assert refusal(scope(content_type="application/json", content_length="2049"))[0] == 413
    assert refusal(scope("GET", content_length="2049"))[0] == 413
    assert refusal(scope(content_type="application/json", content_length="-1"))[0] == 400
    assert refusal(scope(content_type="application/json", origin="https://localhost")) is None
    assert refusal(scope(content_type="application/json", origin="localhost"))[0] == 403
    two_hosts = {"type": "http", "method": "GET", "headers": [(b"host", b"localhost"), (b"host", b"evil.example")]}
    assert refusal(two_hosts) == (400, "host: a request names one Host (it has 2)")


def test_workers_uploads_take_a_tar_archive_on_their_route_only_and_the_daemons_told_name():
    """The one non-JSON body: a worker's results (PUT /jobs/ID/results, application/x-tar, up
    to max_results_bytes); the name the daemon tells workers is one it answers to."""
    check = guard(max_body_bytes=2048, max_results_bytes=10_000)

    def scope(method, path, **headers):
        pairs = [(b"host", b"localhost:8000")] + [
            (k.replace("_", "-").encode(), v.encode()) for k, v in headers.items()
        ]
        return {"type": "http", "method": method, "path": path, "headers": pairs}

    results = "/jobs/job-1/results"
    assert check.refusal(scope("PUT", results, content_type="application/x-tar", content_length="9000")) is None
    assert check.refusal(scope("PUT", results, content_type="application/x-tar", content_length="10001"))[0] == 413
    assert check.refusal(scope("PUT", results, content_type="application/json"))[0] == 415
    assert check.refusal(scope("PUT", "/jobs/job-1/results/x", content_type="application/x-tar"))[0] == 415
    assert check.refusal(scope("POST", results, content_type="application/x-tar"))[0] == 415
    assert check.refusal(scope("POST", "/runs", content_type="application/x-tar"))[0] == 415
    assert check.refusal(scope("POST", "/runs", content_type="application/json", content_length="2049"))[0] == 413
    told = guard(host="0.0.0.0", port=8000, token=TOKEN, public_url="http://rig-1.lab:8000")
    assert told.allowed("rig-1.lab:8000") and not told.allowed("rig-1.lab:8001")
    with pytest.raises(SettingsError, match="public_url"):
        load_settings(None, public_url="rig-1.lab:8000")
    with pytest.raises(SettingsError, match=r"^<settings>: catalog: not a catalog URL: 'mysql://lab@db/x'"):
        load_settings(None, catalog="mysql://lab:s3cret@db/x")  # and no password in the message
