"""Files written whole or not at all."""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import IO


def atomic_write(
    path: Path,
    write: Callable[[IO[bytes]], object],
    *,
    mode: int = 0o666,
    sync_folder: bool = False,
) -> None:
    """Write `path` whole or not at all: `write` fills a temporary file in the same folder
    (created with `mode`, less the umask), which is flushed to disk and renamed over
    `path`. On any failure the temporary file is removed and `path` is left as it was.
    `sync_folder`: also put the rename itself on disk (a record that must survive a
    power cut).
    """
    partial = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as out:
            write(out)
            out.flush()
            os.fsync(out.fileno())  # (a full disk can surface only here)
        os.replace(partial, path)
    except BaseException:
        with contextlib.suppress(OSError):
            partial.unlink()
        raise
    if sync_folder:
        with contextlib.suppress(OSError):
            folder = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(folder)
            finally:
                os.close(folder)


def write_private(path: Path, data: bytes) -> None:
    """Replace `path` by `data` at once (`atomic_write`, the rename synced too), readable
    and writable by its owner only (0600) from creation on; its folder made private
    (0700) if it is new.
    """
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    atomic_write(path, lambda out: out.write(data), mode=0o600, sync_folder=True)
