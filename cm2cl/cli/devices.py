"""``cm2cl devices``: what OpenCL sees, what each device can do, and which one cm2cl uses."""

from __future__ import annotations

import sys

from ..errors import CM2Error

__all__ = ["register", "command"]


def register(sub):
    d = sub.add_parser("devices", help="list the OpenCL devices and what each can do")
    d.add_argument("--device", default=None, help="index or name fragment of the device to mark as chosen")
    d.set_defaults(func=command)
    return d


def command(args) -> int:
    from .. import device
    from ..device import fft

    caps = device.list_devices()
    if not caps:
        print(f"cm2cl: error: {device.runtime.NO_DEVICE_HELP}", file=sys.stderr)
        return 3
    compiles = device.compiler_report()
    try:
        chosen = device.get_runtime(args.device).caps.index
    except CM2Error:
        print(device.format_table(caps, None, compiles))
        raise
    print(device.format_table(caps, chosen, compiles))
    print("\n* = device cm2cl uses now (CM2CL_DEVICE / PYOPENCL_CTX / --device override the choice)")
    print(f"FFT backends available: {', '.join(fft.available_backends())} "
          f"(auto picks {fft.resolve_backend('auto', device.get_runtime(args.device))})")
    return 0
