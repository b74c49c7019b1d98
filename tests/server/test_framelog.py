"""The frame log on real files: torn tails told apart from damage, failed appends leave nothing behind,
and the repairs keep what they say."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from server import framelog
from server.framelog import FrameLog, StorageError, encode, repaired, scan


def payloads(n: int) -> list[bytes]:
    return [bytes([k]) * (100 + 37 * k) for k in range(n)]


def written(path, n: int = 5, first: int = 0) -> bytes:
    data = b"".join(encode(first + k, p) for k, p in enumerate(payloads(n)))
    path.write_bytes(data)
    return data


def test_a_clean_log_scans_to_its_records(tmp_path):
    data = written(tmp_path / "log")
    found = scan(data)
    assert [(r.index, r.payload) for r in found.records] == list(enumerate(payloads(5)))
    assert found.end == found.size == len(data) and not found.torn and not found.damaged


@pytest.mark.parametrize("cut", [1, 3, framelog.HEADER.size - 1, framelog.HEADER.size + 5, 200])
def test_a_crash_mid_append_is_a_torn_tail(tmp_path, cut):
    data = written(tmp_path / "log", 4) + encode(4, payloads(5)[4])[:cut]
    found = scan(data)
    assert len(found.records) == 4 and found.torn and not found.damaged and found.size - found.end == cut


@pytest.mark.parametrize("where", ["payload", "length", "magic", "last record"])
def test_a_flipped_byte_is_damage_never_a_torn_tail(tmp_path, where):
    data = bytearray(written(tmp_path / "log", 6))
    starts = [r.offset for r in scan(bytes(data)).records]
    at = {"payload": starts[2] + framelog.HEADER.size + 10, "length": starts[2] + 5, "magic": starts[2],
          "last record": starts[5] + framelog.HEADER.size + 3}[where]
    data[at] ^= 0x40
    found = scan(bytes(data))
    assert found.damaged and not found.torn
    expected_prefix = 5 if where == "last record" else 2
    assert len(found.records) == expected_prefix
    assert [r.index for r in found.later] == ([] if where == "last record" else [3, 4, 5])


def test_repairs_keep_the_prefix_or_every_intact_frame_numbered_again(tmp_path):
    data = bytearray(written(tmp_path / "log", 6, first=10))  # a snapshot holds frames 0..9
    start = scan(bytes(data)).records[2].offset
    data[start + framelog.HEADER.size] ^= 1  # frame 12 damaged
    records, kept, dropped = repaired(bytes(data), "truncate", 10, b"ids")
    after = scan(b"".join(records))
    assert (kept, dropped) == (2, 3) and not after.damaged
    assert [(r.checkpoint, r.index) for r in after.records] == [(True, 10), (False, 10), (False, 11)]
    records, kept, dropped = repaired(bytes(data), "skip", 10, b"ids")
    after = scan(b"".join(records))
    assert (kept, dropped) == (5, 0)
    assert [r.index for r in after.records if not r.checkpoint] == [10, 11, 12, 13, 14]
    assert [r.payload for r in after.records if not r.checkpoint] == [p for k, p in enumerate(payloads(6)) if k != 2]


def test_records_the_snapshot_holds_go_at_a_repair(tmp_path):
    data = written(tmp_path / "log", 4)  # frames 0..3 logged, and a newer snapshot holds 0..1
    records, kept, _ = repaired(data, "skip", 2, None)
    assert kept == 2 and [(r.index, r.payload) for r in scan(b"".join(records)).records] == [(2, payloads(4)[2]), (3, payloads(4)[3])]


def test_a_scan_copies_no_payload_so_a_mapped_archive_is_never_read_whole_into_memory(tmp_path):
    """A session's archive holds every frame it kept (gigabytes in a long session): a start scans it
    mapped, and each record's payload is a view of the mapping, not a copy."""
    import mmap

    from server.archive import _mapped

    data = written(tmp_path / "log", 3)
    mapped = _mapped(tmp_path / "log")
    assert isinstance(mapped, mmap.mmap)
    records = scan(mapped).records
    assert [bytes(r.payload) for r in records] == payloads(3)
    assert all(r.payload.obj is mapped for r in records) and len(mapped) == len(data)
    assert _mapped(tmp_path / "absent") == b""


