"""The frame archive on real files: lossless compression, replay of frames and corrections on open,
a torn tail cut, damage refused, and the start-up reconciliation with the scene's frame count."""

from __future__ import annotations

import hashlib
import re
import zlib

import numpy as np
import pytest
import torch
import xxhash

from canonical_wire import encode_array, pack
from server.archive import ARCHIVE, SessionArchive
from server.payloads import DamagedFrame, compress_payload, decompress_message
from server.digests import names_payload, payload_digest
from server.wire import encode_png, frame_from_message


def message(k: int, frame_id: str | None = None) -> dict:
    rng = np.random.default_rng(k)
    c2w = np.eye(4)
    c2w[0, 3] = 0.1 * k
    msg = {"rgb": encode_array(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)),
           "K": [[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]], "c2w": c2w.tolist(),
           "depth": encode_array(rng.uniform(0.5, 2.0, (12, 16)).astype(np.float32))}
    return msg | ({"frame_id": frame_id} if frame_id else {})


def archive_of(tmp_path, n: int, retention="all") -> SessionArchive:
    archive = SessionArchive(tmp_path / ARCHIVE, retention)
    for k in range(n):
        archive.append_frame(f"f{k}", f"digest{k}", pack(message(k, f"f{k}")))
    return archive


def test_compression_is_lossless_and_smaller():
    msg = message(3, "a")
    data = compress_payload(pack(msg))
    a, b = frame_from_message(msg), frame_from_message(decompress_message(data))
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and b.frame_id == "a"
    assert np.array_equal(a.camera.c2w64(), b.camera.c2w64())
    smooth = {**msg, "rgb": encode_array(np.broadcast_to(np.arange(16, dtype=np.uint8)[None, :, None] * 8, (12, 16, 3)).copy()),
              "depth": encode_array(np.full((12, 16), 1.5, np.float32))}
    assert len(compress_payload(pack(smooth))) < len(pack(smooth)) / 3  # real images are smooth, noise is not


def test_frames_archived_as_png_and_zlib_read_back():
    """Archives written before zstandard: colour as PNG bytes, zlib over the map."""
    msg = message(4, "b")
    rgb = frame_from_message(msg).rgb.numpy()
    legacy = zlib.compress(pack({**msg, "rgb": encode_png(rgb)}), 6)
    a, b = frame_from_message(msg), frame_from_message(decompress_message(legacy))
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and b.frame_id == "b"


def test_reopening_replays_frames_and_corrections(tmp_path):
    archive = archive_of(tmp_path, 4)
    archive.append_correction({2: np.diag([1.0, -1.0, -1.0, 1.0])}, [1])
    archive.close()
    again = SessionArchive(tmp_path / ARCHIVE, "all")
    assert [(e.arrival, e.frame_id, e.digest) for e in again.entries] == [(0, "f0", "digest0"), (2, "f2", "digest2"),
                                                                          (3, "f3", "digest3")]
    assert again.corrections == 1 and again.next_arrival == 4 and again.problem is None
    frames = list(again.frames(again.entries))
    assert np.array_equal(frames[1].camera.c2w64(), np.diag([1.0, -1.0, -1.0, 1.0]))  # the corrected pose
    assert np.array_equal(frames[2].camera.c2w64(), frame_from_message(message(3)).camera.c2w64())
    assert torch.equal(frames[0].rgb, frame_from_message(message(0)).rgb)
    again.append_frame(None, "digest4", pack(message(4)))  # arrival indices go on after the removed frame
    assert again.entries[-1].arrival == 4


