"""The one writer: every file hsiffc writes goes through :func:`atomic_path`.

Rules, the same for outputs, JSON summaries, reports, figures, calibrations and pipelines:

* **No silent replacement.** An existing file is replaced only when asked (``overwrite=True``,
  on the command line ``--overwrite``). A file this process wrote itself may be written again
  (a summary updated at the end of a run).
* **Never an input.** A path that is an input of the running command (same name, same resolved
  path or same inode, hard links included) is refused even with ``overwrite``.
* **Never through a symbolic link.** A link at the output name is refused; with ``overwrite`` the
  link itself is replaced by the new file and its target is left untouched.
* **Atomic.** The data go to a hidden temporary file in the same folder, are flushed to disk
  (``fsync``) and renamed onto the final name; readers never see a partial file, and a failure
  (disk full, Ctrl-C) leaves the old file, or none, and no temporary file.

The command line sets the policy once per command with :func:`write_policy` (``--overwrite``
and the command's inputs); library code passes ``overwrite=`` explicitly or inherits that policy.
:func:`folder_lock` keeps two batch runs out of one output folder.

>>> import tempfile, pathlib
>>> with tempfile.TemporaryDirectory() as d:
...     p = pathlib.Path(d, "a.txt")
...     atomic_write_text(p, "one")
...     try:
...         atomic_write_text(p, "two", overwrite=False)
...     except FileExistsError as exc:
...         print("refused")
...     atomic_write_text(p, "three", overwrite=True)
...     print(p.read_text())
refused
three
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import re
import stat
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import HsiffcError

__all__ = ["FileSet", "OutputError", "OutputExistsError", "WritePolicy",
           "atomic_path", "atomic_write_bytes", "atomic_write_text", "check_output",
           "check_output_folder", "current_policy", "file_kind",
           "protect_inputs", "require_regular_input", "require_private_file", "write_policy"]

PART_SUFFIX = ".part"


class OutputError(HsiffcError, OSError):
    """An output file cannot or must not be written (the message says why and what to do).

    Examples
    --------
    >>> import tempfile
    >>> try:
    ...     check_output(tempfile.mkdtemp())          # a folder is not a file name
    ... except OutputError as exc:
    ...     print(str(exc).split(": ", 1)[1])
    is a folder; give a file name (the folder was left as it was)
    """


class OutputExistsError(OutputError, FileExistsError):
    """The output exists and replacing it was not asked for.

    Also a :class:`FileExistsError`, so code that catches that one catches it too.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> out = Path(tempfile.mkdtemp()) / "notes.txt"
    >>> _ = out.write_text("kept")                    # a file hsiffc did not write
    >>> try:
    ...     check_output(out)
    ... except FileExistsError as exc:
    ...     print(type(exc).__name__, out.read_text())
    OutputExistsError kept
    """


# -- file kinds: the one place that says whether a path is a regular file we may touch --------
def file_kind(st: os.stat_result) -> str:
    """What a ``stat``/``lstat`` result describes, in words ("a regular file", "a named pipe
    (FIFO)", "a character device", ...)."""
    mode = st.st_mode
    for test, words in ((stat.S_ISREG, "a regular file"), (stat.S_ISDIR, "a folder"),
                        (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
                        (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                        (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return words
    return "not a regular file"


def require_regular_input(path, *, what: str = "input") -> os.stat_result:
    """Check, without opening it, that ``path`` is a regular file hsiffc may read.

    A named pipe, device or socket given (or found) where a file is expected is refused before
    anything opens it: opening a FIFO blocks until a writer comes, and ``/dev/zero`` never
    ends. A symbolic link to a regular file is read (it is an input, never written).

    Parameters
    ----------
    path : path-like
    what : str
        What the file is (for the message), e.g. "EMVA 1288 descriptor".

    Returns
    -------
    os.stat_result
        The file's ``stat`` (sizes checked against it need no second call).

    Raises
    ------
    DataFormatError
        Missing, or not a regular file; one line naming the file and what it is.
    """
    from ..errors import DataFormatError

    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise DataFormatError(f"{what} not found; check the path", path=path) from None
    except OSError as exc:
        raise DataFormatError(f"cannot read this {what} ({exc.strerror}); check the path and "
                              "its permissions", path=path) from None
    if not stat.S_ISREG(st.st_mode):
        raise DataFormatError(f"is {file_kind(st)}, not a regular file; hsiffc reads the {what} "
                              "only from a regular file (it never opens pipes, devices or "
                              "sockets): give a file", path=path)
    return st


def require_private_file(path, st: os.stat_result, *, what: str) -> None:
    """Refuse to write into an existing file unless it is a regular file with one name.

    hsiffc writes its outputs as new files and renames them (a hard link elsewhere keeps the
    old data); the few files it opens and writes in place (the batch folder lock) must be
    regular files with a single name (``st_nlink == 1``), so that a hard link to an input, a
    FIFO or a device planted at that name is never written into.

    Parameters
    ----------
    path : path-like
        The name (for the message).
    st : os.stat_result
        ``lstat`` of the name, or ``fstat`` of the file opened at it.
    what : str
        What hsiffc wanted to write (for the message).

    Raises
    ------
    OutputError
        Not a regular file, or a file with more than one name.
    """
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{path}: is {file_kind(st)}, not the {what} hsiffc writes; hsiffc "
                          "never writes into it: remove it (or choose another output folder)")
    if st.st_nlink != 1:
        raise OutputError(f"{path}: is a hard link ({st.st_nlink} names for one file, e.g. an "
                          f"input), not the {what} hsiffc writes; hsiffc never writes into it: "
                          "remove this name (the other names keep the data) or choose another "
                          "output folder")


# -- the policy -------------------------------------------------------------------------------
def _keys(path) -> set:
    """Identities of a path: its absolute name, its resolved name and its (device, inode)."""
    p = Path(path)
    keys = {("name", os.path.abspath(p))}
    with contextlib.suppress(OSError, RuntimeError):
        keys.add(("name", str(p.resolve())))
    with contextlib.suppress(OSError):
        st = os.stat(p)
        keys.add(("inode", st.st_dev, st.st_ino))
    return keys


@dataclass
class WritePolicy:
    """What the writer may do in the running command.

    Attributes
    ----------
    overwrite : bool
        Replace existing files (``--overwrite``).
    inputs : set
        Identities (names, resolved names, inodes) of the command's inputs: never written.
    written : set
        Absolute names this policy's writes produced (they may be written again).
    """

    overwrite: bool = False
    inputs: set = field(default_factory=set)
    written: set = field(default_factory=set)

    def protect(self, paths) -> None:
        """Add ``paths`` (path-likes; None entries ignored) to the inputs."""
        for p in paths:
            if p is not None:
                self.inputs |= _keys(p)


_DEFAULT = WritePolicy()
_POLICY: contextvars.ContextVar[WritePolicy | None] = contextvars.ContextVar(
    "hsiffc_write_policy", default=None)


def current_policy() -> WritePolicy:
    """The policy in force (the process default when no :func:`write_policy` is active)."""
    return _POLICY.get() or _DEFAULT


@contextlib.contextmanager
def write_policy(*, overwrite: bool = False, inputs=()):
    """Run a block under one write policy (the CLI wraps each command in one).

    Parameters
    ----------
    overwrite : bool
        Writes that do not say ``overwrite=`` themselves replace existing files.
    inputs : iterable of path-like
        The command's inputs: no write inside the block may replace them.

    Examples
    --------
    A tool that reads ``raw.txt`` and writes ``notes.txt``, replacing old notes but never its
    input:

    >>> import tempfile
    >>> from pathlib import Path
    >>> folder = Path(tempfile.mkdtemp())
    >>> raw, notes = folder / "raw.txt", folder / "notes.txt"
    >>> _ = raw.write_text("data"); _ = notes.write_text("old notes")
    >>> with write_policy(overwrite=True, inputs=[raw]):
    ...     atomic_write_text(notes, "new notes")     # replaced: overwrite is the default here
    ...     try:
    ...         atomic_write_text(raw, "oops", overwrite=True)
    ...     except OutputError:
    ...         print("refused:", raw.read_text())
    refused: data
    >>> notes.read_text()
    'new notes'
    """
    policy = WritePolicy(overwrite=bool(overwrite))
    policy.protect(inputs)
    token = _POLICY.set(policy)
    try:
        yield policy
    finally:
        _POLICY.reset(token)


@contextlib.contextmanager
def protect_inputs(paths):
    """Protect ``paths`` (e.g. the files a batch discovered) as inputs inside the block.

    Under a :func:`write_policy` (a CLI command) they stay protected until that policy ends,
    so the command's later writes (its ``--json``) cannot replace them either; without one
    (library use) only inside the block.
    """
    policy = current_policy()
    added = set()
    for p in paths:
        if p is not None:
            added |= _keys(p)
    added -= policy.inputs
    policy.inputs |= added
    try:
        yield
    finally:
        if _POLICY.get() is None:
            policy.inputs -= added


# -- checks -----------------------------------------------------------------------------------
def _allowed(path: Path, overwrite: bool | None, policy: WritePolicy) -> bool:
    """May an existing ``path`` be replaced? An explicit ``overwrite`` decides; otherwise the
    policy's, or whether this policy wrote ``path`` itself."""
    if overwrite is not None:
        return bool(overwrite)
    return policy.overwrite or os.path.abspath(path) in policy.written


def check_output(path, *, overwrite: bool | None = None, inputs=()) -> Path:
    """Check that ``path`` may be written, without writing anything; returns it as a Path.

    Parameters
    ----------
    path : path-like
        The final file name.
    overwrite : bool or None
        Replace an existing file (None: as the policy in force says).
    inputs : iterable of path-like
        Inputs besides the policy's that must not be written.

    Raises
    ------
    OutputError
        ``path`` is an input, a folder, a device, pipe or socket, or a symbolic link (without
        ``overwrite``).
    OutputExistsError
        ``path`` exists and ``overwrite`` is false.

    Examples
    --------
    Check every output name before the work starts, so that a refusal costs nothing:

    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> check_output(folder / "cube.tif").name
    'cube.tif'
    >>> _ = (folder / "old.tif").write_bytes(b"")
    >>> try:
    ...     check_output(folder / "old.tif")
    ... except OutputExistsError:
    ...     print("exists: pass overwrite=True to replace it")
    exists: pass overwrite=True to replace it
    """
    path = Path(path)
    policy = current_policy()
    allowed = _allowed(path, overwrite, policy)
    protected = set(policy.inputs)
    for p in inputs:
        protected |= _keys(p)
    if _keys(path) & protected:
        raise OutputError(f"{path}: is an input of this command; hsiffc never writes over an "
                          "input (not even with --overwrite): choose another output name")
    if os.path.islink(path):
        if not allowed:
            raise OutputError(f"{path}: is a symbolic link (to {os.readlink(path)}); hsiffc "
                              "never writes through a link: choose another name, or pass "
                              "--overwrite to replace the link itself (its target is kept)")
        return path
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; give a file name (the folder was left as it "
                          "was)")
    try:
        st = os.lstat(path)
    except OSError:
        st = None
    if st is not None and not stat.S_ISREG(st.st_mode):
        # a FIFO, socket or device node: renaming a file onto it would replace the node
        # itself (as root, /dev/full or /dev/stdout for every process), never write into it
        raise OutputError(f"{path}: is {file_kind(st)}, not a regular file (a device, pipe "
                          "or socket); hsiffc writes outputs as new files and never "
                          "replaces such a node, even with --overwrite: give a file name")
    if os.path.lexists(path) and not allowed:
        raise OutputExistsError(f"{path}: already exists; pass --overwrite (in Python: "
                                "overwrite=True) to replace it, or choose another name (the "
                                "existing file was left unchanged)")
    return path


def _named(exc: OSError, path: Path, tmp: Path) -> OSError:
    """``exc`` naming the final file (never the hidden temporary one, never no file)."""
    if exc.filename is not None and os.fspath(exc.filename) != os.fspath(tmp):
        return exc
    if isinstance(exc, HsiffcError):
        return exc
    if exc.errno is None:  # e.g. numpy's "N requested and M written": a short write
        if _SHORT_WRITE.search(str(exc)):
            return OSError(errno.ENOSPC, f"the write stopped short ({exc}): the disk or the "
                           "quota is most likely full", str(path))
        new = OSError(str(exc))
        new.strerror, new.filename = str(exc), str(path)
        return new
    new = type(exc)(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))
    return new


_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")


# -- writing ----------------------------------------------------------------------------------
@contextlib.contextmanager
def _removed_on_error(tmp: Path, path: Path):
    """On any error remove the temporary file ``tmp``; an OSError is raised again naming the
    final file ``path`` (never the hidden temporary one)."""
    try:
        yield
    except OSError as exc:
        _remove(tmp)
        named = _named(exc, path, tmp)
        if named is exc:
            raise
        raise named from exc
    except BaseException:
        _remove(tmp)
        raise


def _remove(tmp: Path) -> None:
    """Remove a temporary file if it is there; an error doing so (its folder is a file, or
    was never made) never hides the error that is being reported."""
    with contextlib.suppress(OSError):
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(path, *, overwrite: bool | None = None, inputs=(), defer=None, fileset=None):
    """Yield a hidden temporary path beside ``path``; on success move it onto ``path``.

    The caller writes the temporary file (by name or by reopening it). Afterwards it is
    fsynced and renamed onto ``path``, and the folder is fsynced so the rename is durable.
    On any exception the temporary file is removed and ``path`` is left as it was. The checks
    of :func:`check_output` run before anything is written and again at the rename.

    Parameters
    ----------
    path : path-like
        Final file name. Its folder is created if missing.
    overwrite : bool or None
        Replace an existing file (or a symbolic link itself, never its target). None: as the
        policy in force says (:func:`write_policy`; by default no).
    inputs : iterable of path-like
        Files that must not be written besides the policy's inputs.
    defer : :class:`hsiffc.batch.commits.DeferredCommits`, optional
        Hand the fsync and rename (``defer.submit(path, fn, *args)``) to a committer's thread
        instead of waiting for them here; ``defer.wait(path)`` then says whether they
        succeeded.
    fileset : FileSet, optional
        Keep the written temporary file in this set instead of renaming it now: the set
        renames all its files in :meth:`FileSet.commit` (or removes them all,
        :meth:`FileSet.abort`).

    Raises
    ------
    OutputError, OutputExistsError
        See :func:`check_output`.
    OSError
        Writing failed (permission, disk full, ...); it names ``path``.

    Examples
    --------
    Any writer that takes a file name (numpy, tifffile, matplotlib ...) writes the temporary
    file; the final name appears only when the block ends without an error:

    >>> import tempfile
    >>> import numpy as np
    >>> out = Path(tempfile.mkdtemp()) / "offsets.npy"
    >>> with atomic_path(out) as tmp:
    ...     with open(tmp, "wb") as f:
    ...         np.save(f, np.arange(3))
    ...     print(out.exists())                       # not yet at the final name
    False
    >>> np.load(out).tolist()
    [0, 1, 2]
    """
    path = Path(path)
    inputs = list(inputs)
    check_output(path, overwrite=overwrite, inputs=inputs)
    policy = current_policy()
    allowed = _allowed(path, overwrite, policy)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}{PART_SUFFIX}")
    with _removed_on_error(tmp, path):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except FileExistsError as exc:  # a file where the folder should be
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR),
                                     exc.filename or str(path.parent)) from None
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0),
                     0o666)
        os.close(fd)
        yield tmp
    if fileset is not None:
        fileset.stage(path, tmp, _commit, overwrite, inputs, allowed, policy)
    elif defer is not None:  # the same steps, in this context, on the committer's thread
        defer.submit(path, contextvars.copy_context().run, _commit, tmp, path, overwrite,
                     inputs, allowed, policy)
    else:
        _commit(tmp, path, overwrite, inputs, allowed, policy)


