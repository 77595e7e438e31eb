"""The ``usdface`` command line: parse, call the API, print. Each sub-command lives in
``usdface/commands/<name>.py`` and exposes ``register(subparsers)`` which adds its parser and sets
``func=run(args) -> int``.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import sys
import threading
import warnings

from . import __version__, progress
from .errors import UsdFaceError
from .locks import SharedWhileInside

#: Sub-command modules, in the order ``usdface --help`` lists them.
#: The commands in the order ``usdface --help`` lists them, README's command table's (a new user's: the
#: personalization and what follows it, the inputs, looking at files, the stages alone, pictures, the sample).
COMMAND_MODULES = (
    "personalize", "review", "export", "batch", "capture", "anim", "inspect", "check", "fit", "evaluate",
    "retarget", "landmarks", "render", "sample",
)


#: Commands whose ``--json`` is a flag (the result as JSON on stdout); ``evaluate``/``landmarks`` take a path.
JSON_FLAG_COMMANDS = ("personalize", "fit", "capture", "anim", "sample", "inspect", "check", "batch",
                      "retarget", "export", "review")
#: Commands whose numerical work all runs with BLAS at one thread (``personalize_avatar`` is
#: :func:`usdface.personalize.api.single_threaded_blas`): the program starts their BLAS with one thread
#: (:func:`_one_blas_thread_environment`).
ONE_BLAS_THREAD_COMMANDS = ("personalize", "retarget")
#: ``.argv``: the arguments :func:`main` parses on this thread (for _Parser.error and the command a layer
#: records): per thread, as a host may run main(argv) on threads side by side, and one module-wide list
#: gave a run's layer the command another thread had started since.
_PARSED = threading.local()


def parsed_argv() -> list[str]:
    """The arguments :func:`main` parsed on this thread (``sys.argv[1:]`` for the program); [] outside it."""
    return getattr(_PARSED, "argv", [])


class _Probe(Exception):
    """An error of :meth:`_Parser._unknown_first`'s second parse (its answer is then the first error)."""


