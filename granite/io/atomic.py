"""Atomic file output: write to a temporary file in the destination folder, then
``os.replace`` it onto the destination, so readers never see a half-written file and a crash
leaves the previous version in place.

Missing parent folders are created.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path


def _temp_path(path: Path) -> Path:
    # Keep the suffix so that writers choosing the format by extension (cv2.imwrite,
    # numpy.save) behave as for the real destination.
    return path.with_name(f".{path.stem}.tmp-{secrets.token_hex(6)}{path.suffix}")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` for the caller to create; on normal exit it
    is moved onto ``path`` with ``os.replace``, on an exception it is removed.

    Example::

        with atomic_path("out/image.png") as tmp:
            cv2.imwrite(str(tmp), image)
    """
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_path(dest)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"the writer did not create the temporary file {tmp}")
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Atomically replace ``path`` by ``data`` (flushed to disk before the rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "xb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())


def atomic_write_text(path: str | Path, text: str) -> None:
    """Atomically replace ``path`` by ``text`` encoded as UTF-8 (newlines kept as given)."""
    atomic_write_bytes(path, text.encode("utf-8"))