def test_a_failed_append_is_cut_off_at_once_and_the_log_takes_the_next(tmp_path, monkeypatch):
    path = tmp_path / "log"
    written(path, 2)
    log = FrameLog(path)
    real_write = os.write

    def disk_fills_after_100_bytes(fd, data):
        if fd == log._fd:
            real_write(fd, bytes(data[:100]))
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(framelog.os, "write", disk_fills_after_100_bytes)
    with pytest.raises(StorageError) as caught:
        log.append(2, payloads(3)[2])
    assert caught.value.full and "No space left" in str(caught.value)
    found = scan(path.read_bytes())
    assert len(found.records) == 2 and found.end == found.size  # no partial record left behind
    monkeypatch.undo()
    log.append(2, payloads(3)[2])
    log.close()
    assert [r.payload for r in scan(path.read_bytes()).records] == payloads(3)


def test_a_file_size_limit_is_storage_the_service_cannot_use_as_a_full_disk_is(tmp_path):
    """``ulimit -f`` (RLIMIT_FSIZE; Python ignores SIGXFSZ, so a write past it fails with EFBIG): the
    append is refused as a full disk's (507, retry once space is made), its partial record cut off."""
    script = f"""
import resource, sys
from pathlib import Path
sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r})
from server.framelog import FrameLog, StorageError
resource.setrlimit(resource.RLIMIT_FSIZE, (3000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
log = FrameLog(Path({str(tmp_path / "log")!r}))
try:
    for i in range(100):
        log.append(i, bytes(1000))
except StorageError as exc:
    print(i, exc.full, exc)
"""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    refused, full, message = done.stdout.split(" ", 2)
    assert full == "True" and "too large" in message, done.stdout + done.stderr
    found = scan((tmp_path / "log").read_bytes())
    assert len(found.records) == int(refused) >= 1 and found.end == found.size  # no partial record left


def test_an_append_whose_cut_fails_too_is_wedged(tmp_path, monkeypatch):
    path = tmp_path / "log"
    log = FrameLog(path)

    def failing(*args):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(framelog.os, "write", failing)
    monkeypatch.setattr(framelog.os, "ftruncate", failing)
    with pytest.raises(framelog.LogWedged):
        log.append(0, b"x")
    log.close()


def test_reset_replaces_the_log_atomically(tmp_path):
    path = tmp_path / "log"
    written(path, 3)
    log = FrameLog(path)
    log.reset([encode(3, b"ids", checkpoint=True)])
    log.append(3, b"next")
    log.close()
    assert [(r.checkpoint, r.index, r.payload) for r in scan(path.read_bytes()).records] == [(True, 3, b"ids"), (False, 3, b"next")]
    assert not (tmp_path / "log.tmp").exists()


@pytest.mark.parametrize("bit", range(framelog.HEADER.size * 8))
def test_a_flipped_bit_in_the_last_records_header_is_damage_never_a_torn_tail(tmp_path, bit):
    """A length made longer by one bit runs past the end of the file as a torn record does: the
    header's own CRC tells them apart."""
    data = bytearray(written(tmp_path / "log", 6))
    last = scan(bytes(data)).records[-1]
    data[last.offset + bit // 8] ^= 1 << bit % 8
    found = scan(bytes(data))
    assert found.damaged and not found.torn and len(found.records) == 5 and found.end == last.offset


OLD_FORMAT = Path(__file__).resolve().parents[1] / "fixtures" / "frames_v1.log"  # a checkpoint and frames 2..4


def test_an_old_format_log_is_read_by_its_rules_and_goes_on_in_the_new_format(tmp_path):
    data = OLD_FORMAT.read_bytes()
    found = scan(data)
    assert [(r.checkpoint, r.index, r.version) for r in found.records] == [(True, 2, 1), (False, 2, 1), (False, 3, 1),
                                                                           (False, 4, 1)]
    assert [r.payload for r in found.records[1:]] == payloads(5)[2:] and found.version == 1 and not found.damaged
    last = found.records[-1]
    assert scan(data[:last.offset + 30]).torn  # format 1: a record running past the end is a torn tail
    path = tmp_path / "log"
    path.write_bytes(data)
    log = FrameLog(path)
    log.append(5, b"next")  # the log goes on in the new format
    log.close()
    found = scan(path.read_bytes())
    assert [(r.index, r.version) for r in found.records[-2:]] == [(4, 1), (5, 2)] and found.version == 2
    assert found.end == found.size and path.read_bytes()[:len(data)] == data
