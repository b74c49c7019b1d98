"""Fairness under load, against a real service with its default settings: ten clients looping large
renders of one session neither refuse nor reorder another session's frames, and the web viewer's
pictures of the busy session coalesce (a newer one replaces a waiting one: 204) instead of queueing.

Latency under this load is measured by ``bench/fairness.py``, not asserted here.
"""

from __future__ import annotations

import re
import threading

import httpx
import numpy as np
import pytest

from client.sdk import Client, Session

from .harness import TOKEN, VOXEL, RenderLoop, ServerProcess, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]
AUTH = {"Authorization": f"Bearer {TOKEN}"}
CLIENTS, LARGE = 10, (1280, 960)  # four times a 640x480 frame's pixels


def responses(url: str, status: int) -> int:
    """How many ``status`` answers the service gave since it started (its /metrics)."""
    text = httpx.get(f"{url}/metrics", headers=AUTH).text
    found = re.search(rf'^canonical_http_responses_total{{status="{status}"}} (\d+)$', text, re.M)
    return int(found.group(1)) if found else 0


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """The service as `canonical serve` starts it (default queue and workers), with a token."""
    root = tmp_path_factory.mktemp("fairness")
    proc = ServerProcess(root / "data", root / "server.log", token=TOKEN)
    proc.start()
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def busy(service, frames) -> Session:
    """Session A, which the looping renders draw: the shelf frames folded."""
    with Client(service.url, token=TOKEN) as client:
        session = client.create_session(voxel_size=VOXEL)
        for kwargs in frames:
            session.add_frame(**kwargs)
    return session


def test_another_sessions_frames_are_all_taken_during_ten_looping_large_renders(service, busy, frames):
    refused_before = responses(service.url, 429)
    with Client(service.url, token=TOKEN, max_retries=0) as client:  # a 429 would raise: none is retried
        other = client.create_session(voxel_size=VOXEL)
        with RenderLoop(service.url, busy.id, frames[0], LARGE, CLIENTS, TOKEN):
            # ten clients, a queue of eight: the busy session's is full once the service refuses a render
            assert wait_for(lambda: responses(service.url, 429) > refused_before, timeout=120)
            reports = [other.add_frame(**kwargs) for kwargs in frames]  # CanonicalError on any refusal
        assert [r["frame_index"] for r in reports] == list(range(len(frames)))
        # folded in order and whole: the same state as the same frames folded with nothing else running
        quiet = client.create_session(voxel_size=VOXEL)
        for kwargs in frames:
            quiet.add_frame(**kwargs)
        assert other.digest()["sha256"] == quiet.digest()["sha256"]
        for session in (other, quiet):
            session.delete()


def test_the_viewers_pictures_of_a_busy_session_coalesce(service, busy, frames):
    kwargs = frames[-1]
    K, c2w = kwargs["K"], kwargs["c2w"]
    query = {"pose": ",".join(map(str, np.asarray(c2w).ravel())), "K": f"{K[0][0]},{K[1][1]},{K[0][2]},{K[1][2]}",
             "width": 160, "height": 120}
    answers: dict[str, list[httpx.Response]] = {"page 1": [], "page 2": []}

    def ask(page: str) -> None:
        r = httpx.get(f"{service.url}/v1/sessions/{busy.id}/image", params=query, timeout=120,
                      headers={**AUTH, "X-Canonical-Viewer": page})
        answers[page].append(r)

    with RenderLoop(service.url, busy.id, frames[0], LARGE, CLIENTS, TOKEN) as load:
        assert wait_for(lambda: load.done > 0, timeout=120)  # the renders' queue is full: pictures wait
        pictures = [threading.Thread(target=ask, args=("page 1",)) for _ in range(5)]
        pictures.append(threading.Thread(target=ask, args=("page 2",)))
        for t in pictures:
            t.start()
        for t in pictures:
            t.join()
    # a picture that waited while a newer one of the same page came was answered at once, empty
    page1 = answers["page 1"]
    superseded = [r for r in page1 if r.status_code == 204]
    assert len(page1) == 5 and {r.status_code for r in page1} == {200, 204}
    assert all(r.headers["X-Canonical-Superseded"] == "true" and not r.content for r in superseded)
    # another page's picture is its own: never replaced by page 1's
    assert [r.status_code for r in answers["page 2"]] == [200]
    assert all(r.headers["content-type"] == "image/png" for r in page1 + answers["page 2"] if r.status_code == 200)
