"""The OpenCL layer: device choice and capabilities, the per-device runtime that owns every cache
(programs, FFT plans), program building and launching, FFT plans, and slab-stored volumes.
The only part of cm2cl that imports pyopencl."""

from .runtime import (Capabilities, Runtime, compiler_report, compiler_works, format_table,  # noqa: F401
                      get_runtime, list_devices, select_device)
