"""The ``cm2cl`` command: one sub-command per job; errors are one line and a non-zero exit."""

from __future__ import annotations

import argparse
import sys

from .errors import CM2Error


def _cmd_devices(args) -> int:
    from . import device, fft

    caps = device.list_devices()
    if not caps:
        print(f"cm2cl: error: {device.NO_DEVICE_HELP}", file=sys.stderr)
        return 3
    compiles = {c.index: device.compiler_works(d) for c, d in zip(caps, device._all_devices())}
    try:
        chosen = device.get_runtime(args.device).caps.index
    except CM2Error as exc:
        print(device.format_table(caps, None, compiles))
        raise exc
    print(device.format_table(caps, chosen, compiles))
    print("\n* = device cm2cl uses now (CM2CL_DEVICE / PYOPENCL_CTX / --device override the choice)")
    print(f"FFT backends available: {', '.join(fft.available_backends())} "
          f"(auto picks {fft.resolve_backend('auto')})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cm2cl", description=__doc__)
    p.add_argument("--version", action="version", version=f"cm2cl {__import__('cm2cl').__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    d = sub.add_parser("devices", help="list the OpenCL devices and what each can do")
    d.add_argument("--device", default=None, help="index or name fragment of the device to mark as chosen")
    d.set_defaults(func=_cmd_devices)
    for register in _registrars():
        register(sub)
    return p


def _registrars():
    """Sub-commands that live beside their own concern."""
    from .demo import register as demo
    from .recon_cli import register as reconstruct
    from .simulate.cli import register as simulate

    return [demo, simulate, reconstruct]


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except CM2Error as exc:
        print(f"cm2cl: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cm2cl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
