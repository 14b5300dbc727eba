"""The ``cm2cl`` command: one sub-command per job; errors are one line and a non-zero exit."""

from __future__ import annotations

import argparse
import sys

from ..errors import CM2Error
from .options import flag_names, with_flags


class _Parser(argparse.ArgumentParser):
    """argparse with cm2cl's one-line errors (no usage block): ``cm2cl reconstruct: error: ...``, exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="cm2cl", description=__doc__)
    p.add_argument("--version", action="version", version=f"cm2cl {__import__('cm2cl').__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for register in _registrars():
        register(sub)
    for command in sub.choices.values():   # library errors name parameters; the user typed options
        command.set_defaults(flags=flag_names(command))
    return p


def _registrars():
    """One module per sub-command, each with ``register(subparsers)`` and ``command(args)``."""
    from . import demo, devices, prepare_psf, reconstruct, simulate

    return [devices.register, demo.register, simulate.register, reconstruct.register, prepare_psf.register]


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except CM2Error as exc:
        print(f"cm2cl: error: {with_flags(str(exc), getattr(args, 'flags', {}))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cm2cl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
