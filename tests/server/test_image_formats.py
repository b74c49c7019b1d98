"""The image files a frame's fields may be: a phone's JPEG with the MPF extension is a JPEG, a class
map PNG of fewer than 8 bits a sample is refused (its samples would be scaled), and a depth image
that is no PNG is told to be one."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from canonical_wire import WireError
from server import wire


def encoded(image: Image.Image, **options) -> bytes:
    buf = io.BytesIO()
    image.save(buf, **options)
    return buf.getvalue()


def test_a_jpeg_with_the_mpf_extension_is_read_as_its_first_image():
    rng = np.random.default_rng(0)
    first, second = (Image.fromarray(rng.integers(0, 255, (24, 32, 3)).astype(np.uint8)) for _ in range(2))
    mpo = encoded(first, format="MPO", save_all=True, append_images=[second], quality=95)
    assert Image.open(io.BytesIO(mpo)).format == "MPO"  # what Pillow calls it, as it does a phone's HDR JPEG
    jpeg = encoded(first, format="JPEG", quality=95)
    assert np.array_equal(wire.decode_rgb(mpo), wire.decode_rgb(jpeg))


@pytest.mark.parametrize("bits", [1, 2, 4])
def test_a_class_map_png_of_fewer_than_8_bits_is_refused_naming_labels(bits):
    ids = (np.arange(32) % (2 ** bits)).astype(np.uint8)[None].repeat(8, 0)
    low = encoded(Image.fromarray(ids), format="PNG", bits=bits)
    assert low[24] == bits  # the file is written with that many bits a sample
    with pytest.raises(WireError, match=f"^labels: expected an 8- or 16-bit .* got a {bits}-bit grey PNG"):
        wire.decode_class_png(low)
    assert np.array_equal(wire.decode_class_png(encoded(Image.fromarray(ids), format="PNG")), ids.astype(np.int32) - 1)


def test_depth_that_is_no_png_is_told_to_be_one():
    jpeg = encoded(Image.fromarray(np.zeros((8, 8), np.uint8)), format="JPEG")
    with pytest.raises(WireError, match="^depth: image format JPEG is not accepted; send a PNG$"):
        wire.decode_depth_png(jpeg, 1000.0)
