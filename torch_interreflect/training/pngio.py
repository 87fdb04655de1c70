"""Minimal, byte-deterministic 16-bit RGB PNG writer and reader (zlib + struct, no dependencies).

Pillow cannot write 16-bit RGB (only single-channel ``I;16``), and imageio/pypng are not dependencies, so the
generator writes PNGs itself: colour type 2 (RGB), bit depth 16, no interlace, filter type 0 on every row, one
IDAT chunk compressed by :func:`zlib.compress` at a fixed level. The same array always gives the same bytes (for
a given zlib build). The reader accepts exactly what the writer produces (and any non-interlaced 8/16-bit RGB
PNG whose rows use filter 0), enough for tests and for reading the data back without Pillow.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

__all__ = ["encode_png16", "read_png16", "write_png16"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png16(image: np.ndarray, *, level: int = 6) -> bytes:
    """PNG bytes of a 16-bit RGB image.

    Args:
        image: ``uint16`` array. Shape ``[H, W, 3]``.
        level: zlib compression level (0–9).

    Returns:
        The PNG file's bytes.

    Raises:
        ValueError: not a ``uint16`` ``[H, W, 3]`` array.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint16 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(
            f"image must be a uint16 array [H, W, 3]; got {getattr(image, 'dtype', type(image).__name__)} "
            f"{getattr(image, 'shape', '')}"
        )
    h, w, _ = image.shape
    rows = np.ascontiguousarray(image.astype(">u2")).view(np.uint8).reshape(h, w * 6)
    raw = np.concatenate([np.zeros((h, 1), dtype=np.uint8), rows], axis=1).tobytes()  # filter 0 per row
    header = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)
    return _SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, level)) + _chunk(b"IEND", b"")


def write_png16(path: str | Path, image: np.ndarray, *, level: int = 6) -> None:
    """Write a 16-bit RGB PNG (see :func:`encode_png16`); not atomic by itself.

    Args:
        path: File to write.
        image: ``uint16`` array. Shape ``[H, W, 3]``.
        level: zlib compression level.
    """
    Path(path).write_bytes(encode_png16(image, level=level))


def read_png16(path: str | Path) -> np.ndarray:
    """Read an 8- or 16-bit RGB PNG with unfiltered rows (as :func:`write_png16` writes them).

    Args:
        path: PNG file.

    Returns:
        ``uint16`` (16-bit files) or ``uint8`` array. Shape ``[H, W, 3]``.

    Raises:
        ValueError: not a PNG, or a variant this reader does not handle (palette, alpha, interlace, filters).
    """
    data = Path(path).read_bytes()
    if not data.startswith(_SIGNATURE):
        raise ValueError(f"{path} is not a PNG file")
    pos, idat, header = len(_SIGNATURE), b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            break
    if header is None:
        raise ValueError(f"{path}: no IHDR chunk")
    w, h, depth, colour, _, _, interlace = header
    if colour != 2 or depth not in (8, 16) or interlace:
        raise ValueError(f"{path}: only non-interlaced 8/16-bit RGB is supported; got depth {depth}, colour {colour}")
    bpp = 3 * depth // 8
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + w * bpp)
    if raw[:, 0].any():
        raise ValueError(f"{path}: rows use PNG filters other than 0, which this reader does not decode")
    px = raw[:, 1:].copy()
    if depth == 16:
        return px.view(">u2").reshape(h, w, 3).astype(np.uint16)
    return px.reshape(h, w, 3)
