"""What a request costs besides its work, on a real (in-process) uvicorn server."""

from __future__ import annotations

import fastapi.dependencies.utils as dependency_solver
import httpx
import numpy as np

from client.sdk import Client

from .harness import in_process_server


def test_dependencies_resolve_on_the_event_loop_without_a_thread_hop(tmp_path, monkeypatch, frames):
    """FastAPI runs a plain-function dependency on its threadpool: a hop per dependency and request,
    which the acknowledged path of every fold would pay. The service's dependencies are coroutines."""
    hops = []
    run_in_threadpool = dependency_solver.run_in_threadpool

    async def counting(fn, *args, **kwargs):
        hops.append(getattr(fn, "__name__", repr(fn)))
        return await run_in_threadpool(fn, *args, **kwargs)

    monkeypatch.setattr(dependency_solver, "run_in_threadpool", counting)
    with in_process_server(tmp_path / "data") as url, Client(url) as client:
        session = client.create_session(voxel_size=0.02)
        report = session.add_frame(**frames[0])  # session, settings, jobs and metrics
        assert report["frame_index"] == 0
        stats = session.stats()
        assert stats["frames"] == 1
        K, c2w = np.asarray(frames[0]["K"]), np.asarray(frames[0]["c2w"])
        height, width = frames[0]["rgb"].shape[:2]
        view = {"pose": ",".join(map(str, c2w.reshape(-1))), "K": f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
                "width": width, "height": height}
        r = httpx.get(f"{url}/v1/sessions/{session.id}/render", params=view)  # the view from its query, too
        assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    assert hops == []
