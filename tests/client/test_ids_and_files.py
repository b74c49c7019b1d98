"""What the SDK puts into a request's path (ids escaped whole, never resolved as dot segments) and
how the SDK and the CLI write files (no temporary file left by a failed write, errors naming the path given)."""

from __future__ import annotations

import httpx
import pytest

from client.sdk import CanonicalError, Client, Session
from tests.client.test_cli_errors import assert_one_line_error, canonical


@pytest.fixture
def sent_paths():
    """A client whose requests are recorded (their raw paths) and answered 200 {} without a service."""
    paths: list[bytes] = []

    def answer(request: httpx.Request) -> httpx.Response:
        paths.append(request.url.raw_path)
        return httpx.Response(200, json={"label_dim": 0, "state": "done", "id": "x"})

    client = Client("http://service")
    client._http = httpx.Client(base_url="http://service", transport=httpx.MockTransport(answer))
    yield client, paths
    client.close()


def test_ids_travel_as_one_path_segment_dot_segments_included(sent_paths):
    client, paths = sent_paths
    session = Session(client, "s1")
    session.remove_frame("..")  # resolved as a dot segment, this would be DELETE of the session itself
    session.remove_frame(".")
    session.remove_frame("a/b?c")
    session.correction("..")
    client.session("../sessions")
    Session(client, "..").stats()
    assert paths == [b"/v1/sessions/s1/frames/%2E%2E", b"/v1/sessions/s1/frames/%2E", b"/v1/sessions/s1/frames/a%2Fb%3Fc",
                     b"/v1/sessions/s1/corrections/%2E%2E", b"/v1/sessions/..%2Fsessions", b"/v1/sessions/%2E%2E"]
    with pytest.raises(ValueError, match="session_id: expected an id, got an empty string"):
        client.session("")
    with pytest.raises(ValueError, match="frame_id: expected an id"):
        session.remove_frame("")
    assert len(paths) == 6  # refused before anything was sent


def test_removing_frame_dot_dot_leaves_the_session_whole(server, frames):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=0.02)
        for frame in frames[:2]:
            session.add_frame(**frame)
        for key in ("..", "."):
            with pytest.raises(CanonicalError) as err:  # no frame has that key: the frame route says so
                session.remove_frame(key)
            assert err.value.status != 405, err.value
        assert session.stats()["frames"] == 2


def test_an_empty_session_id_is_a_usage_error_naming_session(server):
    for command in (["view", "--no-browser"], ["export", "-o", "a.ply"], ["poses", "--remove", "0"]):
        assert_one_line_error(canonical(*command, "--url", server.url, "--session", ""), 2, "--session", "expected a session id")


@pytest.fixture(scope="module")
def session_id(server, frames):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=0.02)
        for frame in frames[:2]:
            session.add_frame(**frame)
        return session.id


def test_a_failed_download_leaves_no_part_file_and_names_the_path_given(server, session_id, tmp_path):
    (tmp_path / "adir.ply").mkdir()
    with Client(server.url) as client:
        with pytest.raises(IsADirectoryError) as err:
            client.session(session_id).export_ply(tmp_path / "adir.ply")
    assert err.value.filename == str(tmp_path / "adir.ply")
    exported = canonical("export", "--url", server.url, "--session", session_id, "-o", str(tmp_path / "adir.ply"),
                         "--wait-solved", "0")
    assert_one_line_error(exported, 1, f"-o: cannot write {tmp_path / 'adir.ply'}: Is a directory")
    assert ".part" not in exported.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir.ply"]


def test_export_creates_missing_folders_as_render_does(server, session_id, tmp_path):
    out = tmp_path / "new" / "folder" / "scene.ply"
    exported = canonical("export", "--url", server.url, "--session", session_id, "-o", str(out), "--wait-solved", "0")
    assert exported.returncode == 0 and exported.stdout == f"{out}\n", exported.stderr
    assert out.read_bytes().startswith(b"ply\n")
