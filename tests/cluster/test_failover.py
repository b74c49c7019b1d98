"""`canonical serve --cluster` as a user starts it: a subprocess with the CLI's defaults (2 owners, their
CPUs fitted to this machine, 1 to 4 ingress replicas) on the local Ray cluster it starts itself, once for
this module. Every owner is placed; SIGKILL of the ingress replica, of a session's owner, or of both,
mid-stream, loses no acknowledged frame: the session's digest equals the library's fold of its frames.
Each kill prints the time until the session answered again (``pytest -s``; docs/reliability.md)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import psutil
import pytest

pytest.importorskip("ray.serve")

from client.cli.launch import unclaimed_port, wait_until_healthy  # noqa: E402
from client.sdk import CanonicalError, Client  # noqa: E402
from server.cluster.lease import EPOCH  # noqa: E402
from server.cluster.owner import shard_of  # noqa: E402

from ..server.harness import REPO, VOXEL  # noqa: E402
from .conftest import reference_digest  # noqa: E402

pytestmark = pytest.mark.slow

# Ray names an actor's process after its class ("ray::Class", then ".method" while one runs)
OWNER, INGRESS = "ray::SessionOwner", "ray::ServeReplica:canonical:Ingress"


@dataclass
class Cluster:
    url: str
    proc: subprocess.Popen
    data_dir: Path
    log: Path

    def actors(self, title: str) -> list:
        """The live processes below the service's own that run Ray actors of class ``title``."""
        return [p for p in psutil.Process(self.proc.pid).children(recursive=True)
                if alive(p, lambda: p.cmdline()[:1] and p.cmdline()[0].startswith(title))]

    def owner_of(self, session_id: str):
        """The owner process holding the session's lease (its ``owner.epoch`` open): the session's owner."""
        lease = os.path.realpath(self.data_dir / "sessions" / session_id / EPOCH)
        holders = [p for p in self.actors(OWNER) if alive(p, lambda: any(f.path == lease for f in p.open_files()))]
        assert len(holders) == 1, (session_id, holders)
        return holders[0]


def alive(process, condition) -> bool:
    """Whether ``process`` runs and ``condition()`` holds for it (False once it exited)."""
    try:
        return process.status() != psutil.STATUS_ZOMBIE and bool(condition())
    except psutil.Error:
        return False


def stop(proc: subprocess.Popen, timeout: float) -> list:
    """SIGTERM the service, then SIGKILL what of it and its Ray cluster is left after ``timeout`` s; the
    processes that were left."""
    below = psutil.Process(proc.pid).children(recursive=True) if proc.poll() is None else []
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    _, left = psutil.wait_procs(below, timeout=30)
    for p in left:
        p.kill()
    return left


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, ray_tmpdir):
    root = tmp_path_factory.mktemp("failover")
    port, log = unclaimed_port(), root / "serve.log"
    # the CLI's defaults, and a local cluster of its own (RAY_ADDRESS would make it join another)
    env = {k: v for k, v in os.environ.items() if not k.startswith("CANONICAL_") and k != "RAY_ADDRESS"}
    env["RAY_TMPDIR"] = ray_tmpdir  # this cluster's files apart from any other Ray cluster on the machine
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "client.cli", "serve", "--cluster", "--port", str(port),
                                 "--data-dir", str(root / "data")], cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_healthy(url, proc, 600)  # minutes only on a cold numba cache: each owner compiles
        yield Cluster(url, proc, root / "data", log)
    except RuntimeError as exc:
        raise RuntimeError(f"{exc}:\n{log.read_text(errors='replace')[-5000:]}") from None
    finally:
        stop(proc, 60)


@pytest.fixture(scope="module")
def reference(frames) -> str:
    return reference_digest(frames)


