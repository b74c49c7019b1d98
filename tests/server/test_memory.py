"""The service's memory: a frame is priced before it folds and refused over the budget, a session's
voxels are capped by default, and a deleted session's memory goes back to the system.

The frames are what a hostile client sends: a few kilobytes of PNG (a black image over a smooth depth
ramp) that fold into a million voxels at half-millimetre voxels. Before the budget, each such request
added hundreds of megabytes, without bound; before the memory was released, none of it came back
after DELETE.
"""

from __future__ import annotations

import io
import json

import httpx
import numpy as np
import pytest
import torch
from PIL import Image

from .harness import SOLVE_WAIT_S, ServerProcess, resident_mib, wait_for

SIDE = 1024
FINE = 0.0005  # metres: every pixel of the ramp its own voxel


def png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


RGB = png(np.zeros((SIDE, SIDE, 3), np.uint8))
RAMP = png((np.linspace(500, 3000, SIDE)[None, :] + np.linspace(0, 500, SIDE)[:, None]).astype(np.uint16))
CAMERA = json.dumps({"K": [[SIDE, 0, SIDE / 2], [0, SIDE, SIDE / 2], [0, 0, 1]], "c2w": np.eye(4).tolist(), "depth_scale": 1000})


def post_ramp(url: str, session_id: str) -> httpx.Response:
    return httpx.post(f"{url}/v1/sessions/{session_id}/frames", files={"rgb": ("c.png", RGB), "depth": ("d.png", RAMP)},
                      data={"camera": CAMERA}, timeout=300)


def create(url: str, **settings) -> httpx.Response:
    return httpx.post(f"{url}/v1/sessions", json={"voxel_size": FINE, **settings}, timeout=60)


def ramp_cost() -> int:
    """The library's price of one ramp frame (`fold_cost`): the worst case a fold reserves."""
    import torch

    from canonical_core import Camera, Frame, Scene, SceneConfig
    from canonical_core.scene.folding import fold_cost

    depth = np.asarray(Image.open(io.BytesIO(RAMP)), np.float32) / 1000
    K = np.array(json.loads(CAMERA)["K"])
    frame = Frame(rgb=torch.zeros(SIDE, SIDE, 3, dtype=torch.uint8), camera=Camera(K, np.eye(4), SIDE, SIDE),
                  depth=torch.from_numpy(depth))
    scene = Scene(SceneConfig(voxel_size=FINE))
    scene.keep_undo(4)  # as a session with a frame archive does
    return fold_cost(scene, frame)


@pytest.fixture(scope="module")
def budgeted(tmp_path_factory):
    """A service whose memory budget takes two of the ramp frames but not a third: a fold reserves its
    worst case (one ramp's price), and a folded ramp holds less than half of it, so the second fits
    beside the first and the third does not beside both. Its sessions hold at most 3 million voxels."""
    root = tmp_path_factory.mktemp("memory")
    proc = ServerProcess(root / "data", root / "server.log", memory_budget_bytes=int(1.7 * ramp_cost()),
                         max_session_voxels=3_000_000).start()
    yield proc
    proc.stop()


def test_a_frame_past_the_budget_is_refused_before_it_folds_and_a_delete_gives_room_back(budgeted):
    url = budgeted.url
    ids = [create(url).json()["id"] for _ in range(3)]
    folded = [post_ramp(url, i) for i in ids]
    assert [r.status_code for r in folded[:2]] == [200, 200]
    refused = folded[2]
    assert refused.status_code == 413, refused.text
    error = refused.json()["error"]
    assert error["field"] == "frame" and "CANONICAL_MEMORY_BUDGET_BYTES" in error["message"]
    stats = httpx.get(f"{url}/v1/sessions/{ids[2]}", timeout=60).json()
    assert (stats["frames"], stats["voxels"]) == (0, 0)  # nothing folded, nothing logged
    httpx.delete(f"{url}/v1/sessions/{ids[0]}", timeout=60)
    assert post_ramp(url, ids[2]).status_code == 200  # the deleted session's share is free again
    for i in ids[1:]:
        httpx.delete(f"{url}/v1/sessions/{i}", timeout=60)


def test_sessions_hold_at_most_the_services_voxels(budgeted):
    r = create(budgeted.url)
    assert r.status_code == 201 and r.json()["config"]["max_voxels"] == 3_000_000
    httpx.delete(f"{budgeted.url}/v1/sessions/{r.json()['id']}", timeout=60)
    assert create(budgeted.url, max_voxels=1000).json()["config"]["max_voxels"] == 1000
    r = create(budgeted.url, max_voxels=3_000_001)
    assert r.status_code == 422 and r.json()["error"]["field"] == "max_voxels"
    assert "CANONICAL_MAX_SESSION_VOXELS" in r.json()["error"]["message"]


def test_a_deleted_sessions_memory_goes_back_to_the_system(tmp_path):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", warm_up="false").start()
    try:
        ids = [create(proc.url).json()["id"] for _ in range(2)]
        start = resident_mib(proc.proc.pid)
        assert all(post_ramp(proc.url, i).status_code == 200 for i in ids)
        peak = resident_mib(proc.proc.pid)
        assert peak - start > 400  # two million voxels
        for i in ids:
            assert httpx.delete(f"{proc.url}/v1/sessions/{i}", timeout=60).status_code == 200
        # a background colour solve that was running works on its own copy of the state until it ends
        # (its first steps load kernels, which on a loaded machine can keep a request waiting for seconds)
        assert wait_for(lambda: "canonical_colour_solves_running 0" in httpx.get(f"{proc.url}/metrics", timeout=60).text,
                        SOLVE_WAIT_S)
        after = resident_mib(proc.proc.pid)
        assert after - start < (peak - start) / 4, (start, peak, after)
    finally:
        proc.stop()


