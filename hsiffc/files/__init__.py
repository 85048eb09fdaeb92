"""Safe file handling, used by every layer that reads or writes: none of it is physics.

The public face is what a tool of your own needs to write files the way hsiffc does (the rules
are on the safety page): atomic writes that never replace an input, a link or an existing file
unless asked, and the output folder's lock.

- :func:`atomic_path`, :func:`atomic_write_text`, :func:`atomic_write_bytes`: write through a
  temporary file renamed into place;
- :func:`check_output`: the same checks, without writing (check every name before the work);
- :func:`write_policy`: a block with one rule for existing files and the inputs never written;
- :func:`folder_lock`: keep two runs out of one output folder;
- :class:`OutputError`, :class:`OutputExistsError` (also a :class:`FileExistsError`),
  :class:`FolderLockedError`: what they raise.

The modules: :mod:`.atomic` (the writer and the checks of what kind of file a path is) and
:mod:`.folderlock` are public. :mod:`.limits` (the size limits applied to every header before
anything is decoded, raised through environment variables: see the safety page; its
``ReadLimits`` is public as :class:`hsiffc.io.ReadLimits`), :mod:`.parsers` (the one guarded
JSON and TOML parser) and :mod:`.jsonsafe` (values made JSON-safe for manifests) serve hsiffc's
own readers and writers: their API may change.

This layer imports only :mod:`hsiffc.errors`.

Examples
--------
>>> import tempfile
>>> from pathlib import Path
>>> from hsiffc.files import atomic_write_text, folder_lock
>>> out = Path(tempfile.mkdtemp()) / "results"
>>> with folder_lock(out, what="my-tool"):
...     atomic_write_text(out / "summary.txt", "3 frames corrected")
>>> (out / "summary.txt").read_text()
'3 frames corrected'
"""

from .atomic import (OutputError, OutputExistsError, atomic_path, atomic_write_bytes,
                     atomic_write_text, check_output, write_policy)
from .folderlock import FolderLockedError, folder_lock

__all__ = ["atomic_path", "atomic_write_text", "atomic_write_bytes", "check_output",
           "write_policy", "folder_lock", "OutputError", "OutputExistsError",
           "FolderLockedError"]
