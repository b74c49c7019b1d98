"""An internal error on a real (in-process) uvicorn server: a 500 in the error shape, counted in /metrics."""

from __future__ import annotations

import httpx
import pytest

from .harness import in_process_server


@pytest.fixture
def served(tmp_path, monkeypatch):
    """The real app under uvicorn in a thread, with the renderer replaced by one that raises."""
    import server.routes.views as views

    def broken_render(*args, **kwargs):
        raise RuntimeError("renderer exploded")

    monkeypatch.setattr(views, "render", broken_render)
    with in_process_server(tmp_path / "data") as url:
        yield url


def _count(metrics: str, status: int) -> int:
    line = next((l for l in metrics.splitlines() if l.startswith(f'canonical_http_responses_total{{status="{status}"}}')), None)
    return 0 if line is None else int(line.split()[-1])


def test_unhandled_errors_are_500s_counted_in_metrics(served):
    session = httpx.post(f"{served}/v1/sessions", json={"voxel_size": 0.02}).json()["id"]
    assert _count(httpx.get(f"{served}/metrics").text, 500) == 0
    view = {"K": [[30, 0, 15.5], [0, 30, 11.5], [0, 0, 1]], "c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
            "width": 32, "height": 24}
    for _ in range(2):
        r = httpx.post(f"{served}/v1/sessions/{session}/render", json=view)
        assert r.status_code == 500
        assert r.json()["error"]["code"] == "internal" and "RuntimeError" in r.json()["error"]["message"]
    metrics = httpx.get(f"{served}/metrics").text
    assert _count(metrics, 500) == 2 and _count(metrics, 201) == 1
