"""Fixtures of the service tests: one shared service (token on) and reference digests."""

from __future__ import annotations

import pytest

from client.sdk import Client

from .harness import TOKEN, VOXEL, ServerProcess, small_frames


@pytest.fixture(scope="session")
def frames(shelf_dir) -> list[dict]:
    """10 real shelf frames (every 5th) at 320x240 (the full-size frames of ``shelf_frames``, read lazily)."""
    return small_frames(shelf_dir)


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    """The service most tests share: token required, 4 MiB bodies, 640x480 images, no timed snapshots."""
    root = tmp_path_factory.mktemp("shared_server")
    proc = ServerProcess(root / "data", root / "server.log", token=TOKEN, max_body_bytes=4 * 1024 * 1024,
                         max_image_pixels=640 * 480, snapshot_every_seconds=3600, snapshot_every_frames=1000,
                         max_sessions=20)
    proc.start()
    yield proc
    proc.stop()


@pytest.fixture(scope="session")
def client(server):
    with Client(server.url, token=TOKEN) as c:
        yield c


@pytest.fixture(scope="session")
def reference(client, frames) -> list[dict]:
    """Digests of one uninterrupted, sequential run: reference[k] is the state after frames[:k]."""
    session = client.create_session(voxel_size=VOXEL)
    digests = [session.digest()]
    for kwargs in frames:
        session.add_frame(**kwargs)
        digests.append(session.digest())
    return digests
