"""Image loading: always a 2-D grayscale array, bit depth kept (uint8 or uint16)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from granite.errors import InputError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_problem(data: np.ndarray) -> str | None:
    """Why a PNG byte stream is structurally broken (a chunk running past the end of the
    file, no IEND), or ``None``. Checked before decoding because OpenCV allocates whatever a
    corrupt chunk length claims, which can take seconds."""
    buf = data.tobytes()
    pos, end = len(_PNG_SIGNATURE), len(buf)
    while pos + 8 <= end:
        length = int.from_bytes(buf[pos : pos + 4], "big")
        kind = buf[pos + 4 : pos + 8]
        pos += 12 + length  # length, type, data, CRC
        if pos > end:
            return f"corrupt or truncated PNG ({kind!r} chunk runs past the end of the file)"
        if kind == b"IEND":
            return None
    return "truncated PNG (no IEND chunk)"


def read_image(path: str | Path) -> np.ndarray:
    """Read ``path`` as a 2-D grayscale array (``cv2.IMREAD_UNCHANGED``; colour images are
    converted with ``cv2.cvtColor``, alpha is dropped). Missing, empty or undecodable files
    raise :class:`InputError`."""
    p = Path(path)
    try:
        data = np.fromfile(p, dtype=np.uint8)
    except FileNotFoundError:
        raise InputError("image not found", p) from None
    except OSError as error:
        raise InputError(f"cannot read image: {error.strerror or error}", p) from None
    if data.size == 0:
        raise InputError("empty image file", p)
    if data[:8].tobytes() == _PNG_SIGNATURE:
        problem = _png_problem(data)
        if problem is not None:
            raise InputError(f"cannot decode image: {problem}", p)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError("cannot decode image (corrupt or unsupported format)", p)
    if image.ndim == 3:
        channels = image.shape[2]
        if channels == 1:
            image = image[:, :, 0]
        elif channels == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        elif channels == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
        else:
            raise InputError(f"unsupported number of channels: {channels}", p)
    return np.ascontiguousarray(image)
