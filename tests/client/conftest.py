"""Fixtures of the client tests: a service with a one-job queue (so bursts get 429), no token."""

from __future__ import annotations

import pytest

from tests.server.harness import ServerProcess, small_frames


@pytest.fixture(scope="session")
def frames(shelf_dir) -> list[dict]:
    return small_frames(shelf_dir, count=4, step=10)


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("client_server")
    proc = ServerProcess(root / "data", root / "server.log", queue_limit=1, snapshot_every_seconds=3600)
    proc.start()
    yield proc
    proc.stop()
