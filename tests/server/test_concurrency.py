"""Concurrency: two sessions folded from two client threads while a third renders both; no errors and
the final states equal sequential runs."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from client.sdk import Client

from .harness import TOKEN, VOXEL

pytestmark = [pytest.mark.slow, pytest.mark.realdata]


def test_two_sessions_folding_while_rendering(server, client, frames, reference):
    a = client.create_session(voxel_size=VOXEL)
    b = client.create_session(voxel_size=VOXEL)
    b_frames = frames[::-1][:6]  # another order, so the two sessions differ
    errors: list[BaseException] = []
    renders = {"a": 0, "b": 0}
    rendering, done = threading.Event(), threading.Event()

    def fold(session_id: str, sequence: list[dict]) -> None:
        try:
            with Client(server.url, token=TOKEN) as c:  # one client (connection pool) per thread
                session = c.session(session_id)
                for i, kwargs in enumerate(sequence):
                    assert session.add_frame(**kwargs)["frame_index"] == i
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    def render() -> None:
        try:
            with Client(server.url, token=TOKEN) as c:
                sessions = {"a": c.session(a.id), "b": c.session(b.id)}
                kwargs = frames[0]
                h, w = kwargs["rgb"].shape[:2]
                while not done.is_set():
                    for name, session in sessions.items():
                        view = session.render(kwargs["K"], kwargs["c2w"], w, h)
                        assert view["rgb"].shape == (h, w, 3) and np.isfinite(view["depth"]).all()
                        stats = session.stats()
                        assert stats["gaussians"] <= stats["voxels"]
                        renders[name] += 1
                    rendering.set()  # the folds start once both sessions were rendered: they overlap
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)
        finally:
            rendering.set()

    threads = [threading.Thread(target=fold, args=(a.id, frames[:6])), threading.Thread(target=fold, args=(b.id, b_frames))]
    viewer = threading.Thread(target=render)
    viewer.start()
    assert rendering.wait(120)
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    done.set()
    viewer.join()
    assert not errors, errors
    assert renders["a"] > 1 and renders["b"] > 1  # a round before the folds, at least one beside them

    assert a.digest()["sha256"] == reference[6]["sha256"]  # == frames[:6] folded alone, in order
    sequential = client.create_session(voxel_size=VOXEL)
    for kwargs in b_frames:
        sequential.add_frame(**kwargs)
    assert b.digest()["sha256"] == sequential.digest()["sha256"]
    for s in (a, b, sequential):
        s.delete()
