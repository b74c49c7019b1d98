"""The bounded multipart/form-data parser: parts as written, and every bound and malformation refused."""

from __future__ import annotations

import httpx
import pytest

from canonical_wire import WireError
from server.multipart import MAX_PARAMS, MAX_PART_HEADER_BYTES, MAX_PARTS, FormPart, parse_form_data

CT = "multipart/form-data; boundary=b0und"


def body(*parts: tuple[str, bytes], boundary: str = "b0und") -> bytes:
    out = b""
    for disposition, data in parts:
        out += f"--{boundary}\r\nContent-Disposition: {disposition}\r\n\r\n".encode() + data + b"\r\n"
    return out + f"--{boundary}--\r\n".encode()


def test_parts_match_what_httpx_writes():
    request = httpx.Request("POST", "http://x/", files={"rgb": ("c.png", b"\x89PNG\r\n--b0und-ish\r\n", "image/png")},
                            data={"camera": '{"K": [[1, 0, 0]]}'})
    parts = parse_form_data(request.headers["content-type"], request.read())
    assert sorted(parts) == sorted([FormPart("camera", None, b'{"K": [[1, 0, 0]]}'),
                                    FormPart("rgb", "c.png", b"\x89PNG\r\n--b0und-ish\r\n")])


def test_quoted_boundary_and_empty_payload():
    parts = parse_form_data('multipart/form-data; boundary="a b"', body(('form-data; name="x"', b""), boundary="a b"))
    assert parts == [FormPart("x", None, b"")]


def test_repeated_names_are_kept_for_the_caller():
    parts = parse_form_data(CT, body(('form-data; name="rgb"', b"1"), ('form-data; name="rgb"', b"2")))
    assert [p.data for p in parts] == [b"1", b"2"]


MALFORMED = [
    ("no boundary", "multipart/form-data", body(('form-data; name="x"', b"1")), "Content-Type"),
    ("boundary too long", "multipart/form-data; boundary=" + "b" * 71, b"", "Content-Type"),
    ("content type too long", CT + "; x=" + "y" * 600, b"", "Content-Type"),
    ("no closing boundary", CT, body(('form-data; name="x"', b"1"))[:-4], "body"),
    ("no parts", CT, b"--b0und--\r\n", "body"),
    ("not form-data", CT, body(('attachment; name="x"', b"1")), "body"),
    ("no name", CT, body(('form-data; filename="a"', b"1")), "body"),
    ("header without colon", CT, b"--b0und\r\nnonsense\r\n\r\n1\r\n--b0und--\r\n", "body"),
    ("no header end", CT, b"--b0und\r\nContent-Disposition: form-data; name=x\r\n1\r\n--b0und--\r\n", "body"),
    ("too many parts", CT, body(*[(f'form-data; name="p{i}"', b"1") for i in range(MAX_PARTS + 1)]), "body"),
    ("too many parameters", CT, body(("form-data; name=x" + "; a=1" * MAX_PARAMS, b"1")), "Content-Disposition"),
    ("40k parameters", CT, body(("form-data; name=x" + "; a=1" * 40_000, b"1")), "body"),
    ("header block too long", CT, body(('form-data; name="x"\r\nX-Pad: ' + "p" * MAX_PART_HEADER_BYTES, b"1")), "body"),
]


@pytest.mark.parametrize("content_type, data, field", [c[1:] for c in MALFORMED], ids=[c[0] for c in MALFORMED])
def test_malformed_or_oversized_is_400_naming_the_field(content_type, data, field):
    with pytest.raises(WireError) as info:
        parse_form_data(content_type, data)
    assert info.value.status == 400 and info.value.field == field and str(info.value).startswith(f"{field}: ")


def test_docstring_example_runs():
    import doctest

    import server.multipart

    result = doctest.testmod(server.multipart, verbose=False)
    assert result.attempted > 0 and result.failed == 0
