"""The cluster on a local Ray cluster (started once for this module): the same HTTP API as the
single-process service, an owner killed with SIGKILL mid-stream, eviction, and /metrics over it."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

ray = pytest.importorskip("ray")
pytest.importorskip("ray.serve")

from client.cli.launch import unclaimed_port  # noqa: E402
from client.sdk import Client  # noqa: E402
from server.cluster import serve as cluster  # noqa: E402
from server.cluster.owner import shard_of  # noqa: E402

from ..server.harness import VOXEL, ServerProcess, colours_solved  # noqa: E402
from .conftest import settings  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def cluster_url(tmp_path_factory):
    root = tmp_path_factory.mktemp("cluster")
    config = settings(root / "data", owners=2, owner_cpus=0.5, ingress_cpus=0.25, ingress_min_replicas=2,
                      ingress_max_replicas=2, host="127.0.0.1", port=unclaimed_port())
    cluster.connect(num_cpus=2)
    try:
        cluster.start(config)
        yield f"http://127.0.0.1:{config.port}", config
    finally:
        from ray import serve

        serve.shutdown()
        ray.shutdown()


@pytest.fixture(scope="module")
def single_url(tmp_path_factory):
    root = tmp_path_factory.mktemp("single")
    proc = ServerProcess(root / "data", root / "server.log", warm_up="false", snapshot_every_seconds=3600).start()
    yield proc.url
    proc.stop()


def stream(url: str, frames: list[dict], out: dict, key, statuses: list | None = None, pause: float = 0.0) -> None:
    """Create a session and fold ``frames`` into it (``pause`` s apart); ``out[key]`` = its digest (or the
    exception); ``statuses`` collects every HTTP status the client got, retried ones included."""
    try:
        with Client(url) as client:
            if statuses is not None:
                client._http.event_hooks["response"].append(lambda r: statuses.append(r.status_code))
            session = client.create_session(voxel_size=VOXEL)
            out[(key, "id")] = session.id
            for kwargs in frames:
                session.add_frame(**kwargs)
                out[(key, "acked")] = out.get((key, "acked"), 0) + 1
                time.sleep(pause)
            out[key] = session.digest()
    except Exception as exc:  # reported by the test
        out[key] = exc


def concurrently(*jobs) -> None:
    threads = [threading.Thread(target=stream, args=job) for job in jobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)


def test_two_sessions_streamed_concurrently_give_the_single_process_digests(cluster_url, single_url, frames):
    url, _ = cluster_url
    out: dict = {}
    concurrently((url, frames[:6], out, "a"), (url, frames[2:], out, "b"))
    concurrently((single_url, frames[:6], out, "ref_a"), (single_url, frames[2:], out, "ref_b"))
    for key in ("a", "b"):
        assert isinstance(out[key], dict), out[key]
        assert out[key]["sha256"] == out[f"ref_{key}"]["sha256"] and out[key]["frames"] == 6
    assert shard_of(out[("a", "id")], 2) in (0, 1)
    with Client(url) as client:
        listed = {s["id"] for s in client.sessions()}
    assert {out[("a", "id")], out[("b", "id")]} <= listed


def test_killing_an_owner_mid_stream_loses_no_acknowledged_frame(cluster_url, single_url, frames):
    url, config = cluster_url
    out: dict = {}
    statuses: list[int] = []
    worker = threading.Thread(target=stream, args=(url, frames, out, "k", statuses, 0.3))
    worker.start()
    deadline = time.monotonic() + 120
    while out.get(("k", "acked"), 0) < 3 and time.monotonic() < deadline and worker.is_alive():
        time.sleep(0.02)
    assert out.get(("k", "acked"), 0) >= 3, out
    owner = ray.get_actor(cluster.owner_name(shard_of(out[("k", "id")], 2)), namespace=config.namespace)
    killed = ray.get(owner.pid.remote())
    os.kill(killed, signal.SIGKILL)
    acked_before_kill = out[("k", "acked")]
    worker.join(300)
    assert acked_before_kill < len(frames) and ray.get(owner.pid.remote()) != killed  # it died mid-stream
    assert isinstance(out["k"], dict), out["k"]
    assert out["k"]["frames"] == len(frames)  # every acknowledged frame, and the retried one once
    assert set(statuses) <= {200, 201, 429}, statuses  # the client saw only errors it retries
    ref: dict = {}
    stream(single_url, frames, ref, "ref")
    assert out["k"]["sha256"] == ref["ref"]["sha256"]


def test_eviction_and_restore_keep_the_digest_and_png_bytes_and_metrics_count_them(cluster_url, frames):
    url, config = cluster_url
    with Client(url) as client:
        session = client.create_session(voxel_size=VOXEL)
        for kwargs in frames[:4]:
            session.add_frame(**kwargs)
        K, c2w = frames[0]["K"], frames[0]["c2w"]
        assert colours_solved(session)
        digest, png = session.digest(), session.render_png(K, c2w, 320, 240)
        owner = ray.get_actor(cluster.owner_name(shard_of(session.id, 2)), namespace=config.namespace)
        assert session.id in ray.get(owner.evict.remote(0))
        assert session.digest() == digest
        session.render_png(K, c2w, 320, 240)  # the restored session's first render queues its solve
        assert colours_solved(session) and session.render_png(K, c2w, 320, 240) == png
        text = client.metrics()
    lines = dict(line.rsplit(" ", 1) for line in text.splitlines() if not line.startswith("#"))
    shard = str(shard_of(session.id, 2))
    evictions = [v for k, v in lines.items() if k.startswith("canonical_cluster_evictions_total") and f'owner="{shard}"' in k]
    restores = [v for k, v in lines.items() if k.startswith("canonical_cluster_restores_total") and f'owner="{shard}"' in k]
    assert len(evictions) == len(restores) == 1 and int(evictions[0]) >= 1 and int(restores[0]) >= 1
    assert sum(1 for k in lines if k.startswith("canonical_cluster_sessions{")) == 2
    assert lines["canonical_cluster_owners_unreachable"] == "0"
