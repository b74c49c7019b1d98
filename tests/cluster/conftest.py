"""Fixtures of the cluster tests: real shelf frames, and the cluster's parts in this process (owners
called directly, the ingress app through httpx's ASGI transport); `test_serve.py` runs them on Ray,
`test_failover.py` runs `canonical serve --cluster` itself."""

from __future__ import annotations

import asyncio
import shutil
import tempfile

import httpx
import pytest

from canonical_core import Scene, SceneConfig
from canonical_wire import pack
from server import wire

from ..server.harness import VOXEL, msgpack_frame, small_frames

MSGPACK = {"Content-Type": "application/msgpack"}


@pytest.fixture(scope="session")
def frames(shelf_dir) -> list[dict]:
    """8 real shelf frames (every 5th) at 320x240, each with a frame_id."""
    return small_frames(shelf_dir, count=8)


@pytest.fixture(scope="module")
def ray_tmpdir() -> str:
    """A folder for the files of a Ray cluster that a test's service starts (its RAY_TMPDIR), removed
    after the module: short, as Ray's socket paths under it must fit in 107 bytes."""
    path = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    yield path
    shutil.rmtree(path, ignore_errors=True)


def frame_body(kwargs: dict) -> bytes:
    return pack(msgpack_frame(kwargs))


def reference_digest(frames: list[dict]) -> str:
    """The library's digest of ``frames`` folded in order (what every service's session must equal)."""
    scene = Scene(SceneConfig(voxel_size=VOXEL))
    for kwargs in frames:
        scene.fold(wire.frame_from_message(wire.unpack(frame_body(kwargs))))
    return scene.digest()


def settings(data_dir, **overrides):
    from server.cluster.settings import ClusterSettings

    return ClusterSettings(data_dir=data_dir, warm_up=False, threads=1, snapshot_every_seconds=3600,
                           snapshot_every_frames=1000, **overrides)


def run(coro):
    return asyncio.run(coro)


async def request(owner, method: str, path: str, body: bytes = b"", headers: dict | None = None, query: bytes = b""):
    """One request through an owner's `handle` (as the ingress forwards it): (status, JSON or bytes)."""
    raw = [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    status, out, content = await owner.handle(method, path, query, raw, body)
    kind = dict(out).get(b"content-type", b"")
    return status, httpx.Response(status, content=content).json() if kind.startswith(b"application/json") else content


__all__ = ["MSGPACK", "VOXEL", "frame_body", "frames", "ray_tmpdir", "reference_digest", "request", "run", "settings"]
