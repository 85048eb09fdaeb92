"""The lock that keeps two batch runs out of one output folder (see :mod:`hsiffc.atomic`)."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from pathlib import Path

from .atomic import OutputError

__all__ = ["LOCK_NAME", "FolderLockedError", "folder_lock"]

LOCK_NAME = ".hsiffc.lock"


class FolderLockedError(OutputError):
    """Another run holds the lock of an output folder."""


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
    """
    import fcntl

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_NAME
    if os.path.islink(lock):
        raise OutputError(f"{lock}: is a symbolic link; remove it (hsiffc never writes through "
                          "a link)")
    fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
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


def _holder(fd: int) -> str:
    try:
        doc = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        doc = {}
    if not doc:
        return "a run that is just starting"
    return (f"pid {doc.get('pid')} on host {doc.get('host')}, started {doc.get('started')}")
