"""The one writer (hsiffc.files.atomic): no silent replacement, never an input, never through a
symbolic link, atomic, named errors, and the batch folder lock."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import textwrap

import pytest

from hsiffc.files import atomic
from hsiffc.files.atomic import (
    OutputError,
    OutputExistsError,
    atomic_path,
    atomic_write_text,
    check_output_folder,
    write_policy,
)
from hsiffc.files.folderlock import FolderLockedError, folder_lock
from hsiffc.errors import HsiffcError


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".part"))


def test_existing_file_is_refused_unless_overwrite(tmp_path):
    p = tmp_path / "a.json"
    p.write_text("keep")
    with pytest.raises(OutputExistsError, match="--overwrite") as info:
        atomic_write_text(p, "new")
    assert isinstance(info.value, FileExistsError) and isinstance(info.value, HsiffcError)
    assert p.read_text() == "keep" and not _leftovers(tmp_path)
    atomic_write_text(p, "new", overwrite=True)
    assert p.read_text() == "new"


def test_policy_decides_when_the_call_does_not(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("keep")
    with write_policy(overwrite=True):
        atomic_write_text(p, "replaced")
        with pytest.raises(OutputExistsError):
            atomic_write_text(p, "explicit no", overwrite=False)  # an explicit answer wins
    assert p.read_text() == "replaced"


def test_a_file_the_command_wrote_may_be_written_again(tmp_path):
    p = tmp_path / "summary.json"
    with write_policy(overwrite=False):
        atomic_write_text(p, "first")
        atomic_write_text(p, "final")  # e.g. a summary updated at the end of the run
    assert p.read_text() == "final"
    with write_policy(overwrite=False), pytest.raises(OutputExistsError):
        atomic_write_text(p, "another command")  # a new command did not write it
    assert p.read_text() == "final"


def test_symlink_is_never_written_through(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    link = tmp_path / "out.txt"
    link.symlink_to(victim)
    with pytest.raises(OutputError, match="symbolic link"):
        atomic_write_text(link, "evil")
    assert victim.read_text() == "precious" and link.is_symlink()
    atomic_write_text(link, "mine", overwrite=True)  # replaces the link itself
    assert not link.is_symlink() and link.read_text() == "mine"
    assert victim.read_text() == "precious"


def test_dangling_symlink_is_refused_too(tmp_path):
    link = tmp_path / "out.txt"
    link.symlink_to(tmp_path / "elsewhere" / "target.txt")
    with pytest.raises(OutputError, match="symbolic link"):
        atomic_write_text(link, "x")
    assert not (tmp_path / "elsewhere").exists()


@pytest.mark.parametrize("how", ["same", "relative", "symlink", "hardlink"])
def test_an_input_is_never_written_even_with_overwrite(tmp_path, monkeypatch, how):
    inp = tmp_path / "in.tif"
    inp.write_bytes(b"input data")
    monkeypatch.chdir(tmp_path)
    out = {"same": inp, "relative": "in.tif", "symlink": tmp_path / "ln.tif",
           "hardlink": tmp_path / "hard.tif"}[how]
    if how == "symlink":
        (tmp_path / "ln.tif").symlink_to(inp)
    if how == "hardlink":
        os.link(inp, tmp_path / "hard.tif")
    with write_policy(overwrite=True, inputs=[inp]), \
            pytest.raises(OutputError, match="input of this command"):
        atomic_write_text(out, "x")
    with pytest.raises(OutputError, match="input of this command"):
        atomic_write_text(out, "x", overwrite=True, inputs=[inp])
    assert inp.read_bytes() == b"input data"


def test_folder_as_output_is_refused(tmp_path):
    with pytest.raises(OutputError, match="is a folder"):
        atomic_write_text(tmp_path, "x", overwrite=True)


def test_failure_while_writing_leaves_old_file_and_no_temporary(tmp_path):
    p = tmp_path / "a.bin"
    p.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(p, overwrite=True) as tmp:
        tmp.write_bytes(b"partial")
        raise RuntimeError("boom")
    assert p.read_bytes() == b"old" and not _leftovers(tmp_path)


def test_disk_full_names_the_final_file(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    p = tmp_path / "cal.npz"
    with pytest.raises(OSError) as info:
        atomic_write_text(p, "x" * 1000)
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(p)
    assert not p.exists() and not _leftovers(tmp_path)


def test_a_short_write_without_errno_is_named_as_a_full_disk(tmp_path):
    # numpy's tofile on a full disk raises OSError("N requested and M written"): no errno,
    # no file name; it reached the user as "a file: 524288 requested and 44216 written"
    p = tmp_path / "cube.tif"
    with pytest.raises(OSError) as info, atomic.atomic_path(p):
        raise OSError("524288 requested and 44216 written")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(p)
    assert "44216 written" in info.value.strerror and "full" in info.value.strerror
    assert not p.exists() and not _leftovers(tmp_path)
    with pytest.raises(OSError) as info, atomic.atomic_path(p):
        raise OSError("something else went wrong")
    assert info.value.filename == str(p) and info.value.errno is None
    assert info.value.strerror == "something else went wrong"


def test_permission_error_names_the_final_file_not_the_temporary(tmp_path, monkeypatch):
    real_open = os.open

    def denied(path, *a, **k):
        if str(path).endswith(".part"):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *a, **k)

    monkeypatch.setattr(atomic.os, "open", denied)
    with pytest.raises(PermissionError) as info:
        atomic_write_text(tmp_path / "out.json", "{}")
    assert info.value.filename == str(tmp_path / "out.json")


def test_file_appearing_while_writing_is_not_replaced(tmp_path):
    p = tmp_path / "race.txt"
    with pytest.raises(OutputExistsError), atomic_path(p, overwrite=False) as tmp:
        tmp.write_text("mine")
        p.write_text("theirs")  # another program creates it meanwhile
    assert p.read_text() == "theirs" and not _leftovers(tmp_path)


def test_report_folder_holding_files_is_refused_up_front(tmp_path):
    check_output_folder(tmp_path / "new")  # missing: fine
    (tmp_path / "old").mkdir()
    check_output_folder(tmp_path / "old")  # empty: fine
    (tmp_path / "old" / "report.md").write_text("x")
    with pytest.raises(OutputExistsError, match="report.md"):
        check_output_folder(tmp_path / "old")
    check_output_folder(tmp_path / "old", overwrite=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a folder"):
        check_output_folder(tmp_path / "file", overwrite=True)


def test_folder_lock_refuses_a_second_holder_and_names_the_first(tmp_path):
    script = textwrap.dedent(f"""
        import sys, time
        from hsiffc.files.folderlock import folder_lock
        with folder_lock({str(tmp_path)!r}, what="hsiffc correct"):
            print("locked", flush=True)
            sys.stdin.readline()
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(FolderLockedError) as info, folder_lock(tmp_path):
            pass
        msg = str(info.value)
        assert f"pid {proc.pid}" in msg and "started" in msg and "host" in msg
    finally:
        proc.stdin.write("\n")
        proc.stdin.close()
        proc.wait(timeout=30)
    with folder_lock(tmp_path) as me:  # released when the holder ends
        assert json.loads((tmp_path / ".hsiffc.lock").read_text())["pid"] == me["pid"]


