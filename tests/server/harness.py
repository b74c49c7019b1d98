"""Test harness: a real service in a subprocess (``python -m client.cli serve``) on a free loopback port,
or in this process (`in_process_server`, for tests that patch its parts), and the shelf frames
downscaled to 320x240 as `Session.add_frame` keyword arguments."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import uvicorn

from client.cli.capture import frame_arrays
from client.cli.launch import free_port, wait_until_healthy

REPO = Path(__file__).resolve().parents[2]
TOKEN = "test-token-5f1c"
VOXEL = 0.008  # coarse enough to be fast; quality is not under test


class ServerProcess:
    """One service process. ``settings`` become CANONICAL_* environment variables."""

    def __init__(self, data_dir: Path, log_path: Path, token: str | None = None, **settings):
        self.data_dir, self.log_path, self.token, self.settings = Path(data_dir), Path(log_path), token, settings
        self.proc: subprocess.Popen | None = None
        self.port = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 300.0, same_port: bool = False) -> "ServerProcess":
        """Start the service and wait until it answers (on a new free port, or with ``same_port`` on
        the last one: a restart its clients find again). The deadline is generous: on a cold numba cache
        the service compiles its start-up kernels first (minutes on two cores shared with another
        test worker); `make test` fills the cache beforehand, so there it starts in seconds."""
        self.port = self.port if same_port and self.port else free_port()
        env = {k: v for k, v in os.environ.items() if not k.startswith("CANONICAL_")}
        env.update({f"CANONICAL_{k.upper()}": str(v) for k, v in self.settings.items()})
        if self.token:
            env["CANONICAL_API_TOKEN"] = self.token
        env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
        cmd = [sys.executable, "-m", "client.cli", "serve", "--port", str(self.port), "--data-dir", str(self.data_dir),
               "--threads", "1", "--log-level", "warning"]
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=self._log, stderr=subprocess.STDOUT)
        try:
            wait_until_healthy(self.url, self.proc, timeout)
        except RuntimeError as exc:
            self.kill9()
            raise RuntimeError(f"{exc}:\n{self.log()}") from None
        return self

    def kill9(self) -> None:
        if self.proc and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self._close_log()

    def stop(self) -> None:
        """SIGTERM (graceful: uvicorn runs the shutdown, which snapshots), SIGKILL after 30 s."""
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.kill9()
        self._close_log()

    def _close_log(self) -> None:
        if getattr(self, "_log", None) and not self._log.closed:
            self._log.close()

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-5000:] if self.log_path.exists() else ""


def small_frames(shelf_dir, count: int = 10, step: int = 5) -> list[dict]:
    """``count`` shelf frames (every ``step``-th, read lazily: only those), at 320x240, as add_frame kwargs."""
    from canonical_core.datasets import load_tsdf_fusion

    return [frame_arrays(f, 0.5) for f in load_tsdf_fusion(shelf_dir, stride=step, max_frames=count)]


def msgpack_frame(kwargs: dict) -> dict:
    """The wire message of an add_frame kwargs dict (what the SDK sends), for tests that tamper with it."""
    from client.sdk import encode_array

    msg = {"rgb": encode_array(kwargs["rgb"]), "K": kwargs["K"].tolist(), "c2w": kwargs["c2w"].tolist()}
    if kwargs.get("depth") is not None:
        msg["depth"] = encode_array(kwargs["depth"])
    if kwargs.get("frame_id") is not None:
        msg["frame_id"] = kwargs["frame_id"]
    return msg


@contextlib.contextmanager
def in_process_server(data_dir: Path):
    """The real app (warm-up off) under uvicorn on a free loopback port, in a thread of this process,
    so that a test's patches reach it; yields its URL."""
    from server.app import create_app
    from server.protocol import HeadTimeoutH11Protocol
    from server.settings import Settings

    port = free_port()
    config = uvicorn.Config(create_app(Settings(data_dir=data_dir, warm_up=False)), host="127.0.0.1", port=port,
                            log_level="critical", http=HeadTimeoutH11Protocol)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the in-process server did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(30)


class RenderLoop:
    """``clients`` SDK clients (each with its default 429 retries) rendering session ``session_id`` at
    ``size`` (width, height: the camera of add_frame kwargs ``kwargs``, its intrinsics scaled) in a
    loop while the ``with`` block runs: the load of the fairness test and bench. ``done`` counts the
    renders answered; any other error than a retried 429 is raised when the block ends."""

    def __init__(self, url: str, session_id: str, kwargs: dict, size: tuple[int, int], clients: int,
                 token: str | None = None):
        scale = size[0] / kwargs["rgb"].shape[1]
        self.url, self.session_id, self.size, self.token = url, session_id, size, token
        self.K, self.c2w = kwargs["K"] * [[scale], [scale], [1.0]], kwargs["c2w"]
        self.done, self.errors = 0, []
        self._stop, self._lock = threading.Event(), threading.Lock()
        self._threads = [threading.Thread(target=self._loop) for _ in range(clients)]

    def __enter__(self) -> "RenderLoop":
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for t in self._threads:
            t.join()
        if self.errors:
            raise self.errors[0]

    def _loop(self) -> None:
        from client.sdk import Client, Session

        try:
            with Client(self.url, token=self.token) as client:
                session = Session(client, self.session_id, label_dim=0)
                while not self._stop.is_set():
                    view = session.render(self.K, self.c2w, *self.size)
                    assert view["rgb"].shape == (self.size[1], self.size[0], 3)
                    with self._lock:
                        self.done += 1
        except BaseException as exc:  # noqa: BLE001 - raised by __exit__
            self.errors.append(exc)


def resident_mib(pid: int, peak: bool = False) -> float:
    """Process ``pid``'s resident memory in MiB; ``peak``: its high-water mark so far (what a request
    that let its memory go again still raised)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return int(status.split("VmHWM:" if peak else "VmRSS:")[1].split()[0]) / 1024


def wait_for(condition, timeout: float = 30.0, interval: float = 0.02) -> bool:
    """Poll ``condition()`` until it is true (True) or ``timeout`` seconds pass (False): for what the
    service does off the request's path, such as a due snapshot."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(interval)
    return True


SOLVE_WAIT_S = 300.0  # a background colour solve takes seconds; the cores are shared with other test workers


def colours_solved(session, timeout: float = SOLVE_WAIT_S) -> bool:
    """Wait until ``session`` (an SDK `Session`) shows colours solved for all its frames: renders
    show the last solution, so two renders of one state are equal only once its solve has landed."""
    return wait_for(lambda: (s := session.stats())["colours_solved_frames"] == s["frames"], timeout, 0.1)


def hold_snapshot_commits(monkeypatch) -> tuple[threading.Event, threading.Event]:
    """Hold each snapshot written off the acknowledged path once its file is on disk, before its
    commit: returns (written: set then, release: set it to let the commit go on)."""
    from server import snapshots

    written, release = threading.Event(), threading.Event()
    write_atomic = snapshots.write_atomic

    def held(path, data):
        write_atomic(path, data)
        if path.name.endswith(".next"):  # the pending snapshot's file
            written.set()
            assert release.wait(60)

    monkeypatch.setattr(snapshots, "write_atomic", held)
    return written, release
