"""Start-up: the lifespan warms the kernels up (unless told not to) before it opens the sessions."""

from __future__ import annotations

import asyncio
import logging

import pytest

from server.app import create_app
from server.settings import Settings


@pytest.mark.parametrize("warm_up", [True, False])
def test_lifespan_warms_the_kernels_up_when_asked(tmp_path, caplog, warm_up):
    app = create_app(Settings(data_dir=tmp_path, warm_up=warm_up))

    async def start_and_stop():
        async with app.router.lifespan_context(app):
            pass

    with caplog.at_level(logging.INFO, logger="canonical.server"):
        asyncio.run(start_and_stop())
    messages = [r.getMessage() for r in caplog.records if r.name == "canonical.server"]
    assert any(m.startswith("serving 0 sessions") for m in messages)
    assert any(m.startswith("kernels loaded in") for m in messages) == warm_up


def test_canonical_serve_writes_the_services_own_lines_at_its_log_level(tmp_path):
    """Under `canonical serve` the service's own lines (start-up, restores, retention) come out as
    uvicorn's do, at --log-level; without a handler of their own only warnings came out, bare."""
    import os
    import subprocess
    import sys

    from client.cli.launch import free_port, wait_until_healthy

    from .harness import REPO

    port = free_port()
    with open(tmp_path / "serve.log", "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "client.cli", "serve", "--port", str(port), "--data-dir",
                                 str(tmp_path / "data"), "--log-level", "info"], cwd=REPO, stdout=out,
                                stderr=subprocess.STDOUT, env={**os.environ, "CANONICAL_WARM_UP": "false"})
        try:
            wait_until_healthy(f"http://127.0.0.1:{port}", proc, 120)
        finally:
            proc.terminate()
            proc.wait(timeout=60)
    lines = (tmp_path / "serve.log").read_text().splitlines()
    assert f"INFO:     canonical.server: serving 0 sessions from {tmp_path / 'data'}" in lines, lines
