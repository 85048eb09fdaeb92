"""One or two examples at the end of every command's ``--help`` (and so in the generated
command-line reference).

The examples are in one table so that a test can parse every one of them with the real parser
(a renamed option fails it) and check every command has some. They use the bundled sample
cubes and the file names the guides use, so that a reader can run them from the repository
root in the order given.
"""

from __future__ import annotations

import argparse

__all__ = ["EXAMPLES", "ExamplesFormatter", "add_examples", "give_examples"]

#: command (``"reflectance fit"`` for an action) -> example command lines
EXAMPLES: dict[str, tuple[str, ...]] = {
    "demo": ("hsiffc demo sample_cubes",
             "hsiffc demo sample_cubes -o my-demo"),
    "paper": ("hsiffc paper paper-report",
              "hsiffc paper paper-report --no-emva --threshold 8 --overwrite"),
    "diagnose": ("hsiffc diagnose sample_cubes/sweep_2900K.tif --report diagnosis",
                 "hsiffc diagnose --list-effects"),
    "info": ("hsiffc info sample_cubes/sweep_2900K.tif --json info.json",
             "hsiffc info corrected/test_2200K.corrected.tif"),
    "simulate": ("hsiffc simulate sim.tif --exposures-ms 5 10 20 --lamp 2900K",
                 "hsiffc simulate sweep.tif --exposures-ms 2 4 8 16 32 --frames 2 --seed 3"),
    "calibrate": ("hsiffc calibrate sample_cubes/sweep_2900K.tif -o cal.npz",
                  "hsiffc calibrate sweep/ -o cal.npz --json cal.json --mosaic 5x5"),
    "select": ("hsiffc select sample_cubes/training_2900K.tif --calibration cal.npz "
               "--threshold 12 --json sel.json",),
    "stages": ("hsiffc stages",
               "hsiffc stages --json stages.json"),
    "fit": ("hsiffc fit examples/pipeline.toml sample_cubes/training_2900K.tif "
            "sample_cubes/darks.tif -o pipeline.npz",),
    "correct": ("hsiffc correct --calibration cal.npz raw/ -o corrected/",
                "hsiffc correct --pipeline pipeline.npz 'raw/day*/cube_*.tif' -o corrected/"),
    "reflectance fit": ("hsiffc reflectance fit --dark refs/dark_*.tif --white "
                        "refs/white_*.tif --panel 0.99 -o refl.npz",),
    "reflectance check": ("hsiffc reflectance check grey/ --pipeline refl.npz --expected 0.5",),
    "quicklook": ("hsiffc quicklook corrected/scene.corrected.tif -o scene.png",),
    "import": ("hsiffc import raw/*.png -o sweep.tif --exposure-ms 10 --bit-depth 10",),
    "uniformity": ("hsiffc uniformity sample_cubes/test_2200K.tif --calibration cal.npz "
                   "--json u.json",
                   "hsiffc uniformity sweep.tif --calibration cal.npz --json u.json --plot u.png"),
    "study-ffc": ("hsiffc study-ffc ffc-study",),
    "emva1288": ("hsiffc emva1288 ../shared/data/emva1288-cmos8-roi --json cmos.json "
                 "--report cmos-report",
                 "hsiffc emva1288 my-camera/ --json fig.json --no-leakage"),
}

_MARK = "examples:\n"


class ExamplesFormatter(argparse.HelpFormatter):
    """argparse's formatter, except that an epilog starting with ``examples:`` keeps its lines
    (one command per line, never re-wrapped into a paragraph)."""

    def _fill_text(self, text, width, indent):
        if text.startswith(_MARK):
            return "\n".join(indent + line for line in text.splitlines())
        return super()._fill_text(text, width, indent)


def epilog(command: str) -> str | None:
    """The ``examples:`` epilog of ``command`` (None when the table has none)."""
    lines = EXAMPLES.get(command)
    if not lines:
        return None
    return _MARK + "\n".join(f"  {line}" for line in lines)


def add_examples(sub, prefix: str = "") -> None:
    """Give every sub-command of ``sub`` (an ``add_subparsers()`` action) its examples, and
    the actions of a command that has its own sub-commands theirs.

    Parameters
    ----------
    sub : argparse._SubParsersAction
    prefix : str
        The parent command (``"reflectance "``), for the actions of a command.
    """
    for name, parser in sub.choices.items():
        give_examples(prefix + name, parser)


def give_examples(command: str, parser) -> None:
    """Give the parser of ``command`` (``"reflectance"``) its examples, and the actions of its
    own sub-commands theirs (:func:`add_examples` for one command).

    Parameters
    ----------
    command : str
        The command's name as :data:`EXAMPLES` spells it.
    parser : argparse.ArgumentParser
        Its parser.
    """
    text = epilog(command)
    if text is not None and not parser.epilog:
        parser.epilog = text
        parser.formatter_class = ExamplesFormatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            add_examples(action, prefix=f"{command} ")
