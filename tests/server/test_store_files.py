"""The store's start-up on folders it finds (in process, real files): leftovers of an interrupted
create or delete are cleaned up, anything that may hold frames is kept."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from canonical_core import SceneConfig
from server.framelog import StorageError
from server.session_errors import DataDirLocked
from server.store import SessionStore

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def opened(root) -> SessionStore:
    store = SessionStore(root, max_sessions=8)
    store.open()
    return store


def test_an_interrupted_delete_or_create_leaves_nothing_and_a_folder_with_data_is_kept(tmp_path):
    store = opened(tmp_path)
    kept = store.create(SceneConfig(voxel_size=0.01)).id
    store.close()
    sessions = tmp_path / "sessions"
    (sessions / ".deleted-abc").mkdir()  # a crash after the tombstone rename
    (sessions / ".deleted-abc" / "frames.log").write_bytes(b"x")
    (sessions / "half").mkdir()  # a crash before meta.json was written: an empty log only
    (sessions / "half" / "frames.log").write_bytes(b"")
    (sessions / "halfway").mkdir()  # a crash while meta.json was written: empty logs and its temporary file
    for name, data in (("frames.log", b""), ("archive.log", b""), ("meta.json.tmp", b'{"id": "hal')):
        (sessions / "halfway" / name).write_bytes(data)
    (sessions / kept / "scene.snap.tmp").write_bytes(b"\0" * 4096)  # a crash while a snapshot was written
    (sessions / "orphan").mkdir()  # meta.json lost, but a log with bytes in it: may hold frames
    (sessions / "orphan" / "frames.log").write_bytes(b"CGF1 something")
    store = opened(tmp_path)
    try:
        assert sorted(p.name for p in sessions.iterdir()) == sorted([kept, "orphan"])
        assert not list(sessions.glob("*/*.tmp"))
        assert [s.id for s in store.list()] == [kept]
        assert "meta.json is missing" in store.unavailable["orphan"]
        assert (sessions / "orphan" / "frames.log").read_bytes() == b"CGF1 something"
    finally:
        store.close()


def test_a_delete_whose_files_cannot_be_moved_changes_nothing(tmp_path, monkeypatch):
    store = opened(tmp_path)
    try:
        session = store.create(SceneConfig(voxel_size=0.01))

        def refused(*args):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr("server.store.os.replace", refused)
        with pytest.raises(StorageError, match="cannot delete its files: Permission denied"):
            store.delete(session.id)
        assert store.get(session.id) is session and not session.deleted and session.path.is_dir()
        monkeypatch.undo()
        assert store.delete(session.id) and not session.path.exists()  # and it can be deleted once it can be
    finally:
        store.close()


def test_one_store_per_directory_until_it_closes(tmp_path):
    first = opened(tmp_path)
    with pytest.raises(DataDirLocked, match="data_dir: .* in use by another server"):
        opened(tmp_path)
    first.close()
    opened(tmp_path).close()


def test_a_session_of_an_earlier_version_with_a_snapshot_opens(tmp_path):
    # meta.json without a config digest, the snapshot's settings and meta.json's in the flat layout of then
    meta = json.loads((FIXTURES / "session_meta_v1.json").read_text())
    folder = tmp_path / "sessions" / meta["id"]
    folder.mkdir(parents=True)
    shutil.copy(FIXTURES / "scene_v4.snap", folder / "scene.snap")
    flat = json.loads(np.load(folder / "scene.snap")["header"].tobytes())["config"]
    assert "free_space_margin" in flat
    (folder / "meta.json").write_text(json.dumps({**meta, "config": flat, "archive_retention": "none"}))
    (folder / "frames.log").write_bytes(b"")
    store = opened(tmp_path)
    try:
        assert store.unavailable == {}
        session = store.get(meta["id"])
        # registration_px, newer than that layout, is its sensor family's (`scene.choices`)
        then = SceneConfig.from_dict(flat).replace(sensor={"registration_px": 0.0})
        assert session.scene.frames == 2 and session.config == session.scene.config == then
    finally:
        store.close()