#: The usage errors argparse reports before the arguments it does not know (checked inside the parse, the
#: unknown ones only after it): :meth:`_Parser._unknown_first` reorders them.
_MISSING = ("the following arguments are required", "one of the arguments ")


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (with a pointer to ``--help``), exit status 2; with
    ``--json`` (a command that prints JSON) also ``{"ok": false, "error": {...}}`` on stdout; with no command
    (``usdface`` alone) the usage line before it. An unknown option is said before missing arguments
    (:meth:`_unknown_first`), with the option it most looks like (:meth:`unrecognized`)."""

    def __init__(self, *args, **kwargs):
        if sys.version_info >= (3, 14):     # argparse's own "did you mean" for a misspelt command (3.14+)
            kwargs.setdefault("suggest_on_error", True)
        super().__init__(*args, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        # the arguments this (sub-)command's parser was given: _unknown_first parses them again
        self._given = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def unrecognized(self, extras: list[str]) -> str:
        """argparse's ``unrecognized arguments: ...``, with the option each unknown one most looks like
        (``--hlep``: ``did you mean --help?``; argparse of Python 3.11 offers none for options)."""
        import difflib

        options = [t.split("=", 1)[0] for t in extras if self._unknown_option(t)]
        hints = [(option, close[0]) for option in options
                 for close in [difflib.get_close_matches(option, list(self._option_string_actions), n=1)]
                 if close]
        said = ("; ".join(f"{o}: did you mean {c}?" for o, c in hints) if len(options) > 1 else
                f"did you mean {hints[0][1]}?" if hints else "")
        return "unrecognized arguments: " + " ".join(extras) + (f" ({said})" if said else "")

    def _closest_choice(self, message: str) -> str:
        """``message``, with the choice a misspelt one most looks like when argparse refused a value that
        is not among an argument's choices (``usdface personalise``: ``did you mean 'personalize'?``;
        ``capture improt``, ``fit --method menzle``): argparse of Python 3.11-3.13 lists the choices but
        says none is close, and 3.14 says it itself (``maybe you meant``)."""
        import difflib
        import re

        hit = re.match(r"argument (?P<name>.+?): invalid choice: '(?P<value>[^']*)'", message)
        if hit is None or "maybe you meant" in message:
            return message
        for action in self._actions:
            names = {"/".join(action.option_strings), action.metavar, action.dest}
            choices = [c for c in (action.choices or ()) if isinstance(c, str)]
            if hit["name"] in names and choices:
                close = difflib.get_close_matches(hit["value"], choices, n=1)
                return f"{message}; did you mean '{close[0]}'?" if close else message
        return message

    def _unknown_option(self, token: str) -> bool:
        return (len(token) > 1 and token[0] in self.prefix_chars and token != "--"
                and not self._negative_number_matcher.match(token))

    def _unknown_first(self, message: str) -> str:
        """``message``, or the unknown options of this parser's arguments when argparse was about to say
        that required ones are missing: it checks those inside the parse and the unknown ones after it, so
        ``personalize --hlep`` was told 'the following arguments are required: avatar, capture' where the
        flag was the mistake. The arguments are parsed once more with nothing required (argparse is still
        the parser; this only orders its errors)."""
        given = getattr(self, "_given", None)
        if not message.startswith(_MISSING) or given is None or getattr(self, "_probing", False):
            return message
        required = [a for a in self._actions if a.required]
        groups = [g for g in self._mutually_exclusive_groups if g.required]
        self._probing = True
        try:
            for item in required + groups:
                item.required = False
            _, extras = argparse.ArgumentParser.parse_known_args(self, given, None)
        except (_Probe, SystemExit):
            return message
        finally:
            self._probing = False
            for item in required + groups:
                item.required = True
        return self.unrecognized(extras) if any(map(self._unknown_option, extras)) else message

    def error(self, message):
        if getattr(self, "_probing", False):
            raise _Probe(message)
        message = self._closest_choice(self._unknown_first(message))
        argv = parsed_argv()
        command = next((a for a in argv if not a.startswith("-")), None)
        if "--json" in argv and command in JSON_FLAG_COMMANDS:
            import json

            # the command as the line on stderr names it: 'capture select', not 'capture'
            named = self.prog.removeprefix("usdface").strip()
            named = named if named.split(" ")[0] == command else command
            print(json.dumps({"ok": False, "error": {
                "command": named, "type": "UsageError", "message": message, "file": None, "prim": None,
                "fix": f"see '{self.prog} --help'"}}))
        usage = self.format_usage() if command is None and self._subparsers is not None else ""
        self.exit(2, f"{usage}{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="usdface",
        description="Personalized ARKit facial blendshapes from a phone capture, written as a USD layer.")
    parser.add_argument("--version", action="version", version=f"usdface {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    # required: 'usdface' alone is a usage error (exit 2, as 'usdface capture' alone); it printed the help on
    # stdout and exited 0, so a script's 'usdface $CMD' with $CMD unset passed
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(f"usdface.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"usdface.commands.{name}":
                continue  # command not built yet
            raise
        mod.register(sub)
    _debug_anywhere(sub)
    return parser


def _debug_anywhere(sub) -> None:
    """``--debug`` after the command too (``usdface personalize ... --debug``, where one adds it to a failed
    command line), in every command and sub-command; SUPPRESS keeps the top-level one's value otherwise."""
    for command in set(sub.choices.values()):
        if "--debug" not in command._option_string_actions:
            command.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                                 help="show full tracebacks on errors (as 'usdface --debug COMMAND')")
        for action in command._actions:
            if isinstance(action, argparse._SubParsersAction):
                _debug_anywhere(action)


def _silence_stdout() -> None:
    """Point stdout at /dev/null after the reader closed the pipe, so Python's final flush stays quiet."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # stdout is not a real file (captured in tests)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a farm's or a queue's kill, a Dask worker's shutdown), or another signal that asks the program
    to stop (:data:`STOP_SIGNALS`), raised in the main thread, so that the atomic writers' clean-up runs
    exactly as on Ctrl-C and no temporary file is left behind. ``signum``: the signal."""

    def __init__(self, signum: int | None = None):
        import signal

        super().__init__()
        self.signum = int(signal.SIGTERM if signum is None else signum)

    @property
    def signame(self) -> str:
        import signal

        return signal.Signals(self.signum).name


