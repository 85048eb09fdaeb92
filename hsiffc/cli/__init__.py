"""The ``hsiffc`` command line.

Sub-commands live in one module per command or small group of commands (:mod:`.calibrate`,
:mod:`.diagnose`, :mod:`.data`, :mod:`.pipeline`, :mod:`.reports` ...), each with a
``register(sub)`` function. A group's module is imported and registered only when one of
its commands is parsed (or a listing of every command is asked for: ``hsiffc --help``), so that
``hsiffc --version`` and a light command import none of the batch, calibration or kernel
modules; :data:`COMMANDS` says which module registers which command. Each command runs under
one write policy (:func:`hsiffc.files.atomic.write_policy`: ``--overwrite`` and the command's inputs, declared by the
parser as ``input_args``; its outputs, ``output_args`` and ``output_dirs``, are checked before any
work). Every expected error (input, output, parameter, environment) ends here, in one place:
one line on stderr naming the file or parameter, the problem and the fix, exit status 2 (``--debug`` shows the traceback instead). Commands that process a batch return 1
when some files failed.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import os
import sys
import warnings
from collections.abc import MutableMapping

from .. import __version__
from ..errors import HsiffcError
from .args import OneLineParser
from .examples import give_examples

log = logging.getLogger("hsiffc")

#: command -> the module of this package whose ``register(sub)`` adds it, in the order
#: ``--help`` lists the commands (a test checks each module registers exactly its commands)
COMMANDS = {
    "demo": "reports", "paper": "reports", "diagnose": "diagnose",
    "info": "data", "simulate": "data", "select": "data", "calibrate": "calibrate",
    "stages": "pipeline", "fit": "pipeline", "correct": "pipeline",
    "reflectance": "reflectance",
    "quicklook": "cubes",
    "import": "importer",
    "uniformity": "uniformity", "study-ffc": "uniformity",
    "emva1288": "emva1288",
}
#: the modules that register commands, in the order ``--help`` lists them
COMMAND_MODULES = tuple(dict.fromkeys(COMMANDS.values()))


class _Commands(MutableMapping):
    """The sub-parsers of :data:`COMMANDS` by name, each group's module imported and registered
    the first time one of its commands is looked up; the names are known without importing."""

    def __init__(self, action):
        self._action = action
        self._parsers: dict = {}
        self._registered: set = set()

    def register(self, module: str) -> None:
        """Import the command module ``module`` and let it add its sub-parsers (once)."""
        if module in self._registered:
            return
        self._registered.add(module)
        before = set(self._parsers)
        importlib.import_module(f"{__name__}.{module}").register(self._action)
        for name in [n for n in self._parsers if n not in before]:
            give_examples(name, self._parsers[name])

    def __getitem__(self, name):
        if name not in self._parsers and name in COMMANDS:
            self.register(COMMANDS[name])
        return self._parsers[name]

    def __setitem__(self, name, parser):
        self._parsers[name] = parser

    def __delitem__(self, name):
        del self._parsers[name]

    def __contains__(self, name):
        return name in COMMANDS or name in self._parsers

    def __iter__(self):
        yield from COMMANDS
        yield from (n for n in self._parsers if n not in COMMANDS)

    def __len__(self):
        return len(set(COMMANDS) | set(self._parsers))


class _LazyCommands(argparse._SubParsersAction):
    """argparse's sub-command action over :class:`_Commands`: a command's module is imported
    when the command is parsed; listing every command (``--help``) imports them all."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._name_parser_map = self.choices = _Commands(self)

    def add_parser(self, name, **kwargs):
        """argparse's ``add_parser``, whose check for a name added twice sees the parsers made
        so far, not the names of :data:`COMMANDS` still to be registered."""
        commands = self._name_parser_map
        self._name_parser_map = commands._parsers
        try:
            return super().add_parser(name, **kwargs)
        finally:
            self._name_parser_map = commands

    def _get_subactions(self):
        for module in COMMAND_MODULES:
            self._name_parser_map.register(module)
        order = {name: i for i, name in enumerate(self._name_parser_map)}
        return sorted(self._choices_actions, key=lambda a: order.get(a.dest, len(order)))


