"""Safe file handling, used by every layer that reads or writes: none of it is physics.

- :mod:`.atomic` - every write goes through a temporary file renamed into place, never over an
  input, a link or an existing file unless asked; what kind of file a path is (regular, FIFO,
  device, hard-linked) before it is opened;
- :mod:`.folderlock` - the output folder's lock of a batch;
- :mod:`.limits` - the size limits applied to every header before anything is decoded
  (raised through environment variables: see the safety page);
- :mod:`.parsers` - the one guarded JSON and TOML parser (syntax and nesting depth);
- :mod:`.jsonsafe` - values made JSON-safe for manifests and reports.

This layer imports only :mod:`hsiffc.errors`.
"""
