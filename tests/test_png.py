"""volpuzzle.io.png: the pictures' PNG files, read back by Pillow exactly as they were drawn."""

import io
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from volpuzzle.io.png import png_bytes


def _read(data):
    with Image.open(io.BytesIO(data)) as im:
        im.load()
        return im.mode, np.asarray(im)


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 40), seed=st.integers(0, 2**32 - 1), level=st.integers(0, 9))
def test_every_picture_reads_back_as_it_was_drawn(h, w, seed, level):
    rgb = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    mode, back = _read(png_bytes(rgb, level))
    assert mode == "RGB"
    assert back.shape == (h, w, 3)
    assert np.array_equal(back, rgb)


def test_the_file_is_signature_header_one_data_chunk_and_end_with_unfiltered_rows():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    data = png_bytes(rgb)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    chunks, at = [], 8
    while at < len(data):
        (length,) = struct.unpack(">I", data[at:at + 4])
        kind, body = data[at + 4:at + 8], data[at + 8:at + 8 + length]
        (crc,) = struct.unpack(">I", data[at + 8 + length:at + 12 + length])
        assert crc == zlib.crc32(kind + body)
        chunks.append((kind, body))
        at += 12 + length
    assert [k for k, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    assert struct.unpack(">IIBBBBB", chunks[0][1]) == (3, 2, 8, 2, 0, 0, 0)
    rows = np.frombuffer(zlib.decompress(chunks[1][1]), np.uint8).reshape(2, 1 + 9)
    assert np.all(rows[:, 0] == 0)
    assert np.array_equal(rows[:, 1:], rgb.reshape(2, 9))


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 4), np.uint8),
                                 np.zeros((4, 4, 3), np.float64), np.zeros((0, 4, 3), np.uint8)])
def test_anything_but_an_rgb_byte_picture_is_refused(bad):
    with pytest.raises(ValueError, match=r"expected an \(h, w, 3\) uint8 array, got"):
        png_bytes(bad)
