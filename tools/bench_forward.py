"""Time of H and H^T on the current OpenCL device against numpy/scipy.fft float32 on the same
machine, per FFT backend. Writes the table to docs/benchmarks.md.

    python tools/bench_forward.py [--sizes 256x256x16 324x432x16] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import scipy.fft as sfft

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import best_time, markdown_table, parse_size, write_section  # noqa: E402

from cm2cl.device import fft  # noqa: E402
from cm2cl.device import get_runtime  # noqa: E402
from cm2cl.solver.forward import ForwardModel, centered_psf  # noqa: E402
from cm2cl.device.volume import Volume  # noqa: E402


def numpy_ops(psf, P):
    """float32 scipy.fft version of C H and H^T C^T (all cores)."""
    nz, my, mx = psf.shape
    Hs = sfft.rfft2(centered_psf(psf, P), workers=-1).astype(np.complex64)
    oy, ox = (P[0] - my) // 2, (P[1] - mx) // 2

    def fwd(x):
        return sfft.irfft2((Hs * sfft.rfft2(x, workers=-1)).sum(axis=0), s=P, workers=-1)[oy:oy + my, ox:ox + mx]

    def adj(y):
        v = np.zeros(P, np.float32)
        v[oy:oy + my, ox:ox + mx] = y
        return sfft.irfft2(np.conj(Hs) * sfft.rfft2(v, workers=-1)[None], s=P, workers=-1)

    return fwd, adj


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", nargs="+", default=["256x256x16", "324x432x16"])
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    rt = get_runtime()
    rng = np.random.default_rng(0)
    rows = []
    for spec in a.sizes:
        my, mx, nz = parse_size(spec)
        psf = rng.random((nz, my, mx)).astype(np.float32)
        for backend in fft.available_backends():
            m = ForwardModel(psf, backend=backend)
            P = m.padded_shape
            x = rng.random((nz,) + P).astype(np.float32)
            y = rng.random((my, mx)).astype(np.float32)
            xv = m.new_volume().set(x)
            plane = m.new_plane()
            sens = Volume(rt, [(0, 1)], (my, mx), np.float32).set(y[None])
            t_f = best_time(lambda: m.crop_to_sensor(m.convolve_device(xv, plane.slabs[0]), sens.slabs[0]),
                            a.repeat, sync=rt.queue.finish)
            t_a = best_time(lambda: m.adjoint_padded_device(m.embed_from_sensor(sens.slabs[0], plane.slabs[0]), xv),
                            a.repeat, sync=rt.queue.finish)
            # numpy on the same padded grid
            fwd, adj = numpy_ops(psf, P)
            n_f = best_time(lambda: fwd(x), a.repeat)
            n_a = best_time(lambda: adj(y), a.repeat)
            rows.append([f"{my} x {mx} x {nz}", backend, f"{P[0]} x {P[1]}", f"{t_f * 1e3:.1f}",
                         f"{n_f * 1e3:.1f}", f"{n_f / t_f:.2f}", f"{t_a * 1e3:.1f}", f"{n_a * 1e3:.1f}",
                         f"{n_a / t_a:.2f}"])
            print(" | ".join(rows[-1]), flush=True)
    head = ["sensor x planes", "FFT backend", "padded grid", "H device ms", "H numpy ms", "speed-up",
            "H^T device ms", "H^T numpy ms", "speed-up"]
    text = (f"Device: **{rt.caps.name}** ({rt.caps.platform}), {os.cpu_count()} host cores; float32; "
            f"data resident on the device; numpy = scipy.fft rfft2/irfft2 with workers=-1 on the same "
            f"padded grid; best of {a.repeat}. `python tools/bench_forward.py`\n\n" + markdown_table(head, rows))
    print(text)
    print("written to", write_section("Forward model H and adjoint H^T (tools/bench_forward.py)", text))


if __name__ == "__main__":
    main()