def _commit(tmp: Path, path: Path, overwrite, inputs, allowed: bool, policy,
            sync_folder: bool = True) -> None:
    """The end of :func:`atomic_path`: fsync the written temporary file, check ``path`` again
    (it may have changed), rename, fsync the folder; on error remove the temporary file."""
    with _removed_on_error(tmp, path):
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        check_output(path, overwrite=overwrite, inputs=inputs)  # again: it may have changed
        if allowed:
            os.replace(tmp, path)  # replaces a link itself, never its target
        else:
            _rename_no_replace(tmp, path)
    policy.written.add(os.path.abspath(path))
    if sync_folder:
        _fsync_folder(path.parent)


class FileSet:
    """Files written as one product (an ENVI cube with its DQ and alpha companions, the cubes
    of every frame of an input): each is written to its own temporary file by
    :func:`atomic_path` (``fileset=``) and none is renamed onto its name before
    :meth:`commit`, which renames them all (headers first: an ENVI data file is never put
    in place without the header that says whose it is) and makes the renames durable.

    POSIX renames one file at a time, so a kill during :meth:`commit` can leave some files of
    the new set beside files of an older one; a reader of the set (the batch's resume check)
    therefore checks that every file of it says the same run (hsiffc's cube files record it),
    and redoes the set otherwise. Before :meth:`commit` a kill leaves only hidden temporary
    files (``.NAME.*.part``), which the next batch in that folder removes.

    Examples
    --------
    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> files = FileSet()
    >>> for name in ("a.img", "a.hdr"):
    ...     with atomic_path(folder / name, fileset=files) as tmp:
    ...         _ = Path(tmp).write_text(name)
    >>> sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))
    []
    >>> files.commit()
    >>> sorted(p.name for p in folder.iterdir())
    ['a.hdr', 'a.img']
    """

    def __init__(self):
        self._staged: dict[Path, tuple] = {}

    def stage(self, path, tmp, commit, *args) -> None:
        """Keep ``tmp`` (the written temporary file of ``path``) until :meth:`commit` runs
        ``commit(tmp, path, *args)`` (:func:`atomic_path` calls this)."""
        path = Path(path)
        if path in self._staged:  # written twice: the first version is dropped
            _remove(self._staged[path][0])
        self._staged[path] = (Path(tmp), commit, args)

    def temp(self, path) -> Path:
        """The temporary file that holds ``path`` until :meth:`commit` (to finish it in
        place, e.g. the provenance known only at the end)."""
        return self._staged[Path(path)][0]

    @property
    def paths(self) -> list[Path]:
        """The final names of the staged files, in the order they were written."""
        return list(self._staged)

    def commit(self) -> None:
        """Rename every staged file onto its name (ENVI headers first), then fsync their
        folders; an error removes every temporary file not yet renamed and is raised."""
        order = sorted(self._staged, key=lambda p: p.suffix.lower() != ".hdr")
        try:
            for path in order:
                tmp, commit, args = self._staged[path]
                commit(tmp, path, *args, sync_folder=False)
                del self._staged[path]
        finally:
            self.abort()
        for folder in dict.fromkeys(p.parent for p in order):
            _fsync_folder(folder)

    def abort(self) -> None:
        """Remove every temporary file not yet renamed."""
        for tmp, _, _ in self._staged.values():
            _remove(tmp)
        self._staged.clear()


