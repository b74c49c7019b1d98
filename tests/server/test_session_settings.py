"""Session settings over a real service: the create schema is the library's public settings (groups as
objects, strict types, evaluation-only settings refused), and sessions stored with the flat settings
layout still open."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from canonical_core import Scene, SceneConfig
from canonical_core.scene import FoldReport
from server.store import SessionStore

from .harness import TOKEN

AUTH = {"Authorization": f"Bearer {TOKEN}"}
FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def create(server, body):
    return httpx.post(f"{server.url}/v1/sessions", json=body, headers=AUTH)


@pytest.mark.parametrize("body, field", [
    ({"voxel_size": 0.01, "research": {"weighting": "average"}}, "research"),
    ({"voxel_size": 0.01, "weighting": "average"}, "weighting"),
    ({"voxel_size": 0.01, "eps": 1e-6}, "eps"),
    ({"voxel_size": 0.01, "free_space_margin": 3.0}, "free_space_margin"),  # the flat layout is not the API
    ({"voxel_size": "0.01"}, "voxel_size"),
    ({"voxel_size": True}, "voxel_size"),
    ({"voxel_size": 0.01, "sh_degree": 1.0}, "sh_degree"),
    ({"voxel_size": 0.01, "depth": {"completion": 1}}, "depth.completion"),
    ({"voxel_size": 0.01, "free_space": False}, "free_space"),
    ({"voxel_size": 0.01, "free_space": {"margin": -1}}, "free_space.margin"),
    ({"voxel_size": 0.01, "free_space": {"margn": 1}}, "free_space.margn"),
    ({"voxel_size": 0.01, "depth": {"hypotheses": 513}}, "depth.hypotheses"),
    ({"voxel_size": 0.01, "decoder": {"opacity_slope": "steep"}}, "decoder.opacity_slope"),
    ({"voxel_size": 0.01, "range": {"near": 2.0, "far": 1.0}}, "range.near"),
    ({"voxel_size": 0.01, "model": "/etc/passwd"}, "model"),
    ({"voxel_size": 0.01, "model": "/tmp/trained.safetensors"}, "model"),  # the service reads no file a client names
])
def test_create_refuses_naming_the_field_and_makes_nothing(server, client, body, field):
    before = len(client.sessions())
    r = create(server, body)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["field"] == field and error["message"].startswith(f"{field}: ")
    assert len(client.sessions()) == before
    if field == "free_space_margin":  # an old flat name says where the setting is now
        assert error["message"] == "free_space_margin: unknown field (it is free_space.margin now)"


def test_a_model_other_than_default_or_none_is_refused_with_what_http_allows(server, client):
    """Any path, a checkpoint's or not, gets the one answer of what a client may choose: the library's
    own message (which offers a checkpoint path) would invite what the service then refuses."""
    before = len(client.sessions())
    messages = []
    for model in ("/etc/passwd", "/tmp/trained.safetensors"):
        r = create(server, {"voxel_size": 0.01, "model": model})
        assert r.status_code == 422, r.text
        error = r.json()["error"]
        assert error["field"] == "model" and error["message"].startswith("model: "), error
        messages.append(error["message"].replace(repr(model), "MODEL"))
    assert messages[0] == messages[1], messages
    assert "over HTTP" in messages[0] and "'default'" in messages[0] and "'none'" in messages[0], messages[0]
    assert ".safetensors" not in messages[0] and "path of" not in messages[0], messages[0]
    assert len(client.sessions()) == before


def test_create_takes_groups_and_fills_their_defaults(server, client):
    r = create(server, {"voxel_size": 0.01, "free_space": {"margin": 3}, "depth": {"sources": 3}, "max_voxels": 1000})
    assert r.status_code == 201, r.text
    config = r.json()["config"]
    expected = SceneConfig(voxel_size=0.01, free_space={"margin": 3.0}, depth={"sources": 3}, max_voxels=1000)
    assert config == expected.to_dict()
    assert client.session(r.json()["id"]).stats()["config"] == config
    client.session(r.json()["id"]).delete()


def test_openapi_schemas_are_generated_from_the_library(server):
    schemas = httpx.get(f"{server.url}/openapi.json", headers=AUTH).json()["components"]["schemas"]  # the docs need the token too
    create_schema = schemas["SessionCreate"]
    assert set(create_schema["properties"]) == set(SceneConfig.model_fields) - {"research"} | {"archive_retention"}
    assert "required" not in create_schema  # voxel_size too: the first frame chooses it
    report = schemas["FoldReportOut"]
    assert list(report["properties"]) == list(FoldReport.__dataclass_fields__)


def test_a_session_stored_with_flat_settings_opens(tmp_path):
    # a session made by the store, whose meta.json then gets the flat-layout settings of the fixture and,
    # as earlier versions wrote it, no digest of them
    flat = json.loads((FIXTURES / "session_meta_v1.json").read_text())["config"]
    store = SessionStore(tmp_path, max_sessions=2)
    store.open()
    session_id = store.create(SceneConfig(voxel_size=0.01)).id
    store.close()
    meta_path = next((tmp_path / "sessions").glob(f"{session_id}*/meta.json"))
    meta = {k: v for k, v in json.loads(meta_path.read_text()).items() if k != "config_sha256"}
    meta_path.write_text(json.dumps({**meta, "config": flat}))
    store = SessionStore(tmp_path, max_sessions=2)
    store.open()
    try:
        session = store.get(session_id)
        # the flat layout's sensor values under their family, completed by its preset (newer settings)
        assert session.config == Scene(SceneConfig.from_dict(flat)).config != SceneConfig.from_dict(flat)
        assert (session.config.free_space.enabled, session.config.colour_solve.views) == (False, 4)
        assert session.scene.config == session.config and session.scene.frames == 0
    finally:
        store.close()
