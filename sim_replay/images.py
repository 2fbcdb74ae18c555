"""Image files of a recording, decoded only when complete: a truncated PNG or
JPEG is refused rather than decoded in part.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


_JPEG_SOI = b"\xff\xd8"


_JPEG_EOI = b"\xff\xd9"


_JPEG_TAIL_BYTES = 1024  # some encoders pad after the end-of-image marker


def _png_has_iend(data: bytes) -> bool:
    """Walk the PNG chunk list: complete only if an IEND chunk fits in the data.

    Walking the chunks (a few dozen per frame) is exact, where searching for the
    bytes "IEND" could hit compressed data or miss trailing padding.
    """
    pos = len(_PNG_SIGNATURE)
    while pos + 12 <= len(data):
        (length,) = struct.unpack_from(">I", data, pos)
        end = pos + 12 + length  # length + type + payload + crc
        if end > len(data):
            return False
        if data[pos + 4 : pos + 8] == b"IEND":
            return True
        pos = end
    return False


def looks_complete(data: bytes) -> bool:
    """False for a PNG without its IEND chunk or a JPEG without its EOI marker.

    OpenCV 4.x builds decode a truncated file partially and only warn (a
    half-grey image would reach the tracker); checking the end cheaply catches
    that whatever the decoder does. Other formats are judged by the decoder.
    """
    if data.startswith(_PNG_SIGNATURE):
        return _png_has_iend(data)
    if data.startswith(_JPEG_SOI):
        return _JPEG_EOI in data[-_JPEG_TAIL_BYTES:]
    return True


def decode_image(path: Path, flags: int) -> tuple[np.ndarray | None, str]:
    """Decode an image file; returns (image, "") or (None, reason)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        return None, f"cannot read ({e.strerror})"
    if not data:
        return None, "empty file"
    if not looks_complete(data):
        return None, "truncated (no end marker)"
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if img is None:
        return None, "not a decodable image"
    return img, ""