#: The signals the ``usdface`` program turns into :class:`Terminated`: SIGTERM (a farm's or a queue's kill),
#: SIGHUP (the terminal or ssh session the run was started from closed; ``kill -HUP``) and SIGXCPU (a batch
#: system's CPU-time limit, ``ulimit -t``, reached). By their default action SIGHUP and SIGXCPU killed the
#: process at once: a write under way left its hidden temporary file or folder behind (``.objs.wzp9wxkc/``
#: full of OBJs, ``.p.usda.XXXXXXXX.tmp.usda``). One started ignored (``nohup``) stays ignored.
STOP_SIGNALS = ("SIGTERM", "SIGHUP", "SIGXCPU")


#: How long the ``usdface`` program may take to end once a stop signal has reached it (Ctrl-C, SIGTERM, ...):
#: the stop's clean-up (a write's temporary file removed, a batch's report written, its pool or its Dask
#: client closed) takes well under a second, and a Dask client's close is given 10 s
#: (:data:`usdface.pipeline.batch.DASK_CLOSE_SECONDS`) and its thread 10 s more. Counted from when the
#: program takes the signal (Python runs its handler once the native call under way returns). Past it the
#: program exits at once with the stop's status, whatever it was waiting for (a thread joined at exit, a
#: cluster that does not answer). ``USDFACE_STOP_SECONDS`` sets another bound (a farm's grace before its
#: SIGKILL).
STOP_SECONDS = 30.0


class _Stop:
    """The ``usdface`` program's stop under way: the first stop signal starts a watchdog that ends the process
    :data:`STOP_SECONDS` later if it has not ended by then; a second Ctrl-C after a Ctrl-C ends it at once.

    Nothing in the stop path may wait without end: a Ctrl-C or a farm's SIGTERM ends the run within a bound
    the user can count on. ``os._exit``, not ``sys.exit``: the exit itself may be what waits (the
    interpreter joins every non-daemon thread at exit, without a timeout). Outputs are published only
    complete (temporary file, then rename), so an exit forced here leaves no half-written output; a write
    under way at that moment may leave its hidden temporary file."""

    def __init__(self) -> None:
        self.status: int | None = None          # the exit status of the stop under way
        self.signum: int | None = None

    def begin(self, signum: int) -> None:
        if self.status is not None:
            return
        self.signum, self.status = signum, 128 + signum
        try:
            seconds = float(os.environ.get("USDFACE_STOP_SECONDS", STOP_SECONDS))
        except ValueError:
            seconds = STOP_SECONDS
        threading.Thread(target=self._watch, args=(max(seconds, 0.0),), name="usdface stop watchdog",
                         daemon=True).start()

    def _watch(self, seconds: float) -> None:
        import time

        time.sleep(seconds)
        self.exit_now(f"still stopping after {seconds:g} s; exiting without waiting any longer")

    def exit_now(self, why: str) -> None:
        """End the process at once with the stop's status, saying why on stderr."""
        status = self.status or 130
        what = "interrupted" if status == 130 else "terminated"
        with contextlib.suppress(OSError):
            os.write(2, f"usdface: {what}: {why}\n".encode())
        os._exit(status)


_STOP = _Stop()


def _on_sigterm(signum, frame):
    _STOP.begin(signum)
    raise Terminated(signum)


def _on_sigint(signum, frame):
    """Ctrl-C: ``KeyboardInterrupt``, as Python's own handler; a second Ctrl-C while the first one's stop
    runs (the user insists: a clean-up that waits on something) ends the process at once."""
    import signal

    if _STOP.signum == signal.SIGINT:
        _STOP.exit_now("interrupted again; exiting without waiting for the clean-up")
    _STOP.begin(signum)
    raise KeyboardInterrupt


