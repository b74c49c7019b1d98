"""A small, bounded multipart/form-data parser for frame uploads.

The stdlib email parser is general (MIME nesting, encoded words, any number of header parameters)
and its cost grows faster than linearly with hostile headers. A frame upload needs none of that:
a few named parts, each with a short Content-Disposition. Here the body is split on its boundary
in one linear pass, and the number of parts, the size of each part's header block and the number
of header parameters are bounded before anything else is looked at.

Example:
    >>> body = b'--xx\\r\\nContent-Disposition: form-data; name="a"\\r\\n\\r\\nhello\\r\\n--xx--\\r\\n'
    >>> parse_form_data('multipart/form-data; boundary=xx', body)
    [FormPart(name='a', filename=None, data=b'hello')]
"""

from __future__ import annotations

from typing import NamedTuple

from canonical_wire import WireError

MAX_PARTS = 8
MAX_PART_HEADER_BYTES = 2048  # all header lines of one part
MAX_PARAMS = 8  # parameters of one header (name, filename, ...)
MAX_CONTENT_TYPE_BYTES = 512


class FormPart(NamedTuple):
    name: str
    filename: str | None
    data: bytes


def _malformed(message: str) -> WireError:
    return WireError("body", f"malformed multipart body ({message})", 400, "malformed_body")


def header_params(value: str, field: str) -> tuple[str, dict[str, str]]:
    """``'form-data; name="rgb"; filename="a.png"'`` -> ("form-data", {"name": "rgb", ...}), with at most
    `MAX_PARAMS` parameters (WireError naming ``field`` otherwise)."""
    items = value.split(";")
    if len(items) - 1 > MAX_PARAMS:
        raise WireError(field, f"{len(items) - 1} header parameters exceed the limit of {MAX_PARAMS}", 400, "malformed_body")
    params: dict[str, str] = {}
    for item in items[1:]:
        key, sep, val = item.strip().partition("=")
        if not sep:
            continue
        val = val.strip()
        if len(val) >= 2 and val[0] == val[-1] == '"':
            val = val[1:-1].replace('\\"', '"')
        params[key.strip().lower()] = val
    return items[0].strip().lower(), params


def boundary_of(content_type: str) -> bytes:
    """The boundary parameter of a multipart Content-Type (1 to 70 characters, RFC 2046)."""
    if len(content_type) > MAX_CONTENT_TYPE_BYTES:
        raise WireError("Content-Type", f"header of {len(content_type)} bytes exceeds {MAX_CONTENT_TYPE_BYTES}", 400, "malformed_body")
    _, params = header_params(content_type, "Content-Type")
    boundary = params.get("boundary", "")
    if not 1 <= len(boundary) <= 70:
        raise WireError("Content-Type", "multipart needs a boundary parameter of 1 to 70 characters", 400, "malformed_body")
    try:
        return boundary.encode("ascii")
    except UnicodeEncodeError:
        raise WireError("Content-Type", "the multipart boundary must be ASCII", 400, "malformed_body") from None


def parse_form_data(content_type: str, body: bytes) -> list[FormPart]:
    """The parts of a multipart/form-data body, in order. Raises WireError(400) naming ``body`` or
    ``Content-Type`` for a malformed body or one over the bounds; repeated names are kept (the caller decides)."""
    delimiter = b"--" + boundary_of(content_type)
    if body.count(delimiter) > MAX_PARTS + 1:
        raise WireError("body", f"more than {MAX_PARTS} form parts", 400, "malformed_body")
    chunks = body.split(delimiter)
    if len(chunks) < 3 or not chunks[-1].startswith(b"--"):
        raise _malformed("no parts, or no closing boundary")
    parts = []
    for chunk in chunks[1:-1]:
        if not chunk.startswith(b"\r\n") or not chunk.endswith(b"\r\n"):
            raise _malformed("a boundary is not on a line of its own")
        chunk = chunk[2:-2]
        end = chunk.find(b"\r\n\r\n", 0, MAX_PART_HEADER_BYTES + 4)
        if end < 0:
            raise WireError("body", f"a part's headers are missing or exceed {MAX_PART_HEADER_BYTES} bytes", 400, "malformed_body")
        name, filename = None, None
        for line in chunk[:end].decode("latin-1").split("\r\n"):
            key, sep, value = line.partition(":")
            if not sep:
                raise _malformed(f"header line {line[:40]!r}")
            if key.strip().lower() == "content-disposition":
                kind, params = header_params(value, "Content-Disposition")
                if kind != "form-data" or "name" not in params:
                    raise _malformed("Content-Disposition must be form-data with a name")
                name, filename = params["name"], params.get("filename")
        if name is None:
            raise _malformed("a part without Content-Disposition")
        parts.append(FormPart(name, filename, chunk[end + 4:]))
    return parts