def _rename_no_replace(tmp: Path, path: Path) -> None:
    """Rename ``tmp`` onto ``path`` only if ``path`` does not exist (atomically where the file
    system has hard links; elsewhere check, then rename)."""
    try:
        os.link(tmp, path, follow_symlinks=False)
    except FileExistsError:
        raise OutputExistsError(f"{path}: appeared while it was being written; pass --overwrite "
                                "to replace it (the file that appeared was left unchanged)"
                                ) from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV,
                             errno.EMLINK, errno.ENOSYS):
            raise
        if os.path.lexists(path):
            raise OutputExistsError(f"{path}: appeared while it was being written; pass "
                                    "--overwrite to replace it") from None
        os.replace(tmp, path)
        return
    tmp.unlink()


def _fsync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):  # make the rename durable (POSIX)
        dir_fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def atomic_write_text(path, text: str, *, overwrite: bool | None = None, inputs=()) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8); rules of :func:`atomic_path`.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "report.md"
    >>> atomic_write_text(out, "# Report")
    >>> atomic_write_text(out, "# Report, updated")    # this process wrote it: allowed
    >>> out.read_text()
    '# Report, updated'
    """
    with atomic_path(path, overwrite=overwrite, inputs=inputs) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def atomic_write_bytes(path, data: bytes, *, overwrite: bool | None = None, inputs=()) -> None:
    """Write ``data`` to ``path`` atomically; rules of :func:`atomic_path`.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp()) / "frame.raw"
    >>> atomic_write_bytes(out, b"P5 2 1 255 ")
    >>> out.read_bytes()
    b'P5 2 1 255 '
    """
    with atomic_path(path, overwrite=overwrite, inputs=inputs) as tmp:
        Path(tmp).write_bytes(data)


def check_output_folder(folder, *, overwrite: bool | None = None, inputs=()) -> Path:
    """Check that a report may be written into ``folder`` (created later if missing).

    A folder that already holds visible files is refused without ``overwrite``, before any
    work is done, so a report is never half replaced.

    Raises
    ------
    OutputError
        ``folder`` is a file, a symbolic link (without ``overwrite``) or an input.
    OutputExistsError
        ``folder`` holds files and ``overwrite`` is false.
    """
    folder = Path(folder)
    policy = current_policy()
    allowed = policy.overwrite if overwrite is None else bool(overwrite)
    protected = set(policy.inputs)
    for p in inputs:
        protected |= _keys(p)
    if _keys(folder) & protected:
        raise OutputError(f"{folder}: is an input of this command; choose another output folder")
    if os.path.islink(folder) and not allowed:
        raise OutputError(f"{folder}: is a symbolic link; give the real folder, or pass "
                          "--overwrite to write into the folder it points to")
    if os.path.lexists(folder) and not folder.is_dir():
        raise OutputError(f"{folder}: is a file, not a folder; give a folder name")
    if folder.is_dir() and not allowed:
        held = sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))
        if held:
            shown = ", ".join(held[:3]) + (", ..." if len(held) > 3 else "")
            raise OutputExistsError(f"{folder}: already holds files ({shown}); pass --overwrite "
                                    "to replace them, or choose an empty or new folder")
    return folder