def test_a_torn_tail_is_cut_and_damage_refuses_corrections(tmp_path):
    archive_of(tmp_path, 3).close()
    path = tmp_path / ARCHIVE
    intact = path.read_bytes()
    path.write_bytes(intact + intact[:30])  # a crash mid-append
    torn = SessionArchive(path, "all")
    assert len(torn.entries) == 3 and torn.problem is None and path.read_bytes() == intact
    torn.close()
    damaged = bytearray(intact)
    damaged[len(intact) // 2] ^= 0xFF
    path.write_bytes(bytes(damaged))
    broken = SessionArchive(path, "all")
    assert broken.problem and "damaged record" in broken.problem
    assert path.read_bytes() == bytes(damaged)  # nothing cut


def test_cut_to_removes_one_unfolded_frame_and_flags_any_other_difference(tmp_path):
    archive = archive_of(tmp_path, 3)
    archive.cut_to(2)  # the last frame was archived, never folded
    assert len(archive.entries) == 2 and archive.problem is None and archive.next_arrival == 2
    archive.cut_to(2)
    assert archive.problem is None
    archive.cut_to(5)  # the scene holds frames the archive lacks
    assert archive.problem and "holds 2 of the session's 5 frames" in archive.problem
    archive.close()
    reopened = SessionArchive(tmp_path / ARCHIVE, "all")
    assert len(reopened.entries) == 2


def test_keyframes_retention_keeps_one_frame_in_five(tmp_path):
    archive = archive_of(tmp_path, 7, "keyframes")
    assert [e.kept for e in archive.entries] == [True, False, False, False, False, True, False]
    assert [f is None for f in archive.frames(archive.entries)] == [False, True, True, True, True, False, True]
    with pytest.raises(ValueError, match=r"^archive_retention: "):
        SessionArchive(tmp_path / "other.log", "some")


def test_a_payload_digest_names_its_payload_and_so_do_the_older_digests_of_its_bytes():
    a, b = pack(message(1, "f1")), pack(message(2, "f2"))
    digest = payload_digest(a)
    assert re.fullmatch(r"xxh3m:[0-9a-f]{32}", digest) and digest == payload_digest(bytes(a))
    assert names_payload(digest, a) and not names_payload(digest, b)
    for older in ("xxh3:" + xxhash.xxh3_128_hexdigest(a), hashlib.blake2b(a, digest_size=16).hexdigest()):
        assert names_payload(older, a) and not names_payload(older, b)  # what sessions written before hold
    assert payload_digest(b"not msgpack") == "xxh3:" + xxhash.xxh3_128_hexdigest(b"not msgpack")


def test_a_message_encoded_otherwise_has_the_same_digest_and_another_message_another():
    """A retry that packs the same message otherwise names the same frame: keys in another order (a
    Go client's maps), nested ones too, and 615 for 615.0; any other value, key or type does not."""
    msg = message(3, "f3")
    reordered = {k: (dict(reversed(v.items())) if isinstance(v, dict) else v) for k, v in reversed(msg.items())}
    as_ints = {**msg, "K": [[20, 0, 8], [0, 20, 6], [0, 0, 1]]}
    assert pack(reordered) != pack(msg) and pack(as_ints) != pack(msg)
    assert payload_digest(pack(reordered)) == payload_digest(pack(as_ints)) == payload_digest(pack(msg))
    others = [{**msg, "frame_id": "f4"}, {**msg, "K": [[20.5, 0, 8], [0, 20, 6], [0, 0, 1]]},
              {**msg, "depth_scale": 1.0}, {**msg, "frame_id": b"f3"},
              {**msg, "rgb": {**msg["rgb"], "data": msg["rgb"]["data"][:-1] + b"\x00"}}]
    assert len({payload_digest(pack(m)) for m in [msg, *others]}) == 1 + len(others)


def test_deferred_frames_are_archived_in_order_by_the_writer(tmp_path):
    archive = SessionArchive(tmp_path / ARCHIVE, "all")
    payloads = [pack(message(k, f"f{k}")) for k in range(5)]
    for k, p in enumerate(payloads):
        archive.defer_frame(f"f{k}", payload_digest(p), p)
    archive.flush()
    assert [(e.arrival, e.frame_id, e.digest) for e in archive.entries] == [
        (k, f"f{k}", payload_digest(p)) for k, p in enumerate(payloads)]
    archive.defer_frame("f5", "d5", pack(message(5, "f5")))
    archive.close()  # archives what is still queued
    again = SessionArchive(tmp_path / ARCHIVE, "all")
    assert len(again.entries) == 6 and torch.equal(next(iter(again.frames(again.entries[5:]))).rgb,
                                                   frame_from_message(message(5)).rgb)


def test_a_writer_failure_refuses_corrections_and_does_not_hang_a_flush(tmp_path):
    archive = archive_of(tmp_path, 1)
    archive._log.close()  # every append fails from here on
    archive.defer_frame("f1", "d1", pack(message(1, "f1")))
    archive.defer_frame("f2", "d2", pack(message(2, "f2")))
    archive.flush()
    assert archive.problem is not None and "could not be archived" in archive.problem
    assert len(archive.entries) == 1


def test_cut_to_archives_the_frames_it_lacks_from_the_log(tmp_path):
    archive = archive_of(tmp_path, 2)
    logged = {k: pack(message(k, f"f{k}")) for k in range(1, 4)}  # the log after a snapshot of 1 frame
    archive.cut_to(4, logged)
    assert archive.problem is None
    assert [(e.arrival, e.frame_id) for e in archive.entries] == [(k, f"f{k}") for k in range(4)]
    assert [e.digest for e in archive.entries[2:]] == [payload_digest(logged[2]), payload_digest(logged[3])]
    (tmp_path / "b").mkdir()
    short = archive_of(tmp_path / "b", 1)
    short.cut_to(3, {2: logged[2]})  # frame 1 is in neither: the archive cannot serve corrections
    assert short.problem is not None and len(short.entries) == 1


def test_a_damaged_frame_record_is_named():
    data = bytearray(compress_payload(pack(message(5, "c"))))
    data[len(data) // 2] ^= 0xFF
    with pytest.raises(DamagedFrame, match=r"^archive\.log: an archived frame does not decompress"):
        decompress_message(bytes(data))


def test_a_frame_that_came_compressed_is_kept_as_it_came_and_checked_by_its_digest():
    msg = message(6, "d")
    rgb, depth = frame_from_message(msg).rgb.numpy(), frame_from_message(msg).depth.numpy()
    compact = pack({**msg, "rgb": encode_png(rgb), "depth": encode_array(depth, codec="zstd")})
    assert compress_payload(compact) == compact  # zstandard over PNG and zstandard bytes would gain nothing
    assert compress_payload(pack(msg))[:4] == b"\x28\xb5\x2f\xfd"  # raw arrays are compressed
    a, b = frame_from_message(msg), frame_from_message(decompress_message(compact, payload_digest(compact)))
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
    damaged = bytearray(compact)
    damaged[len(damaged) // 2] ^= 0xFF
    with pytest.raises(DamagedFrame, match=r"^archive\.log: an archived frame no longer matches its digest"):
        decompress_message(bytes(damaged), payload_digest(compact))


def test_an_archive_reads_back_the_bytes_the_client_sent(tmp_path):
    archive = SessionArchive(tmp_path / ARCHIVE, "all")
    payloads = []
    for k in range(3):
        msg = message(k, f"f{k}")
        frame = frame_from_message(msg)
        payloads.append(pack({**msg, "rgb": encode_png(frame.rgb.numpy()), "depth": encode_array(frame.depth.numpy(), codec="zstd")}))
        archive.append_frame(f"f{k}", payload_digest(payloads[-1]), payloads[-1])
    archive.close()
    assert all(p in (tmp_path / ARCHIVE).read_bytes() for p in payloads)  # verbatim
    again = SessionArchive(tmp_path / ARCHIVE, "all")
    assert list(again.payloads(again.entries)) == payloads
    again.close()


def test_an_undo_restores_what_its_background_correction_changed_and_keeps_the_frames_since(tmp_path):
    archive = archive_of(tmp_path, 3)
    moved = np.eye(4)
    moved[0, 3] = 1.0
    archive.append_correction({archive.entries[0].arrival: moved}, [archive.entries[1].arrival], 0, "job", {})
    archive.append_frame("f3", "digest3", pack(message(3, "f3")))  # arrived while it re-folded
    assert [e.frame_id for e in archive.entries] == ["f0", "f2", "f3"] and archive.corrections == 1
    archive.append_undo("job", "CapacityError: max_voxels")
    for state in (archive, SessionArchive(tmp_path / ARCHIVE, "all")):  # in memory, and replayed
        assert [e.frame_id for e in state.entries] == ["f0", "f1", "f2", "f3"] and state.poses == {}
        assert state.corrections == 0 and state.problem is None
        assert state.status("job", "s", 4)["state"] == "failed" and state.background_correction is None
    archive.append_undo("other", "?")  # names no background correction: the archive serves no correction
    assert "undoes correction other" in archive.problem