def main(argv=None) -> int:
    """Run one command; the exit status: 0 done, 1 findings (check, batch failures), 2 an error, 130
    interrupted (Ctrl-C), 143 terminated (SIGTERM), 141 a closed pipe.

    Run as the ``usdface`` program (``argv`` None: the console script, ``python -m usdface``), SIGTERM is
    turned into :class:`Terminated` so the atomic writers clean up; called with ``argv`` from a host
    application, the host's own signal handling is left alone."""
    import signal

    if argv is None:
        _program_environment()
        _standard_streams()
        if sys.stdout is not None and not isinstance(sys.stdout, _StdoutReporter):
            sys.stdout = _StdoutReporter(sys.stdout)
    previous = {}
    program = argv is None and threading.current_thread() is threading.main_thread()
    for name in STOP_SIGNALS if program else ():
        signum = getattr(signal, name, None)
        if signum is not None and signal.getsignal(signum) is not signal.SIG_IGN:  # started ignored: stays
            previous[signum] = signal.signal(signum, _on_sigterm)
    # Ctrl-C as Python's own handler has it (KeyboardInterrupt), with the stop's bound; a SIGINT ignored at
    # start (a background job of a script, nohup) stays ignored, and one a launcher set is its own
    if program and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, _on_sigint)
    stopped = False
    try:
        return _main(argv, program=program)
    except Terminated as exc:
        stopped = True
        print("usdface: terminated" + ("" if exc.signum == signal.SIGTERM else f" ({exc.signame})"),
              file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:  # before the command ran (reading the command line), one line as after
        stopped = True
        print("usdface: interrupted", file=sys.stderr)
        return 130
    finally:
        if _STOP.status is None:      # stopped, the program is ending: a second Ctrl-C still ends it now
            for signum, handler in previous.items():
                signal.signal(signum, handler)
        if argv is None:
            _forget_interrupts_handled_inside_exec()
            if stopped:
                # the stopped run's frames (Open3D point clouds and registrations among their locals) hang
                # in reference cycles through the traceback: frozen below, they outlived the interpreter,
                # and Open3D's allocation statistics then listed them as leaks at exit and turned the exit
                # status 143 into 1 (a SIGTERM during the registration)
                gc.collect()
            # the program ends here: the interpreter's shutdown collections need not walk every object of
            # the ~2,000 modules loaded (Open3D's Dash/Plotly among them; 0.15-0.3 s of a personalize run).
            # Shutdown itself is unchanged (atexit, flushes, threads joined, modules torn down)
            gc.freeze()


def _forget_interrupts_handled_inside_exec() -> None:
    """Clear CPython's record of a ``KeyboardInterrupt`` that left an ``exec``/``eval`` of a string, once the
    program has handled it (exit status 130 or 143, or a run that went on).

    CPython notes a ``KeyboardInterrupt`` leaving any ``exec(str)``/``eval(str)`` as "unhandled"
    (``_Py_UnhandledKeyboardInterrupt``), even when the caller catches it, and under ``python -m`` (not the
    console script) the interpreter reads that note after the program's ``sys.exit``: it then kills itself
    with SIGINT instead of exiting with the program's status. SciPy's first import runs ``exec("from numpy
    import *")``; dataclasses and namedtuples are built with ``exec``: a Ctrl-C landing there made ``python -m
    usdface personalize ...`` die by SIGINT (a farm's ``returncode`` -2, ``WIFSIGNALED``) although it had
    printed ``usdface: interrupted`` and cleaned up, about one run in seven stopped ~0.5 s after its start.
    Every ``exec`` of a string clears the note before it runs, and this one raises nothing."""
    exec("pass")   # a fixed string: it only clears the note


def _one_blas_thread_environment(command: str | None) -> None:
    """Start BLAS with one thread in the program's own process when its ``command`` runs all its numerical
    work at one BLAS thread anyway (:data:`ONE_BLAS_THREAD_COMMANDS`), before numpy is imported
    (:func:`usdface.natives.start_blas_single_threaded`; a thread count the user set is kept)."""
    if command in ONE_BLAS_THREAD_COMMANDS:
        from .natives import start_blas_single_threaded

        start_blas_single_threaded()


def _import_natives_with_signals_held() -> None:
    """Import numpy and the USD Python modules usdface uses with SIGINT and SIGTERM held back, then let a
    held signal through.

    Both turn a Ctrl-C or SIGTERM that lands inside their native imports into something else. USD's C++
    module loader (``Tf.PreparePythonModule``) imports the modules a library depends on and catches every
    Python exception doing so, printing it as a warning: a signal in that first ``from pxr import ...`` (the
    first ~0.3 s of a run) was swallowed, and the run went on to the end, wrote its output and exited 0, with
    pxr half-loaded (``Error loading lib gf's module 'pxr.Gf'``). numpy's C extension imports ``datetime``
    through the C API, which reports the ``KeyboardInterrupt`` as a failed import, and numpy raises that as
    an ImportError telling the user the installation is broken ("Importing the numpy C-extensions failed",
    exit status 1). Held back, the signal arrives once the imports are done, where
    ``KeyboardInterrupt``/:class:`Terminated` end the run as at any other moment (exit 130/143, nothing
    written)."""
    from .natives import signals_held

    with signals_held():                  # each held signal let through after, to the handler it had
        import numpy  # noqa: F401
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt  # noqa: F401


def _standard_streams() -> None:
    """Give the ``usdface`` program a stdin, stdout and stderr when it was started with one closed (``>&-``,
    a launcher that closes them): /dev/null in their place.

    Python leaves ``sys.stdout`` None then, and the final flush of the output's summary raised
    AttributeError (a traceback, exit status 1, after the output was written); worse, the next file opened
    takes the free descriptor 1 or 2, and what C++ code (USD's diagnostics) writes to stdout or stderr went
    into that file."""
    for fd, name in ((0, "stdin"), (1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        null = os.open(os.devnull, os.O_RDONLY if fd == 0 else os.O_WRONLY)
        if null != fd:
            os.dup2(null, fd)
            os.close(null)
        if getattr(sys, name) is None:
            setattr(sys, name, open(fd, "r" if fd == 0 else "w", encoding="utf-8", closefd=False,
                                    **({} if fd == 0 else {"errors": "backslashreplace"})))


def _program_environment() -> None:
    """Settings for the ``usdface`` program's own process (and the batch workers it starts), before numpy
    is imported; a host application calling :func:`main` keeps its own.

    numpy asks the kernel for transparent huge pages for every array of 4 MB or more (``madvise``). Where
    the kernel's THP ``defrag`` setting is ``madvise`` (this machine class), each such page fault may stall
    in direct memory compaction once memory is fragmented: a fresh 100 MB array took 1.43 s instead of
    0.09 s, and the field that carries the person's motion onto a 300k-vertex body mesh 2.7 s instead of
    0.4 s (docs/scale.md). The program opts out (``NUMPY_MADVISE_HUGEPAGE=0``, numpy's own switch) unless
    the user set it.

    The cyclic garbage collector runs a young collection every 50,000 container allocations, not Python's
    700: a cold ``personalize`` imports ~2,000 modules (USD, SciPy, Open3D with Dash and Plotly), and at 700
    the collector ran ~270 times over them, the oldest generation twice (0.1-0.15 s of a 4-5 s run). The
    arrays are freed by reference counting as before; the peak RSS of a dev1 run is unchanged.

    numpy's ``f2py`` and ``testing``, which SciPy's array-API shim imports, and ``scipy.spatial.transform``,
    which ``scipy.spatial`` imports, none used by any step, load at their first use
    (:func:`usdface.natives.defer_unused_submodules`: 0.1-0.2 s of a cold run)."""
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    gc.set_threshold(50_000, *gc.get_threshold()[1:])
    _matplotlib_config_dir()
    from .natives import defer_unused_submodules

    defer_unused_submodules()


def _matplotlib_config_dir() -> None:
    """A private ``MPLCONFIGDIR`` for this run, removed at exit, when matplotlib's own folders cannot be
    written (a farm's render user with a read-only or missing home folder).

    matplotlib then made a temporary folder itself, but said so on stderr in two lines that are not
    usdface's and that ``-q`` did not silence (``mkdir -p failed for path ~/.config/matplotlib: [Errno 30]
    Read-only file system`` and ``Matplotlib created a temporary cache directory at /tmp/matplotlib-... it
    is highly recommended to set the MPLCONFIGDIR environment variable ...``), in every ``render``,
    ``evaluate --plot`` and ``landmarks --plot`` log. A ``MPLCONFIGDIR`` the user set is kept."""
    if os.environ.get("MPLCONFIGDIR") or not sys.platform.startswith(("linux", "freebsd")):
        return
    home = os.path.expanduser("~")
    bases = (os.environ.get("XDG_CONFIG_HOME") or os.path.join(home, ".config"),
             os.environ.get("XDG_CACHE_HOME") or os.path.join(home, ".cache"))

    def writable(folder: str) -> bool:              # it, or the nearest existing folder it would be made in
        folder = os.path.abspath(folder)
        while not os.path.lexists(folder) and os.path.dirname(folder) != folder:
            folder = os.path.dirname(folder)
        return os.path.isdir(folder) and os.access(folder, os.W_OK)

    if all(writable(os.path.join(base, "matplotlib")) for base in bases):
        return
    import atexit
    import shutil
    import tempfile

    try:
        private = tempfile.mkdtemp(prefix="usdface-matplotlib-")
    except OSError:                                 # no temporary folder either: matplotlib's own way
        return
    os.environ["MPLCONFIGDIR"] = private
    atexit.register(shutil.rmtree, private, ignore_errors=True)


def _subparser(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser | None:
    """The parser of the (sub-)command ``args`` ran, down to its action (``capture import``): its errors name
    it (``usdface capture import: error: ...``) and its ``--help``; None for no command."""
    found = None
    while True:
        action = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        parser = action.choices.get(getattr(args, action.dest, None)) if action is not None else None
        if parser is None:
            return found
        found = parser


def _empty_argument(argv: list[str]) -> str | None:
    """The usage error for the first empty argument of a command line (``-o ""``, ``--output=``, a positional
    ``""``), or None.

    A farm's job template or a script whose variable was unset (``-o "$OUT"``) passes an empty value, and
    Python reads an empty path as the current folder: ``capture import CAP -o ""`` wrote the capture's
    ``neutral.obj``, ``template/``, ``train/`` and ``test/`` into the current folder (it was empty, so it was
    taken as a new output folder), ``personalize -o ""`` wrote the default ``<avatar>.personalized.usda``
    there, and the other commands said ``.: output path is a folder``. No usdface argument means anything
    when empty."""
    for i, token in enumerate(argv):
        if token.startswith("--") and token.endswith("=") and len(token) > 3:
            name = token[:-1]
        elif token == "":
            before = argv[i - 1] if i else ""
            name = before if before.startswith("-") and before != "--" and "=" not in before else None
        else:
            continue
        what = f"argument {name}: empty value" if name else "an empty argument"
        return f"{what} (an unset variable in the command line?)"
    return None


def _unknown_before_the_command(parser: _Parser, argv: list[str]) -> None:
    """Refuse an option before the command that ``usdface`` itself does not take (``usdface --hlep
    personalize``): argparse sets it aside and parses on, so the command's parser said its required
    arguments were missing. usdface's own options take no value, so what precedes the first plain word is
    options only; one is known when it is an option of ``parser`` or a unique prefix of one (argparse's
    abbreviations: ``--deb``). A parser of another class (a host's or a test's ``build_parser``) is left to
    argparse."""
    if not isinstance(parser, _Parser):
        return
    for token in argv:
        if not parser._unknown_option(token):
            return
        name = token.split("=", 1)[0]
        if len([o for o in parser._option_string_actions if o.startswith(name)]) != 1 and \
                name not in parser._option_string_actions:
            parser.error(parser.unrecognized([token]))


def _main(argv=None, program: bool = False) -> int:
    parser = build_parser()
    _PARSED.argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    _unknown_before_the_command(parser, _PARSED.argv)
    args, extra = parser.parse_known_args(argv)
    if extra:          # the sub-command's parser reports them, so the error line names the command
        named = _subparser(parser, args) or parser
        named.error(named.unrecognized(extra))
    empty = _empty_argument(_PARSED.argv)
    if empty is not None:
        (_subparser(parser, args) or parser).error(empty)
    from .commands import reset_warnings

    reset_warnings(json_on_stdout=getattr(args, "json", None) is True)
    # progress on stderr unless -q, or --json prints a document on stdout (a --json PATH keeps it); a host
    # calling main(argv) gets its own setting back (usdface.progress.set_enabled): -q turned its progress off
    # for good, and a run without -q turned it back on after the host had turned it off
    with contextlib.nullcontext() if program else _HOST_PROGRESS:
        progress.set_enabled(not (getattr(args, "quiet", False) or getattr(args, "json", None) is True))
        return _run(args, program)


def _run(args, program: bool) -> int:
    """The parsed command run, its errors turned into the exit status and the one line (or ``--json``)."""
    from .commands import say_warning

    try:
        if program:  # the usdface program's main thread (a host application's signals are its own)
            _one_blas_thread_environment(getattr(args, "command", None))
            _import_natives_with_signals_held()
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            # third-party import machinery (six's importer under Dask) is not the user's business
            warnings.filterwarnings("ignore", category=ImportWarning)
            warnings.showwarning = lambda message, *_a, **_k: say_warning(message)
            if os.environ.get("SOURCE_DATE_EPOCH", "").strip():   # before scipy's import reads it
                from .io.layers import source_date_epoch

                source_date_epoch()
            code = int(args.func(args) or 0)
        if sys.stdout is not None:  # a closed pipe (`usdface inspect x | head`) fails here, not at exit
            sys.stdout.flush()
        return code
    except BrokenPipeError:
        _silence_stdout()
        return 141  # 128 + SIGPIPE, what a shell tool killed by the closed pipe returns
    except UsdFaceError as exc:
        if args.debug:
            raise
        name_output_option(exc, args)
        if getattr(args, "json", None) is True:
            _json_error(args, str(exc), type(exc).__name__, exc.path, exc.prim, exc.fix)
        else:
            print(f"usdface {_command_name(args)}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _stopped(args, exc)
    except ImportError as exc:
        # a Ctrl-C or SIGTERM landing in a native module's initialisation (open3d's, imported at the first
        # registration or ray cast): pybind11 turns it into 'ImportError: initialization failed'
        stop = _interrupt_behind(exc)
        if stop is None:
            raise
        return _stopped(args, stop)
    except OSError as exc:  # a write that failed: read-only folder or file system, full disk, path clash
        if args.debug:
            raise
        if isinstance(exc, StdoutError):                  # stdout itself (`> /dev/full`): not the outputs
            _silence_stdout()
            written = ("; the outputs were written, its report was not" if getattr(args, "output", None)
                       else "")
            print(f"usdface {_command_name(args)}: error: could not write to stdout: {exc.strerror or exc} "
                  f"(fix: free space where stdout goes, or send it elsewhere{written})", file=sys.stderr)
            return 2
        text = os_error_text(exc, hasattr(args, "output"))
        if getattr(args, "json", None) is True:
            _json_error(args, text, type(exc).__name__, exc.filename, None,
                        os_error_fix(exc, hasattr(args, "output")))
        else:
            print(f"usdface {_command_name(args)}: error: {text}", file=sys.stderr)
        return 2


#: Runs of :func:`main` called by a host (``argv`` given, or not the main thread) under way: the first of
#: runs side by side keeps the host's progress setting, the last one out puts it back. Each run putting back
#: what it found, two runs on the host's threads side by side (``-q`` and not) left the second's find, the
#: first's setting, for good.
_HOST_PROGRESS = SharedWhileInside(lambda: progress._ENABLED, lambda enabled: progress.set_enabled(enabled))


def _stopped(args, exc: KeyboardInterrupt) -> int:
    """A run stopped by Ctrl-C (exit status 130) or SIGTERM (:class:`Terminated`, raised on to :func:`main`:
    143); with ``--json`` stdout still gets its one document."""
    terminated = isinstance(exc, Terminated)
    report = getattr(exc, "report_path", None)    # a stopped batch's report of what finished
    if getattr(args, "json", None) is True:   # stdout still holds one document: the run did not finish
        _json_stopped(args, terminated, exc.signame if terminated else "SIGINT", report,
                      getattr(exc, "batch_report", None))
    if report is not None:
        print(f"report: {report}", file=sys.stderr)
    if terminated:
        raise exc
    print("usdface: interrupted", file=sys.stderr)
    return 130


def _interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (or :class:`Terminated`) an exception was raised from or while handling."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


class StdoutError(OSError):
    """A write to the ``usdface`` program's stdout failed (a full disk, ``> /dev/full``): told apart from a
    failed output, whose fix is another ``-o`` (the outputs were written; the report on stdout was not)."""


class _StdoutReporter:
    """The program's ``sys.stdout``, raising :class:`StdoutError` where a write or flush of it fails (a closed
    pipe stays ``BrokenPipeError``); everything else is the stream's own."""

    def __init__(self, stream):
        self._stream = stream

    def _call(self, name, *args):
        try:
            return getattr(self._stream, name)(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise StdoutError(exc.errno, exc.strerror) from exc

    def write(self, text):
        return self._call("write", text)

    def writelines(self, lines):
        return self._call("writelines", lines)

    def flush(self):
        return self._call("flush")

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _json_error(args, text, kind, path, prim, fix) -> None:
    """With ``--json`` an error is JSON too: one object on stdout (``{"ok": false, "error": {...}}``) and the
    usual one line on stderr."""
    import json

    # the command as the line on stderr names it ('capture select', 'anim import'): it said 'capture' for
    # both capture actions
    doc = {"ok": False, "error": {"command": _command_name(args), "type": kind, "message": text,
                                  "file": None if path is None else str(path), "prim": prim, "fix": fix}}
    print(json.dumps(doc))
    print(f"usdface {_command_name(args)}: error: {text}", file=sys.stderr)


def _json_stopped(args, terminated: bool, signame: str = "SIGTERM", report=None, batch_report=None) -> None:
    """The ``--json`` document of a run stopped by Ctrl-C or SIGTERM (the line on stderr follows): a
    pipeline that reads stdout gets ``{"ok": false, ...}``, not an empty document. A stopped batch's
    document is its report too (``batch_report``, written to ``report``: ``report_path``, the counts, each
    item), as a finished batch's is; it had the report file's path alone (stop 54)."""
    import json

    kind, signame = ("Terminated", signame) if terminated else ("Interrupted", "SIGINT")
    batch = args.command == "batch"
    doc = {"ok": False, "error": {
        "command": _command_name(args), "type": kind,
        "message": f"stopped by {signame} before it finished" + (
            ": the items that finished are kept, the report says which" if batch
            else "; its output was not written"),
        "file": None if report is None else str(report), "prim": None,
        "fix": "run the same command again (finished items are skipped)" if batch
        else "run the command again"}}
    if batch_report is not None and report is not None:      # what finished, as the report file lists it
        doc.update(report_path=os.path.abspath(report), **batch_report.to_dict())
    try:
        print(json.dumps(doc), flush=True)
    except OSError:
        pass


def _command_name(args) -> str:
    """The command as typed, with its action for the commands that have actions (``anim import``, ``capture
    select``: their errors said ``usdface anim: error``)."""
    action = getattr(args, f"{args.command}_command", None)
    return f"{args.command} {action}" if isinstance(action, str) else str(args.command)


def name_output_option(exc: UsdFaceError, args) -> None:
    """An output refused inside an input folder is told the place beside it as the path alone
    (``exc.beside``, :func:`usdface.io.atomic.check_not_input`: the API and a Pyblish instance have no
    ``-o``); on the command line the fix names ``-o`` with it where the refused output is the one ``-o``
    gives (given, or its default: ``capture import .`` inside the folder), not another option's
    (``personalize --correspondence cap/corr.npz`` was told ``-o corr.npz``, the layer's; stop 54). The error
    :func:`_run` prints, and ``personalize --dry-run``'s early word on the output (it said the path alone)."""
    beside = getattr(exc, "beside", None)
    if not beside or not exc.fix or exc.path is None or not hasattr(args, "output"):
        return
    refused = os.path.abspath(exc.path)
    for name, value in vars(args).items():
        if name != "output" and isinstance(value, str | os.PathLike) and str(value) \
                and os.path.abspath(value) == refused:
            return                                                 # another option's output
    exc.fix = exc.fix.replace(f"({beside}, beside it)", f"(-o {beside}, beside it)")


def os_error_fix(exc: OSError, output_option: bool = True) -> str:
    """What to do about an OSError (by its errno: :func:`usdface.errors.write_fix`), naming ``-o`` only when
    ``output_option``: the command has one. The ``fix`` of the one-line error and of the ``--json`` error
    document."""
    from .errors import write_fix

    return write_fix(exc.errno, output_option)


def os_error_text(exc: OSError, output_option: bool = True) -> str:
    """One line for an OSError: the file, what the system said and the fix (:func:`os_error_fix`)."""
    where = exc.filename if exc.filename is not None else ""
    what = exc.strerror or str(exc)
    fix = os_error_fix(exc, output_option)
    return f"{where}: {what} (fix: {fix})" if where else f"{what} (fix: {fix})"


if __name__ == "__main__":
    # ``python -m usdface.cli``: this file runs as ``__main__``, a second copy of the module beside the
    # ``usdface.cli`` the commands import; its ``main`` kept the parsed arguments where
    # ``commands.command_line`` never looked, and every layer recorded its command as ``usdface`` alone
    from usdface.cli import main as _main

    sys.exit(_main())