class Stream(threading.Thread):
    """A client streaming ``frames`` into a new session back to back, as a robot does. A 429 is retried
    by the SDK; a 500 from Serve's proxy (its request was in flight in an ingress replica that died, so
    its outcome is unknown) is retried once with the same ``frame_id``, which the owner recognises if it
    folded the frame already. It pauses just before it sends frame ``hold`` (from 0) until ``go`` is set."""

    def __init__(self, url: str, frames: list[dict], hold: int):
        super().__init__(daemon=True)
        self.url, self.frames, self.hold = url, frames, hold
        self.acked: list[float] = []  # when each frame was acknowledged (time.monotonic)
        self.statuses: list[int] = []  # every answer the client got, retried ones included
        self.paused, self.go = threading.Event(), threading.Event()
        self.session_id = self.digest = self.error = None

    def _sending(self, request) -> None:
        if request.url.path.endswith("/frames") and len(self.acked) == self.hold and not self.go.is_set():
            self.paused.set()
            self.go.wait(120)

    def run(self) -> None:
        try:
            with Client(self.url) as client:
                client._http.event_hooks["request"].append(self._sending)
                client._http.event_hooks["response"].append(lambda r: self.statuses.append(r.status_code))
                session = client.create_session(voxel_size=VOXEL)
                self.session_id = session.id
                for kwargs in self.frames:
                    try:
                        session.add_frame(**kwargs)
                    except CanonicalError as exc:
                        if exc.status != 500:
                            raise
                        session.add_frame(**kwargs)
                    self.acked.append(time.monotonic())
                self.digest = session.digest()
        except Exception as exc:  # reported by the test
            self.error = exc


def test_the_defaults_place_every_owner_and_sessions_created_in_a_row_all_answer(cluster, frames):
    owners = cluster.actors(OWNER)
    assert len(owners) == 2  # before the claims were fitted, the second owner could never be placed
    statuses: list[int] = []
    with Client(cluster.url) as client:
        client._http.event_hooks["response"].append(lambda r: statuses.append(r.status_code))
        sessions = []
        while len(sessions) < 40 and min(sum(shard_of(s.id, 2) == k for s in sessions) for k in (0, 1)) < 3:
            sessions.append(client.create_session(voxel_size=VOXEL))
        for session in sessions:
            assert session.add_frame(**frames[0])["frame_index"] == 0
    assert set(statuses) == {200, 201}, statuses  # not one 429: every session's owner was running
    assert {cluster.owner_of(s.id).pid for s in sessions} == {p.pid for p in owners}


@pytest.mark.parametrize("victims", [(INGRESS,), (OWNER,), (INGRESS, OWNER)], ids=["ingress", "owner", "both"])
def test_sigkill_mid_stream_the_service_answers_again_with_every_frame(cluster, frames, reference, victims):
    stream = Stream(cluster.url, frames, hold=4)
    stream.start()
    assert stream.paused.wait(120), (stream.error, stream.statuses)  # frames 0-3 acknowledged
    assert len(cluster.actors(INGRESS)) == 1  # the default: one replica, so killing it stops the ingress
    killed = {title: (cluster.owner_of(stream.session_id) if title == OWNER else cluster.actors(INGRESS)[0]).pid
              for title in victims}
    stream.go.set()
    killed_at = time.monotonic()  # as frame 4 leaves: the kill lands before it arrives or while it is served
    for pid in killed.values():
        os.kill(pid, signal.SIGKILL)
    stream.join(300)
    assert stream.error is None and not stream.is_alive(), (stream.error, stream.statuses)
    answered = next(t for t in stream.acked if t > killed_at) - killed_at
    print(f"\nfailover, SIGKILL of {' and '.join(killed)}: the session answered again after {answered:.1f} s "
          f"(answers: {stream.statuses})")
    assert stream.digest["frames"] == len(frames) and stream.digest["sha256"] == reference
    allowed = {200, 201, 429} | ({500} if INGRESS in killed else set())  # 500: Serve's, for the request in flight
    assert set(stream.statuses) <= allowed and stream.statuses.count(500) <= 1, stream.statuses
    if OWNER in killed:
        assert cluster.owner_of(stream.session_id).pid != killed[OWNER]  # restarted, and took the lease back
    assert len(cluster.actors(OWNER)) == 2 and len(cluster.actors(INGRESS)) == 1
    assert cluster.actors(INGRESS)[0].pid != killed.get(INGRESS)


def test_sigterm_stops_the_service_and_the_ray_cluster_it_started(cluster):
    """Last in this module: it stops the module's service."""
    assert stop(cluster.proc, 120) == [] and cluster.proc.returncode == 0, cluster.log.read_text(errors="replace")[-3000:]
