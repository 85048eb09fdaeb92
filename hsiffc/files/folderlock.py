"""The lock that keeps two batch runs out of one output folder (see :mod:`hsiffc.files.atomic`)."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import stat
import time
from pathlib import Path

from .atomic import OutputError, require_private_file

__all__ = ["LOCK_NAME", "FolderLockedError", "folder_lock"]

LOCK_NAME = ".hsiffc.lock"


class FolderLockedError(OutputError):
    """Another run holds the lock of an output folder.

    Examples
    --------
    >>> import tempfile
    >>> folder = tempfile.mkdtemp()
    >>> with folder_lock(folder):
    ...     try:
    ...         with folder_lock(folder, what="my-tool"):
    ...             pass
    ...     except FolderLockedError as exc:
    ...         print("another", str(exc).split("another ", 1)[1].split(" run")[0], "run")
    another my-tool run
    """


@contextlib.contextmanager
def folder_lock(folder, *, wait_s: float = 0.0, what: str = "hsiffc"):
    """Hold an exclusive lock on an output folder while a batch writes into it.

    The lock is ``folder/.hsiffc.lock``, locked with ``fcntl.flock`` (released by the kernel
    if the process dies) and holding who took it (pid, host, start time, command).

    Parameters
    ----------
    folder : path-like
        Created if missing.
    wait_s : float
        Seconds to wait for another run to finish before giving up (0: give up at once).

    Raises
    ------
    FolderLockedError
        Another run holds the lock; the message names its pid, host and start time.
    OutputError
        ``.hsiffc.lock`` is not a lock file hsiffc made: a symbolic or hard link (e.g. to an
        input), a FIFO, device or folder, or a file holding anything but a lock record. It is
        refused without being written (never truncated).

    Examples
    --------
    A tool that writes many files into one folder keeps a second run of itself (or of
    ``hsiffc correct``) out while it works:

    >>> import tempfile
    >>> from pathlib import Path
    >>> out = Path(tempfile.mkdtemp()) / "cubes"
    >>> with folder_lock(out, what="my-tool") as holder:
    ...     print(holder["command"], (out / LOCK_NAME).exists())
    my-tool True
    """
    import fcntl

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_NAME
    fd = _open_lock(lock)
    try:
        deadline = time.monotonic() + max(0.0, float(wait_s))
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise FolderLockedError(
                        f"{folder}: another {what} run is writing into this folder "
                        f"({_holder(fd)}); wait for it to finish, or choose another output "
                        "folder") from None
                time.sleep(0.2)
        _check_lock_file(lock, fd)  # again under the lock: a holder may have left a record
        me = {"pid": os.getpid(), "host": socket.gethostname(),
              "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "command": what}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(me) + "\n").encode(), 0)
        try:
            yield me
        finally:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the flock


_RECORD_MAX = 4096  # a lock record (pid, host, start, command) is a few hundred bytes


def _open_lock(lock: Path) -> int:
    """Open (or create) the lock file without following a link, without blocking on a FIFO
    and without truncating anything; refuse any lock file that is not a regular file with one
    name holding nothing but a lock record (:func:`hsiffc.files.atomic.require_private_file`)."""
    with contextlib.suppress(FileNotFoundError):
        st = os.lstat(lock)
        if stat.S_ISLNK(st.st_mode):
            raise OutputError(f"{lock}: is a symbolic link; remove it (hsiffc never writes "
                              "through a link)")
        require_private_file(lock, st, what="lock file")  # refused before it is opened
    flags = (os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        fd = os.open(lock, flags, 0o666)
    except OSError as exc:
        raise OutputError(f"{lock}: the lock file cannot be opened ({exc.strerror}); check the "
                          "folder's permissions, or remove the file") from None
    try:  # the file opened may not be the one checked: check it again (its record once locked)
        require_private_file(lock, os.fstat(fd), what="lock file")
    except BaseException:
        os.close(fd)
        raise
    return fd


def _check_lock_file(lock: Path, fd: int) -> None:
    """The open lock file is a regular file with one name that is empty or holds one lock
    record; anything else (a hard link to an input, data of any kind) is never written."""
    st = os.fstat(fd)
    require_private_file(lock, st, what="lock file")
    if st.st_size == 0:
        return
    text = os.pread(fd, _RECORD_MAX + 1, 0) if st.st_size <= _RECORD_MAX else b""
    try:
        doc = json.loads(text.decode())
    except (UnicodeDecodeError, ValueError):
        doc = None
    if not (isinstance(doc, dict) and {"pid", "host", "started"} <= doc.keys()):
        raise OutputError(f"{lock}: holds {st.st_size} bytes that are not an hsiffc lock "
                          "record; hsiffc never writes into a file it did not make: move it "
                          "away (it may be data) or choose another output folder")


def _holder(fd: int) -> str:
    try:
        doc = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        doc = {}
    if not doc:
        return "a run that is just starting"
    return (f"pid {doc.get('pid')} on host {doc.get('host')}, started {doc.get('started')}")
