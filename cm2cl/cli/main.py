"""The ``cm2cl`` command: one sub-command per job; errors are one line and a non-zero exit."""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from ..errors import CM2Error, KernelBuildError


class _Parser(argparse.ArgumentParser):
    """argparse with cm2cl's one-line errors (no usage block): ``cm2cl reconstruct: error: ...``, exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    from .options import flag_names

    p = _Parser(prog="cm2cl", description=__doc__)
    p.add_argument("--version", action="version", version=f"cm2cl {__import__('cm2cl').__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for register in _registrars():
        register(sub)
    for command in sub.choices.values():   # library errors name parameters; the user typed options
        _add_logging(command)
        command.set_defaults(flags=flag_names(command))
    return p


#: --log-level choices
LOG_LEVELS = ("debug", "info", "warning", "error")


def _add_logging(command) -> None:
    g = command.add_argument_group("logging")
    g.add_argument("-v", "--verbose", action="count", default=0,
                   help="log what cm2cl does on stderr: -v info (plans, solves, devices), -vv debug")
    g.add_argument("--log-level", choices=LOG_LEVELS, default=None,
                   help="level of the cm2cl logger's messages on stderr (default warning; overrides -v)")


def _log_handler(args):
    """A stderr handler on the ``cm2cl`` logger at the level -v / --log-level ask for (removed after the
    command, so that repeated calls of :func:`main` do not stack handlers)."""
    import logging

    level = (getattr(logging, args.log_level.upper()) if getattr(args, "log_level", None)
             else {0: logging.WARNING, 1: logging.INFO}.get(getattr(args, "verbose", 0), logging.DEBUG))
    logger = logging.getLogger("cm2cl")
    handler = logging.StreamHandler(sys.stderr)
    # the module that logs is named with -v / -vv; at the default level a warning reads "cm2cl: WARNING: ..."
    # (it read "cm2cl: WARNING: cm2cl: ...")
    handler.setFormatter(logging.Formatter("cm2cl: %(levelname)s: %(name)s: %(message)s" if level < logging.WARNING
                                           else "cm2cl: %(levelname)s: %(message)s"))
    handler.setLevel(level)
    previous = logger.level
    logger.addHandler(handler)
    logger.setLevel(min(level, previous) if previous else level)
    return logger, handler, previous


def _registrars():
    """One module per sub-command, each with ``register(subparsers)`` and ``command(args)``."""
    from . import analyze, demo, devices, prepare_psf, reconstruct, simulate, verify

    return [devices.register, demo.register, simulate.register, reconstruct.register, prepare_psf.register,
            verify.register, analyze.register]


class Terminated(BaseException):
    """SIGTERM (a batch system's stop, ``kill``) or SIGHUP (the terminal closed), raised in the main thread
    so that every ``finally`` and ``with`` on the way out runs: staged outputs are dropped and locks
    released, as on Ctrl-C. ``signum``: the signal."""

    def __init__(self, signum=signal.SIGTERM):
        super().__init__(signum)
        self.signum = signum


#: the signals that stop a command as SIGTERM does (SIGHUP where the platform has it)
STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


def _raise_terminated(signum, frame):
    raise Terminated(signum)


def _save_log(text: str) -> str:
    """Write a build log to a new file in the temporary folder; its path."""
    import tempfile

    fd, path = tempfile.mkstemp(prefix="cm2cl-build-", suffix=".log")
    with open(fd, "w") as f:
        f.write(text)
    return path


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, _raise_terminated) for sig in STOP_SIGNALS}
    logger, handler, level = _log_handler(args)
    try:
        return int(args.func(args) or 0)
    except KernelBuildError as exc:     # one line; the whole build log in a file
        print(f"cm2cl: error: {exc.summary}; full build log: {_save_log(exc.log or str(exc))}; a device that "
              "cannot compile: docs/install.md, 'When you need Debian's pocl-opencl-icd'", file=sys.stderr)
        return 2
    except CM2Error as exc:
        from .options import with_flags

        print(f"cm2cl: error: {with_flags(str(exc), getattr(args, 'flags', {}))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cm2cl: interrupted; nothing incomplete was written (a series resumes when the same command is run "
              "again)", file=sys.stderr)
        return 130
    except Terminated as exc:
        print(f"cm2cl: terminated ({signal.Signals(exc.signum).name}); nothing incomplete was written (a series "
              "resumes when the same command is run again)", file=sys.stderr)
        return 128 + int(exc.signum)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        for sig, handler_before in previous.items():
            signal.signal(sig, handler_before)


def _load_quietly() -> None:
    """The sub-commands' modules (the solver, numpy, OpenCL: about half a second), loaded while Ctrl-C leaves
    with one line and 130: an interrupt there gave an import's traceback. Nothing is written before."""
    import os

    def early(signum, frame):
        sys.stderr.write("cm2cl: interrupted while starting; nothing was written\n")
        sys.stderr.flush()
        os._exit(130)

    if threading.current_thread() is not threading.main_thread():
        _registrars()
        return
    previous = signal.signal(signal.SIGINT, early)
    try:
        from . import options  # noqa: F401

        _registrars()
    finally:
        signal.signal(signal.SIGINT, previous)


def run() -> None:
    """The console entry point: ``main``, then exit. After Ctrl-C, SIGTERM or SIGHUP (everything cleaned up by
    then) it leaves without the interpreter's finalisation: with a solve's worker thread just stopped, the
    OpenCL runtime's teardown aborted the process ("terminate called without an active exception", exit
    134) instead of the 130 / 143 / 129 that was printed."""
    import os

    _load_quietly()
    code = main()
    if code == 130 or code in (128 + int(sig) for sig in STOP_SIGNALS):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
