"""What a command is doing while it works: one status line on stderr.

The library never prints: it logs what it starts (``logging.getLogger("hsiffc...").info``) and
numba announces each compilation as an event. :func:`command_status` turns both into one
line for the user:

- on a terminal, a rich status line (spinner, what is being done, seconds elapsed) that
  replaces itself and disappears at the end; its text is the library's latest INFO record;
- the first time hsiffc's kernels compile on a machine (numba caches them on disk afterwards),
  the line says so: ``compiling hsiffc's kernels (first run only, about a minute)``, with the
  number compiled so far; off a terminal (a pipe, a log file) that notice is printed once as a
  plain line and the end of the compilation as another, so that nothing looks hung either.

Commands that draw their own progress bar (:data:`OWN_PROGRESS`) get the plain notice only:
rich allows one live display at a time.
"""

from __future__ import annotations

import logging
import sys
import time
from contextlib import ExitStack, contextmanager

__all__ = ["COMPILE_NOTICE", "OWN_PROGRESS", "CompileWatch", "command_status"]

#: what the status line says while hsiffc's kernels compile
COMPILE_NOTICE = "compiling hsiffc's kernels (first run only, about a minute)"
#: commands that show their own rich progress bar
OWN_PROGRESS = frozenset({"correct"})


class CompileWatch:
    """Counts numba compilations of hsiffc's own functions (a numba event listener, registered
    as a virtual subclass of ``numba.core.event.Listener`` when numba loads).

    Parameters
    ----------
    on_change : callable
        Called with no argument when a compilation of an hsiffc function starts or ends.
    """

    def __init__(self, on_change):
        if "numba.core.event" in sys.modules:  # else _listening registers it when numba loads
            sys.modules["numba.core.event"].Listener.register(CompileWatch)
        self.on_change = on_change
        self.started = 0
        self.finished = 0
        self.first_at: float | None = None
        self.last_end: float | None = None

    @staticmethod
    def _name(event) -> str | None:
        data = event.data if isinstance(event.data, dict) else {}
        fn = getattr(data.get("dispatcher"), "py_func", None)
        module = getattr(fn, "__module__", "") or ""
        if module != "hsiffc" and not module.startswith("hsiffc."):
            return None  # another library's jit function (or a test's): not ours to announce
        return getattr(fn, "__name__", "kernel")

    def notify(self, event) -> None:
        if event.is_start:
            self.on_start(event)
        elif event.is_end:
            self.on_end(event)

    def on_start(self, event) -> None:
        name = self._name(event)
        if name is None:
            return
        if self.first_at is None:
            self.first_at = time.perf_counter()
        self.started += 1
        self.on_change()

    def on_end(self, event) -> None:
        if self._name(event) is None:
            return
        self.finished += 1
        self.last_end = time.perf_counter()
        self.on_change()

    @property
    def compiling(self) -> bool:
        return self.started > self.finished

    def since_last(self) -> float:
        """Seconds since the last compilation ended (inf when none has)."""
        return float("inf") if self.last_end is None else time.perf_counter() - self.last_end

    def seconds(self) -> float:
        return 0.0 if self.first_at is None else time.perf_counter() - self.first_at


class _LatestInfo(logging.Handler):
    """Keeps the latest INFO message of hsiffc's loggers (shown in the status line)."""

    def __init__(self, on_change):
        super().__init__(level=logging.INFO)
        self.on_change = on_change
        self.text = ""

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno != logging.INFO:
            return
        try:
            self.text = " ".join(record.getMessage().split())
        except Exception:  # a malformed record must not break the command
            return
        self.on_change()


