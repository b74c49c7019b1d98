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
