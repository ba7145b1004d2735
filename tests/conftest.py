"""Shared fixtures: the reduced rig, free ports, and real daemon processes."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import OpenEXR
import pytest

ROOT = Path(__file__).resolve().parent.parent
REDUCED_RIG = ROOT / "tests" / "rigs" / "reduced.toml"


def rig_with(**edits):
    """The default rig with fields replaced: ``camera__width=500`` sets ``[camera] width``."""
    import tomllib

    from drivers.contracts.rig import DEFAULT_RIG_PATH, rig_from_dict

    data = tomllib.loads(DEFAULT_RIG_PATH.read_text())
    for path, value in edits.items():
        node = data
        *parents, leaf = path.split("__")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    return rig_from_dict(data)


def write_simulated_run(path, rig, run_id, positions, exposures, seed, on_capture=None):
    """A run file at ``path`` holding ``positions`` of ``rig``'s sweep, ``exposures`` each, as the
    simulated camera (``seed``) takes them, ended "aborted"; ``on_capture(index, camera)`` is
    called after each position's frames (to keep what the camera rendered)."""
    from drivers.contracts.runfile import PositionTimes, RunFileWriter, RunHeader
    from sim_devices.camera import SimulatedCamera
    from sim_devices.world import SimWorld

    tools = rig.tool_poses()
    here = {"pose": tools[0]}
    camera = SimulatedCamera(rig, SimWorld(lambda: here["pose"]), path.parent / f"{path.stem}-spool", seed=seed)
    header = RunHeader(
        run_id=run_id,
        rig=rig,
        tool_poses=tools,
        light_poses=rig.light_poses(),
        max_exposures=len(exposures),
        frame_shape=(rig.camera.height, rig.camera.width),
        bracket={"mode": "fixed", "exposures_s": list(exposures)},
        metadata={},
        devices={"arm": "test", "camera": camera.identity},
        software_version="test",
        created_utc="2026-11-21T00:00:00+00:00",
        preset="light-sweep",
    )
    with RunFileWriter.create(path, header) as writer:
        for index in positions:
            here["pose"] = tools[index]
            frames = [camera.capture(t) for t in exposures]
            if on_capture is not None:
                on_capture(index, camera)
            writer.write_position(index, tools[index], PositionTimes(0.0, 0.0, 0.0), frames)
        writer.set_status("aborted", f"{len(positions)} positions only")
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DaemonProcess:
    """``mirrorgonio serve`` in its own process, reached over HTTP only."""

    def __init__(self, config: Path, port: int, log: Path, token: str | None = None):
        self.config, self.port, self.log_path, self.token = config, port, log, token
        self.url = f"http://127.0.0.1:{port}"
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 60.0) -> DaemonProcess:
        exe = Path(sys.executable).with_name("mirrorgonio")
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        if self.token:
            env["MG_TOKEN"] = self.token
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [str(exe), "serve", "--config", str(self.config), "--port", str(self.port)],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"daemon exited: {self.log_path.read_text()[-2000:]}")
            try:
                httpx.get(self.url + "/health", timeout=1.0)
                return self
            except httpx.HTTPError:
                time.sleep(0.1)
        raise RuntimeError(f"daemon did not start: {self.log_path.read_text()[-2000:]}")

    def client(self) -> httpx.Client:
        """A client with the token, if any; every request is sent as JSON (the daemon takes
        nothing else for a request that changes something, body or none)."""
        headers = {"Content-Type": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        return httpx.Client(base_url=self.url, headers=headers, timeout=30.0)

    def kill(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.kill()
        if getattr(self, "_log", None):
            self._log.close()


def write_config(path: Path, data_dir: Path, arm_port: int = 0, extra: str = "") -> Path:
    path.write_text(
        f'data_dir = "{data_dir}"\nrig = "{REDUCED_RIG}"\n'
        f'[arm]\nkind = "simulated"\nport = {arm_port}\n[arm.simulated]\nspeed_m_s = 0.5\naccel_m_s2 = 5.0\n'
        f"{extra}"
    )
    return path


@pytest.fixture()
def daemon_factory(tmp_path):
    """Start real daemons; every one is stopped at the end of the test."""
    started: list[DaemonProcess] = []

    def make(config: Path, token: str | None = None, port: int | None = None) -> DaemonProcess:
        daemon = DaemonProcess(config, port or free_port(), tmp_path / f"daemon-{len(started)}.log", token)
        started.append(daemon)
        return daemon.start()

    yield make
    for daemon in started:
        daemon.stop()


def wait_for(
    client: httpx.Client, run_id: str, states, timeout: float = 300.0, done_at_least: int | None = None
) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = client.get(f"/runs/{run_id}").json()
        if status["state"] in states:
            return status
        if done_at_least is not None and status["positions_done"] >= done_at_least:
            return status
        time.sleep(0.1)
    raise AssertionError(f"run {run_id} did not reach {states}: {status}")


# --- the simulated truth light as a light model (the object chains' tests) ---------------------
TRUTH = "five-gaussians"


def truth_light_model(rig):
    """Each emitter fitted (gaussian) to noise-free samples of its own intensity: a LightModel."""
    from drivers.contracts.rig import rig_to_toml_dict
    from processing.fit import Samples, fit_intensity
    from processing.lightmodel import LightModel, SourceModel, samples_table
    from sim_devices.lights import load_truth

    theta = np.radians(np.linspace(0.5, 45.0, 60))
    sources = []
    for emitter in load_truth(TRUTH).emitters:
        values = emitter.intensity_w_sr(theta)
        samples = Samples(theta, np.zeros_like(theta), values, 1e-4 * values.max() + 0 * values, emitter.name)
        fit = fit_intensity(samples, "gaussian")
        sources.append(
            SourceModel(
                emitter.name,
                tuple(emitter.centre_m),
                emitter.radius_m,
                fit,
                samples_table(samples, np.arange(theta.size), values),
            )
        )
    return LightModel(sources, "W/sr", {"run_id": "truth", "rig": rig_to_toml_dict(rig)})


# pbrt-v4 goniometric lights as the renderer reads them (tests/test_exports.py, test_brdf_chain.py)


def pbrt_square_from_direction(w):
    """pbrt-v4's ``EqualAreaSphereToSquare`` (Clarberg 2008), with the exact arctangent where
    pbrt has its minimax polynomial: our own reading of the renderer, not the writer's map."""
    x, y, z = np.abs(w[:, 0]), np.abs(w[:, 1]), np.abs(w[:, 2])
    r = np.sqrt(np.maximum(1.0 - z, 0.0))
    a, b = np.maximum(x, y), np.minimum(x, y)
    phi = np.arctan(np.divide(b, a, out=np.zeros_like(a), where=a > 0)) * 2 / np.pi
    phi = np.where(x < y, 1.0 - phi, phi)
    v = phi * r
    u = r - v
    south = w[:, 2] < 0
    u, v = np.where(south, 1.0 - v, u), np.where(south, 1.0 - u, v)
    u, v = np.copysign(u, w[:, 0]), np.copysign(v, w[:, 1])
    return 0.5 * (u + 1.0), 0.5 * (v + 1.0)


def read_pbrt_lights(path):
    """Per ``LightSource "goniometric"``: (world ← light 4×4, table (n, n), rgb I, scale), as pbrt
    reads them (``Transform`` column by column; the table's ``Y`` channel)."""
    text = Path(path).read_text()
    lights = []
    for block in re.findall(r"AttributeBegin(.*?)AttributeEnd", text, re.S):
        numbers = [float(t) for t in re.search(r"Transform \[(.*?)\]", block).group(1).split()]
        matrix = np.array(numbers).reshape(4, 4).T
        name = re.search(r'"string filename" "(.*?)"', block).group(1)
        rgb = np.array([float(t) for t in re.search(r'"rgb I" \[(.*?)\]', block).group(1).split()])
        scale = float(re.search(r'"float scale" (\S+)', block).group(1))
        with OpenEXR.File(str(Path(path).parent / name)) as exr:
            table = np.array(exr.channels()["Y"].pixels, dtype=float)
        lights.append((matrix, table, rgb, scale))
    return lights


def pbrt_irradiance_rgb(lights, points, normals):
    """``Σ I(w)·max(0, n·ω)/r²`` as pbrt evaluates its goniometric lights: the direction into the
    light's space, y and z swapped, the nearest pixel of the equal-area table."""
    swap = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    E = np.zeros((len(points), 3))
    for matrix, table, rgb, scale in lights:
        d = points - matrix[:3, 3]
        dist = np.linalg.norm(d, axis=1)
        w = (d / dist[:, None]) @ np.linalg.inv(matrix[:3, :3]).T @ swap.T
        u, v = pbrt_square_from_direction(w)
        n = table.shape[0]
        col, row = np.clip((u * n).astype(int), 0, n - 1), np.clip((v * n).astype(int), 0, n - 1)
        cos_in = np.maximum(0.0, -np.einsum("ij,ij->i", normals, d) / dist)
        E += (scale * table[row, col] * cos_in / dist**2)[:, None] * rgb
    return E


# --- the catalog on both of its databases --------------------------------------------------
@pytest.fixture(scope="session")
def postgres_server():
    """A throwaway PostgreSQL server for this test process (installed by ``make test``)."""
    from acquisition.daemon.catalog.throwaway_server import PostgresNotFoundError, ThrowawayPostgres

    try:
        server = ThrowawayPostgres()
    except PostgresNotFoundError as exc:
        pytest.fail(f"{exc}: `make test` installs it", pytrace=False)
    yield server
    server.close()


_databases = iter(range(1_000_000))


@pytest.fixture(params=["sqlite", "postgresql"])
def catalog_url(request, tmp_path):
    """A new, empty catalog's location, on each database: an SQLite file, or a database of
    its own on the throwaway PostgreSQL server."""
    if request.param == "sqlite":
        return str(tmp_path / "catalog.sqlite")
    server = request.getfixturevalue("postgres_server")
    return server.create_database(f"catalog_{os.getpid()}_{next(_databases)}")


def run_sql(location: str, *statements: tuple[str, tuple] | str) -> list[list[tuple]]:
    """Run statements on a catalog's database directly (``?`` placeholders), past the Catalog;
    each statement's rows (those that return some)."""
    import sqlite3

    results = []
    if location.startswith("postgresql://"):
        import psycopg

        with psycopg.connect(location, autocommit=True) as conn:
            for statement in statements:
                sql, params = (statement, ()) if isinstance(statement, str) else statement
                cursor = conn.execute(sql.replace("?", "%s"), params)
                results.append(cursor.fetchall() if cursor.description else [])
        return results
    conn = sqlite3.connect(location)
    try:
        with conn:
            for statement in statements:
                sql, params = (statement, ()) if isinstance(statement, str) else statement
                results.append(conn.execute(sql, params).fetchall())
    finally:
        conn.close()
    return results


def unable(reason: str) -> None:
    """A test this machine cannot run (it needs root: a mount, a namespace): skipped on a
    developer's machine, a failure in CI, which runs as root and must run it."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason} (CI must run this test)", pytrace=False)
    pytest.skip(reason)