def test_golden_regeneration_replaces_the_file_on_purpose(tmp_path):
    """``regenerate=True`` (``pytest --regen-golden``) is the explicit ask to replace."""
    import numpy as np

    from hsiffc.testing import assert_golden

    assert_golden("case", {"a": np.zeros(3)}, golden_dir=tmp_path, regenerate=True)
    assert_golden("case", {"a": np.ones(3)}, golden_dir=tmp_path, regenerate=True)
    assert_golden("case", {"a": np.ones(3)}, golden_dir=tmp_path)


def test_protected_inputs_last_for_the_command_not_for_the_process(tmp_path):
    from hsiffc.files.atomic import protect_inputs

    raw = tmp_path / "raw.tif"
    raw.write_bytes(b"raw")
    with protect_inputs([raw]), pytest.raises(OutputError, match="input"):
        atomic_write_text(raw, "x", overwrite=True)
    atomic_write_text(raw, "library use: free again", overwrite=True)
    with write_policy(overwrite=True):
        with protect_inputs([raw]):
            pass
        with pytest.raises(OutputError, match="input"):  # still the same command
            atomic_write_text(raw, "x")
    assert raw.read_text() == "library use: free again"


def test_deferred_commit_puts_the_file_in_place_only_when_done(tmp_path):
    """With defer=, the fsync and rename run on the committer's thread: the file appears once
    its commit ran; the write policy in force at the write is the one the commit checks; a
    commit that fails (the name appeared meanwhile) leaves the other file, removes the
    temporary one and says so through wait() and, in a batch, settle()."""
    import threading

    from hsiffc.batch.commits import DeferredCommits
    from hsiffc.batch.task import settle

    gate = threading.Event()
    out, other = tmp_path / "out.txt", tmp_path / "other.txt"
    other.write_text("old")
    with DeferredCommits() as commits:
        commits.submit("gate", gate.wait)  # holds the committer until the test lets it go
        with atomic_path(out, defer=commits) as tmp:
            tmp.write_text("new")
        with write_policy(overwrite=True):
            with atomic_path(other, defer=commits) as tmp:
                tmp.write_text("replaced")
        assert not out.exists() and commits.pending(out)
        assert other.read_text() == "old"  # not before its commit
        gate.set()
        commits.wait(out)
        commits.wait(other)
        assert out.read_text() == "new" and other.read_text() == "replaced"
        assert _leftovers(tmp_path) == []

        late = tmp_path / "late.txt"
        gate.clear()
        commits.submit("gate2", gate.wait)
        with atomic_path(late, defer=commits) as tmp:
            tmp.write_text("mine")
        late.write_text("someone else's")  # appears before the commit runs
        gate.set()
        res = {"status": "done", "output": str(late), "input": "in.tif", "frames": 3}
        settle(res, commits)
        assert res["status"] == "failed" and "late.txt" in res["reason"]
        assert late.read_text() == "someone else's" and _leftovers(tmp_path) == []