def test_the_memory_of_large_views_goes_back_to_the_system_once_they_are_answered(tmp_path):
    """Renders of 7 MP work in arrays of hundreds of megabytes that glibc would keep in its heap
    after the answer: a service that draws a few such views a minute would hold gigabytes."""
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", warm_up="false").start()
    try:
        session = create(proc.url, voxel_size=0.004).json()["id"]
        assert post_ramp(proc.url, session).status_code == 200
        view = {"pose": ",".join(map(str, np.eye(4).ravel())), "width": 3240, "height": 2160,
                "K": f"{3 * SIDE},{3 * SIDE},1620,1080"}

        def draw() -> None:
            r = httpx.get(f"{proc.url}/v1/sessions/{session}/render", params=view, timeout=300)
            assert r.status_code == 200, r.text

        draw()  # the first loads what every later one uses
        before = resident_mib(proc.proc.pid)
        for _ in range(4):
            draw()
        assert resident_mib(proc.proc.pid) - before < 100, before  # 470 MB more without giving it back
    finally:
        proc.stop()


def bomb(side: int) -> bytes:
    """A frame of a few kilobytes whose arrays decode to ``side``² x 7 bytes (zstd of zeros: no depth
    anywhere, so its fold adds nothing)."""
    import msgpack

    from canonical_wire import encode_array

    K = [[side, 0, side / 2], [0, side, side / 2], [0, 0, 1]]
    return msgpack.packb({"rgb": encode_array(np.zeros((side, side, 3), np.uint8), codec="zstd"),
                          "depth": encode_array(np.zeros((side, side), np.float32), codec="zstd"),
                          "K": K, "c2w": np.eye(4).tolist()}, use_bin_type=True)


def test_decoded_frames_are_held_from_the_budget_until_answered(tmp_path):
    """Numbered frames wait decoded for their turn: what their arrays hold counts against the memory
    budget from their decode on, so a few compressed kilobytes cannot make the service hold gigabytes.
    One that does not fit beside those waiting now is 429 (sent again, it is taken once they folded)."""
    from concurrent.futures import ThreadPoolExecutor

    side, decoded = 2048, 2048 * 2048 * 7  # 28 MiB a frame once decoded
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", warm_up="false",
                         memory_budget_bytes=int(2.5 * decoded), frame_order_wait_s=60).start()
    try:
        sid = create(proc.url, voxel_size=0.05).json()["id"]
        url, body = f"{proc.url}/v1/sessions/{sid}/frames", bomb(side)

        def post(index: int, data: bytes = body) -> httpx.Response:
            return httpx.post(url, content=data, timeout=120,
                              headers={"content-type": "application/msgpack", "Frame-Index": str(index)})

        def held() -> float:
            lines = httpx.get(f"{proc.url}/metrics", timeout=60).text.splitlines()
            return next(float(line.split()[1]) for line in lines if line.startswith("canonical_memory_held_bytes "))

        with ThreadPoolExecutor(2) as pool:
            waiting = [pool.submit(post, i) for i in (1, 2)]  # decoded, held while frame 0 has not come
            assert wait_for(lambda: held() == 2 * decoded, 60)
            refused = post(3)
            error = refused.json()["error"]
            assert refused.status_code == 429 and refused.headers["retry-after"] == "1", refused.text
            assert error["field"] == "frame" and "CANONICAL_MEMORY_BUDGET_BYTES" in error["message"], error
            assert post(0, bomb(64)).status_code == 200  # frame 0: the two waiting fold after it
            assert [f.result().status_code for f in waiting] == [200, 200]
        assert post(3).status_code == 200  # their share given back: taken now, in its place
        assert httpx.get(f"{proc.url}/v1/sessions/{sid}", timeout=60).json()["frames"] == 4
    finally:
        proc.stop()


def test_the_budget_tells_a_frame_that_never_fits_from_one_that_fits_once_others_are_done():
    """413 (`MemoryBudgetExceeded`) only when the sessions' memory leaves too little; when what folds
    and decoded frames hold for moments does, 429 (`MemoryBudgetBusy`): the client sends it again."""
    from server.memory import MemoryBudget
    from server.session_errors import MemoryBudgetBusy, MemoryBudgetExceeded

    budget = MemoryBudget(100, lambda: 40)
    with budget.reserve(50):
        with pytest.raises(MemoryBudgetBusy, match="has 10 bytes left, beside 50 bytes"):
            budget.take(30)
        with pytest.raises(MemoryBudgetExceeded, match="has 10 bytes left$"):
            budget.take(61)
    budget.take(30)  # the fold's share given back: it fits
    assert budget.reserved == 30


def test_a_fold_is_never_refused_for_the_decoded_frames_that_wait_for_it():
    """The numbered frames after a frame, and its own arrays, hold their decoded bytes until it has
    folded: were its fold weighed against them, it would be refused every time it was sent again and
    they would wait for it until refused too. The decoded frames give way to the folds instead; and a
    hold whose request was dropped unreleased (cancelled while a worker decoded it) gives its bytes back."""
    import gc

    from server.memory import DecodedHold, MemoryBudget
    from server.session_errors import MemoryBudgetBusy

    budget = MemoryBudget(100, lambda: 0)
    budget.take(60, decoded=True)  # frames waiting for the next one's fold
    with budget.reserve(40):  # that fold: taken
        with pytest.raises(MemoryBudgetBusy):
            budget.take(1, decoded=True)  # another decoded frame waits for room instead
    budget.give(60, decoded=True)

    class Frame:
        rgb, depth, depth_std, features, labels = torch.zeros(10, dtype=torch.uint8), None, None, None, None

    held = DecodedHold(budget, Frame())
    assert budget.decoded == 10
    del held
    gc.collect()
    assert budget.decoded == 0
