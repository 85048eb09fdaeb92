"""Hostile and unusual inputs, round three (issue 52): one test per cause.

Each test names the cause it covers; each failed before its fix.
"""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from hsiffc.cli import main
from hsiffc.io.corrected import read_provenance
from test_hostile_inputs import sweep  # noqa: F401  (the module's simulated sweep + calibration)
from test_cli_bad_input import _one_line  # the one checker of one-line errors


# -- cause: the resume identity left out the metadata sources' content ---------------------------
def test_resume_redoes_an_output_whose_sidecar_changed(sweep, tmp_path, capsys):
    """A sidecar's exposure changed from 12 to 24 ms: the rerun redoes the file (it used to
    say "0 done, 1 skipped" and keep the old exposure); an unchanged rerun still skips, and a
    sidecar added next to the input later redoes it too."""
    from hsiffc.io import read_sweep

    data = read_sweep(sweep / "s.tif").data
    raw = tmp_path / "in"
    raw.mkdir()
    tifffile.imwrite(raw / "plain.tif", data, photometric="minisblack")
    side = raw / "hsiffc.toml"
    side.write_text("[defaults]\nexposure_ms = 12\nbit_depth = 10\n")
    out = tmp_path / "out"
    argv = ["correct", str(raw / "plain.tif"), "--calibration", str(sweep / "cal.npz"),
            "-o", str(out)]
    assert main(argv) == 0
    made = out / "plain.corrected.tif"
    assert read_provenance(made)["exposure"][0] == 12.0
    capsys.readouterr()
    assert main(argv) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out
    side.write_text("[defaults]\nexposure_ms = 24\nbit_depth = 10\n")
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "1 done, 0 skipped" in text
    assert read_provenance(made)["exposure"][0] == 24.0
    sources = read_provenance(made)["input"]["metadata_sources"]
    assert [src["path"] for src in sources] == [str(side)]
    # a sidecar that is gone: redone (here it fails, as the exposure is nowhere now)
    side.unlink()
    assert main(argv) == 1

