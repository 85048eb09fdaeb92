"""Atomic file output: a file appears under its final name complete, or not at all."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path, *, overwrite: bool = True):
    """Yield a hidden temporary path beside ``path``; on success move it onto ``path``.

    The temporary file is created empty with exclusive-create (permissions follow the umask);
    the caller writes it (by name or by reopening it). Afterwards it is fsynced and renamed with
    :func:`os.replace`, and the folder is fsynced so the rename is durable. Readers never see a
    partial file under the final name. On any exception the temporary file is removed and
    ``path`` is left as it was.

    Parameters
    ----------
    path : path-like
        Final file name. Its folder is created if missing.
    overwrite : bool
        If False and ``path`` exists, raise :class:`FileExistsError` before writing anything
        (and again if it appeared while writing).
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; give a file name")
    if not overwrite and path.exists():
        raise FileExistsError(f"{path} already exists; pass overwrite=True (CLI: --overwrite) "
                              "to replace it (the existing file was left unchanged)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.part")
    try:
        with open(tmp, "xb"):
            pass
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if not overwrite and path.exists():
            raise FileExistsError(f"{path} appeared while writing; pass overwrite=True to "
                                  "replace it")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    with contextlib.suppress(OSError):  # make the rename durable (POSIX)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def atomic_write_text(path, text: str, *, overwrite: bool = True) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def atomic_write_bytes(path, data: bytes, *, overwrite: bool = True) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        Path(tmp).write_bytes(data)
