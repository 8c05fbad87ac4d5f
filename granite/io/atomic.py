"""Atomic file output: write to a temporary file in the destination folder, then
``os.replace`` it onto the destination, so readers never see a half-written file and a crash
leaves the previous version in place.

Missing parent folders are created.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _temp_path(path: Path) -> Path:
    # Keep the suffix so that writers choosing the format by extension (cv2.imwrite,
    # numpy.save) behave as for the real destination.
    return path.with_name(f".{path.stem}.tmp-{secrets.token_hex(6)}{path.suffix}")


class PendingFile:
    """A file written through a temporary path beside ``path`` over a longer span than one
    ``with`` block (e.g. a recording logged frame by frame): the writer creates ``tmp``,
    :meth:`commit` moves it onto ``path``, :meth:`discard` removes it (both: once only)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = _temp_path(self.path)
        self._done = False

    def commit(self) -> None:
        if self._done:
            return
        if not self.tmp.exists():
            raise FileNotFoundError(f"the writer did not create the temporary file {self.tmp}")
        os.replace(self.tmp, self.path)
        self._done = True

    def discard(self) -> None:
        if not self._done:
            self._done = True
            with contextlib.suppress(FileNotFoundError):
                self.tmp.unlink()


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` for the caller to create; on normal exit it
    is moved onto ``path`` with ``os.replace``, on an exception it is removed.

    Example::

        with atomic_path("out/image.png") as tmp:
            cv2.imwrite(str(tmp), image)
    """
    pending = PendingFile(path)
    try:
        yield pending.tmp
        pending.commit()
    except BaseException:
        pending.discard()
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


def check_writable(path: str | Path, folder: bool = True) -> None:
    """Fail early, before any work, when ``path`` cannot be written: raises
    :class:`granite.errors.InputError` naming it. ``folder``: ``path`` is a folder to create or
    fill (else a file to create or replace). Nothing is created: the nearest existing ancestor
    must be a folder in which a probe file can be made (and is removed again)."""
    from granite.errors import InputError

    path = Path(path)
    if path.exists():
        if folder and not path.is_dir():
            raise InputError("exists and is not a folder", path)
        if not folder and path.is_dir():
            raise InputError("is a folder, expected a file name", path)
    probe_in = path if folder and path.is_dir() else path.parent
    while not probe_in.exists() and probe_in != probe_in.parent:
        probe_in = probe_in.parent
    if not probe_in.is_dir():
        raise InputError(f"cannot be created: {probe_in} is not a folder", path)
    try:
        fd, name = tempfile.mkstemp(prefix=".granite-write-test-", dir=probe_in)
        os.close(fd)
        os.unlink(name)
    except OSError as error:
        raise InputError(f"cannot be written ({error.strerror or error} in {probe_in})", path) from None