@contextmanager
def command_status(command: str, *, terminal: bool | None = None, stream=None):
    """Show what ``command`` is doing until the block ends (see the module's docstring).

    Parameters
    ----------
    command : str
        The sub-command's name (prefix of the plain lines).
    terminal : bool, optional
        Draw the live line (default: whether ``stream`` is a terminal).
    stream : file, optional
        Where to write (default ``sys.stderr``).

    Yields
    ------
    CompileWatch
        The compilation counter (tests read it).
    """
    stream = sys.stderr if stream is None else stream
    if terminal is None:
        terminal = bool(getattr(stream, "isatty", lambda: False)())
    live = terminal and command not in OWN_PROGRESS
    state = {"announced": False}

    def text() -> str:
        if watch.compiling or watch.since_last() < 2.0:  # kernels compile in bursts
            return f"{COMPILE_NOTICE}: {watch.finished} compiled"
        return info.text or f"hsiffc {command}: working"

    def changed() -> None:
        if watch.compiling and not state["announced"] and not live:
            state["announced"] = True
            print(f"hsiffc {command}: {COMPILE_NOTICE}", file=stream, flush=True)

    watch = CompileWatch(changed)
    info = _LatestInfo(changed)
    logger = logging.getLogger("hsiffc")
    with ExitStack() as stack:
        stack.enter_context(_listening(watch))
        logger.addHandler(info)
        stack.callback(logger.removeHandler, info)
        old_level = logger.level
        if logger.getEffectiveLevel() > logging.INFO:  # records reach the handler; the root
            logger.setLevel(logging.INFO)              # handler still filters what is printed
            stack.callback(logger.setLevel, old_level)
            stack.enter_context(_root_keeps_its_level())
        if live:
            stack.enter_context(_live_line(stream, text, watch))
        yield watch
    if watch.started and (state["announced"] or live):
        print(f"hsiffc {command}: compiled {watch.finished} kernel functions in {watch.seconds():.0f} s "
              "(cached on disk: later runs start at once)", file=stream, flush=True)


class _WhenImported:
    """A meta-path finder that calls ``then()`` once module ``name`` has been executed."""

    def __init__(self, name, then):
        self.name, self.then = name, then

    def find_spec(self, fullname, path=None, target=None):
        if fullname != self.name or self not in sys.meta_path:
            return None
        sys.meta_path.remove(self)
        import importlib.util

        spec = importlib.util.find_spec(fullname)  # as the other finders find it
        run = getattr(getattr(spec, "loader", None), "exec_module", None)
        if run is not None:
            def exec_module(module):
                run(module)
                self.then()

            spec.loader.exec_module = exec_module
        return spec


@contextmanager
def _listening(watch):
    """``watch`` hears numba's compilations for the block: from its start when numba is
    loaded, else from when it loads (a command that needs no kernel, such as ``emva1288``'s
    figures of a small set, never loads numba: 0.4 s of CPU and 60 MB here)."""
    with ExitStack() as installed:
        def install():
            from numba.core import event

            event.Listener.register(CompileWatch)
            installed.enter_context(event.install_listener("numba:compile", watch))

        if "numba" in sys.modules:
            install()
            yield
            return
        hook = _WhenImported("numba", install)
        sys.meta_path.insert(0, hook)
        try:
            yield
        finally:
            if hook in sys.meta_path:
                sys.meta_path.remove(hook)


@contextmanager
def _live_line(stream, text, watch):
    """A transient rich line on ``stream``: spinner, ``text()`` and the seconds elapsed, redrawn
    8 times a second, blank for a command's first second and a half unless kernels compile
    (a quick command shows nothing). What the command prints to stdout and stderr meanwhile
    goes above it (stdout only when it is the terminal too: a redirected stdout is left
    alone)."""
    from rich.console import Console
    from rich.live import Live
    from rich.spinner import Spinner
    from rich.text import Text

    t0 = time.perf_counter()

    class Line:
        def __rich__(self):
            elapsed = time.perf_counter() - t0
            line = f"{text()}  [{elapsed:.0f} s]" if elapsed >= 1.5 or watch.started else ""
            return Text(line, no_wrap=True, overflow="ellipsis")

    class Quiet:  # the spinner appears with its text
        def __init__(self):
            self.spinner = Spinner("dots", Line())

        def __rich_console__(self, console, options):
            if time.perf_counter() - t0 >= 1.5 or watch.started:
                yield self.spinner

    console = Console(file=stream, force_terminal=True)
    stdout_tty = bool(getattr(sys.stdout, "isatty", lambda: False)())
    with Live(Quiet(), console=console, transient=True, refresh_per_second=8,
              redirect_stdout=stdout_tty, redirect_stderr=stream is sys.stderr):
        yield


@contextmanager
def _root_keeps_its_level():
    """Lowering the ``hsiffc`` logger to INFO lets its records reach the root handlers, which
    print every record that reaches them: give each a level filter for the time of the block so
    that what is printed still follows ``-v``."""
    root = logging.getLogger()
    threshold = root.getEffectiveLevel()
    added = []
    for handler in root.handlers:
        if handler.level < threshold:
            f = _AtLeast(threshold)
            handler.addFilter(f)
            added.append((handler, f))
    try:
        yield
    finally:
        for handler, f in added:
            handler.removeFilter(f)


class _AtLeast(logging.Filter):
    def __init__(self, level: int):
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= self.level