EXIT_USAGE = 2
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141  # as a shell reports a process ended by SIGPIPE


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered.

    Returns
    -------
    OneLineParser
        ``hsiffc`` with the sub-commands of :data:`COMMANDS`, each registered by its module
        when first looked up (the command-line reference of the documentation is generated
        from it).
    """
    parser = OneLineParser(
        prog="hsiffc",
        description="Leakage-aware calibration and flat-field correction for low-light CMOS "
                    "hyperspectral snapshot-mosaic sensors.")
    parser.add_argument("--version", action="version", version=f"hsiffc {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log progress (-v: info, -vv: debug)")
    parser.add_argument("--debug", action="store_true",
                        help="on an error, show the Python traceback instead of one line")
    # a command's module registers it when it is parsed; its help ends with examples
    # (hsiffc.cli.examples)
    parser.add_subparsers(dest="command", metavar="COMMAND", action=_LazyCommands)
    return parser


_OS_FIXES = {
    errno.EACCES: "check the permissions or choose another path",
    errno.EPERM: "check the permissions or choose another path",
    errno.EISDIR: "give a file name, not a folder",
    errno.ENOTDIR: "a part of the path is a file, not a folder; check the path",
    errno.ENOENT: "check the path",
    errno.EEXIST: "choose another name or pass --overwrite where the command offers it",
    errno.ENOSPC: "free some disk space or write to another disk",
    errno.EROFS: "the file system is read-only; write somewhere else",
    errno.ENAMETOOLONG: "use a shorter path",
}


def describe_os_error(exc: OSError) -> str:
    """One line for an operating-system error: the file, the problem and what to do.

    Parameters
    ----------
    exc : OSError
        The error (its ``filename``, ``strerror`` and ``errno`` are used).

    Returns
    -------
    str
        E.g. ``"out.tif: Permission denied; check the folder's permissions"``.
    """
    where = exc.filename if exc.filename is not None else "a file"
    what = exc.strerror or str(exc)
    fix = _OS_FIXES.get(exc.errno, "check the path and try again")
    return f"{where}: {what}; {fix}"


def main(argv=None) -> int:
    """Run the command line; returns the exit status.

    Every expected error (bad input, output, parameter, environment) is one line on stderr
    naming the file or parameter, the problem and the fix; ``--debug`` shows the traceback.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success, 1 when some files of a batch failed, 2 for a usage or expected error.

    Examples
    --------
    >>> main(["--version"])   # doctest: +ELLIPSIS
    hsiffc ...
    0
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error (already on stderr)
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:  # one filter per handler, for this run
        for old in [f for f in handler.filters if isinstance(f, _LibraryChatter)]:
            handler.removeFilter(old)
        handler.addFilter(_LibraryChatter(args.verbose))
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    from ..files.atomic import write_policy
    from .common import check_declared_outputs, declared, input_files
    from .status import command_status

    if getattr(args, "reuse_memory", True):  # a command that streams small state opts out
        from ..batch.memory import reuse_freed_memory

        reuse_freed_memory()  # a frame's large arrays reuse the last frame's pages
    prefix = f"hsiffc {args.command}: error:"
    try:
        inputs = declared(args, "input_args")
        if args.command != "correct":  # correct discovers and protects its own inputs
            inputs = inputs + input_files(inputs)
        with warnings.catch_warnings(), write_policy(
                overwrite=bool(getattr(args, "overwrite", False)), inputs=inputs):
            if not args.debug:  # every warning shown once, as one line
                warnings.simplefilter("always")
                warnings.showwarning = _warning_printer(args.command)
            check_declared_outputs(args)
            with command_status(args.command):  # what it is doing, kernel compiles included
                return int(args.func(args) or 0)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"hsiffc {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except SystemExit as exc:  # not hsiffc's (it returns its status): a plugin or library
        if args.debug:  # ending the process would end the command with its code, maybe 0
            raise
        print(f"hsiffc {args.command}: internal error: something called sys.exit({exc.code!r}) "
              "during the command (a plugin?); nothing more was done (run again with --debug "
              "for the traceback)", file=sys.stderr)
        return EXIT_INTERNAL
    except HsiffcError as exc:
        if args.debug:
            raise
        print(f"{prefix} {_one_line(str(exc))}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # the reader of stdout went away (e.g. "| head"): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as exc:
        if args.debug:
            raise
        print(f"{prefix} {_one_line(describe_os_error(exc))}", file=sys.stderr)
        return EXIT_USAGE
    except MemoryError:
        if args.debug:
            raise
        print(f"{prefix} out of memory; process smaller inputs or fewer frames at a time",
              file=sys.stderr)
        return EXIT_USAGE
    except Exception as exc:  # an unexpected error: still one line, the traceback on request
        if args.debug:
            raise
        print(f"hsiffc {args.command}: internal error: {type(exc).__name__}: "
              f"{_one_line(str(exc))} (run again with --debug for the traceback and please "
              "report it)", file=sys.stderr)
        return EXIT_INTERNAL


class _LibraryChatter(logging.Filter):
    """Keep other libraries' INFO and DEBUG records off stderr unless ``-vv``: Dask's
    distributed sets its own loggers to INFO when it is imported, so ``--workers 2`` printed
    some 30 scheduler and nanny lines per run. Their warnings and errors still show, and
    hsiffc's own records follow ``-v``."""

    def __init__(self, verbose: int):
        super().__init__()
        self.verbose = int(verbose)

    def filter(self, record: logging.LogRecord) -> bool:
        return (record.levelno >= logging.WARNING or self.verbose >= 2
                or record.name == "hsiffc" or record.name.startswith("hsiffc."))


def _warning_printer(command: str):
    """Warnings as one line each on stderr (``hsiffc CMD: warning: ...``), each text once;
    ``--debug`` keeps Python's format with the source line."""
    seen: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None):
        text = _one_line(str(message))
        if text not in seen:
            seen.add(text)
            print(f"hsiffc {command}: warning: {text}", file=sys.stderr)
    return show


def _one_line(text: str) -> str:
    return " ".join(text.split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
