"""Memory model and planner: bytes the solver allocates on a device for a problem, the layout of its
depth planes over devices (resident or streamed slabs, :mod:`.parts`) that fits the memory it is given,
and the memory the host has available (psutil: Linux, macOS and Windows alike)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..device.fft import spectrum_shape
from ..errors import DeviceError, InputError

__all__ = ["memory_estimate", "check_fits", "host_available_bytes", "plan_layout", "PartPlan", "device_budget",
           "streamed_bytes_per_iteration", "fft_scratch_per_plane", "iteration_bytes", "expected_seconds"]

#: fraction of a device's global memory the planner uses by default (drivers and FFT scratch need some)
BUDGET_FRACTION = 0.9
#: host memory a CPU device's runtime takes beside the buffers once the solver's kernels are built, with
#: a margin: 0.34 GiB of anonymous RSS beyond the buffers and the inputs with 16 planes of a 3360 x 4000
#: grid (PoCL 3.1; tools/bench_fullframe.py's full frame peaked at 20.2 GiB with this reserve)
CPU_RUNTIME_BYTES = 2 ** 30


def host_available_bytes() -> int:
    """Memory the host can give without swapping (psutil's ``available``)."""
    import psutil

    return int(psutil.virtual_memory().available)


#: planes per slab of a lean layout (plan_layout): its x spectra are one slab of these; a few planes
#: keep that slab small next to the volumes, and each slab's kernels long enough to hide their launch
LEAN_SLAB_PLANES = 2

#: real volumes on the padded grid and reduction slots of the default terms' fused set (x, x_old/scratch,
#: s, u, px, py, pz; w, rho and eta derived: cm2cl.solver.terms.fused); other term sets give theirs
REAL_VOLUMES = 7
DEFAULT_SLOTS = 18
#: padded planes of the default data term's own (the background's target, cm2cl.solver.terms.background)
DEFAULT_PLANES = 1


def fft_scratch_per_plane(rt, padded_shape, dtype, backend) -> int:
    """The FFT library's scratch for one plane on ``rt`` (from a one-plane plan; it grows with the batch)."""
    from ..device.fft import get_plan

    return get_plan(rt, padded_shape, 1, dtype, backend).scratch_bytes


def memory_estimate(nz, padded_shape, dtype, backend, scratch_per_plane=0, lean_slab=None,
                    real_volumes=REAL_VOLUMES, nslots=DEFAULT_SLOTS, planes=DEFAULT_PLANES) -> dict:
    """Bytes the solver allocates on one device for ``nz`` resident planes: ``per_plane`` for each depth
    plane, ``fixed`` for the plane buffers; ``scratch_per_plane`` is the FFT library's scratch for one
    plane (:func:`fft_scratch_per_plane`; the one-plane transforms need it once more). ``lean_slab``:
    the lean layout with slabs of that many planes (cm2cl.solver.parts.LEAN_SCRATCH), whose x spectra
    are one slab, a fixed cost, and whose planes hold the real volumes and the PSF spectra only.
    ``real_volumes``, ``nslots`` and ``planes``: the real volumes, the reduction slots and the padded
    planes of their own of the solve's terms (cm2cl.solver.terms; the defaults: the default set's with
    the background in the data term)."""
    py, px = padded_shape
    item = np.dtype(dtype).itemsize
    spec_plane = int(np.prod(spectrum_shape((py, px), backend))) * 2 * item
    real_plane = py * px * item
    # + x spectra + PSF spectra; the reductions' partial sums: nslots per work-item of the row kernels,
    # each of >= 32 nslots elements (cm2cl/solver/launch.py) but for the rounding to whole blocks of x
    # and of rows (at most one more per column block and per row block) and for short columns
    partials = real_plane // 32 + int(nslots) * (py + px + 1) * item
    spectra = 1 if lean_slab else 2
    per_plane = int(real_volumes) * real_plane + spectra * spec_plane + partials + int(scratch_per_plane)
    # planes: v, xi, hx, cty, cw, r and two halos (real); R, S, comp (complex); hn2 (real, spectrum grid)
    fixed = (8 + int(planes)) * real_plane + 3 * spec_plane + spec_plane // 2 + 1024 + int(scratch_per_plane)
    if lean_slab:   # one slab of x spectra, and the plane r_next (real)
        fixed += int(lean_slab) * spec_plane + real_plane
    return {"per_plane": per_plane, "fixed": fixed, "total": nz * per_plane + fixed,
            "real_volume": nz * real_plane, "psf_spectra": nz * spec_plane,
            "volumes_per_plane": int(real_volumes) * real_plane + spectra * spec_plane}


def device_budget(rt, max_memory=None, reserve: int = 0) -> int:
    """Bytes the planner may use on ``rt``: ``max_memory`` (a cap, e.g. for tests) or 90% of its memory.
    A CPU device's buffers are host memory: its memory is what the host has available now less
    ``reserve`` (what the host still needs beside the device's buffers, e.g. the result) and less what
    the runtime itself takes (CPU_RUNTIME_BYTES), whatever the driver reports (PoCL: a quarter of the RAM
    on one machine, allocating beyond it; 94% of it on another, which the inputs already use part of)."""
    mem = int(rt.caps.global_mem)
    if getattr(rt.caps, "kind", None) == "CPU":
        mem = max(host_available_bytes() - int(reserve) - CPU_RUNTIME_BYTES, 0)
    cap = int(mem * BUDGET_FRACTION)
    return min(cap, int(max_memory)) if max_memory else cap


def _of_host(rt) -> str:
    """' of host memory' for a CPU device, whose buffers are the host's (device_budget), else ''."""
    return " of host memory" if getattr(rt.caps, "kind", None) == "CPU" else ""


def size_text(nbytes) -> str:
    """A size for a message, in the unit that shows it with three significant digits (0.00 GiB said
    nothing of a budget of a few KiB)."""
    n = float(nbytes)
    for unit, k in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(n) >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n:.0f} bytes"


def check_fits(rt, nz, padded_shape, dtype, backend, max_memory=None):
    est = memory_estimate(nz, padded_shape, dtype, backend)
    budget = device_budget(rt, max_memory)
    if est["total"] > budget:
        fit = max(0, (budget - est["fixed"]) // est["per_plane"])
        raise DeviceError(
            f"problem too large for device '{rt.caps.name}': {nz} planes on a "
            f"{padded_shape[0]} x {padded_shape[1]} padded grid need {size_text(est['total'])}, "
            f"the device offers {size_text(budget)}; {fit} planes fit at this size "
            "(stream depth slabs, spread them over devices, use fewer planes or bin the measurement)"
        )
    return est


def streamed_bytes_per_iteration(planes, padded_shape, dtype, backend, tv_iters, rhs_ready=True,
                                 relaxed=False) -> int:
    """Host <-> device bytes one iteration moves for ``planes`` streamed planes (halo planes aside):
    each step copies in what it reads and out what it writes (cm2cl.solver.admm): x step V + S in
    (the rhs that the previous TV finish made; ``rhs_ready=False``, the first iteration and after the
    penalties change: 5V + S to make it), S out, then 2S in, V out; w split 3V in, V out; the first TV
    iteration 4V in, 3V + S out, each further one 3V + S in, 3V out; TV finish 6V + S in, 2V out (V: a
    real volume of the planes, S: their spectra; S also carries the TV prox's argument). ``relaxed``
    (over-relaxation, alpha != 1): the first TV iteration also reads u, V more. ``tv_iters=None``: the
    set without TV (cm2cl.solver.terms.fused), whose x step makes its rhs from s (V in) and which has no
    TV steps: 6V + 4S."""
    est = memory_estimate(planes, padded_shape, dtype, backend)
    V, S = est["real_volume"], est["psf_spectra"]
    if tv_iters is None:
        return int(6 * V + 4 * S)
    return int(((1 if rhs_ready else 5) + 1 + 3 + 1 + 6 + 2 + 6 * tv_iters + 1 + (1 if relaxed else 0)) * V
               + (4 + tv_iters + 1) * S)


def iteration_bytes(nz, padded_shape, dtype, backend, tv_iters, lean=False, relaxed=False) -> int:
    """Device memory traffic of one iteration's kernels, each FFT counted as one read and one write:
    FFT V+S; x-step accumulate 2S (reads only) and solve 3S; IFFT S+V; w split 4V; TV: residual 5V (6V
    the first time) and dual step 7V per inner iteration; TV finish 9V, which also makes the next x
    step's rhs (V: a real volume, S: a spectrum volume; rhs_volume's 6V, on the first iteration and
    after the penalties change, are not counted). With cm2cl's FFT ("cl") the solve runs inside the
    IFFT's column pass, which then reads the PSF spectra too: 2S less (ClPlan.inverse_xstep). ``lean``:
    the x step transforms its rhs twice, V+S more. ``relaxed`` (over-relaxation): the first TV residual
    also reads u, V more. ``tv_iters=None``: the set without TV, whose TV steps are one rhs_volume
    from s (2V)."""
    est = memory_estimate(nz, padded_shape, dtype, backend)
    spectra = (5 if backend == "cl" else 7) + (1 if lean else 0)
    tv = 2 if tv_iters is None else 9 + 12 * tv_iters + (1 if relaxed else 0)
    real = 1 + 1 + 4 + 1 + tv + (1 if lean else 0)
    return int(real * est["real_volume"] + spectra * est["psf_spectra"])


#: seconds per iteration over the bandwidth floor of cm2cl's kernels, the larger of the CPUs measured so
#: that estimates do not promise too much (docs/benchmarks.md, "ADMM iteration"); GPUs not measured
KERNEL_FLOOR_RATIO = 2.1


def expected_seconds(layout, padded_shape, dtype, backend, tv_iters, copy_rates, transfer_rates) -> float:
    """Expected seconds per iteration of a layout from rates measured on its devices (by runtime):
    each part's kernels at KERNEL_FLOOR_RATIO x its bandwidth floor, plus its streamed bytes at the
    transfer rate (the larger of the two where double-buffered slabs overlap them); parts on different
    devices run side by side, parts on one device one after another."""
    per_device: dict = {}
    for lp in layout:
        t = KERNEL_FLOOR_RATIO * iteration_bytes(lp.z1 - lp.z0, padded_shape, dtype, backend, tv_iters, lp.lean) \
            / copy_rates[id(lp.rt)]
        if lp.streamed:
            c = streamed_bytes_per_iteration(lp.z1 - lp.z0, padded_shape, dtype, backend, tv_iters) \
                / transfer_rates[id(lp.rt)]
            t = max(t, c) if lp.overlap else t + c
        per_device[id(lp.rt)] = per_device.get(id(lp.rt), 0.0) + t
    return max(per_device.values())


@dataclass(frozen=True)
class PartPlan:
    """Planes [z0, z1) on runtime ``rt``: resident, or streamed in slabs of ``slab_planes``."""
    rt: object
    z0: int
    z1: int
    streamed: bool
    slab_planes: int | None
    device_bytes: int
    host_bytes: int
    overlap: bool = False   #: streamed with two sets of slab buffers: the next slab's copies overlap this one's work
    lean: bool = False      #: resident with one slab of x spectra (memory_estimate's lean_slab: slab_planes)


def plan_layout(nz, padded_shape, dtype, backend, runtimes, *, max_memory=None, stream="auto",
                max_slab_planes=None, scratch_per_plane=0, overlap="auto", lean="auto",
                real_volumes=REAL_VOLUMES, nslots=DEFAULT_SLOTS, planes=DEFAULT_PLANES) -> list[PartPlan]:
    """Spread ``nz`` planes over ``runtimes`` (contiguous runs, in proportion to each device's budget):
    resident where every run fits its device; else resident and lean (``lean`` 'auto' or True: one slab
    of LEAN_SLAB_PLANES planes of x spectra instead of a volume of them, for one more forward FFT per
    iteration) where that fits; else (``stream`` 'auto' or True) streamed slabs sized to the budget.
    ``lean=True`` takes the lean layout even where the whole state fits, ``lean=False`` never;
    ``stream=True`` streams even when resident would fit. Streamed slabs are double-buffered
    (``overlap``: two sets of slab buffers, so that copies overlap work) where the part has two slabs or
    more and two buffers of at least one plane fit; ``overlap='auto'`` double-buffers on devices with
    their own memory (GPUs, accelerators) and not on CPUs, where a copy is the same cores' work and
    double buffering measured no faster (docs/schedule.md). Refuses with the smallest plan's needs when not even
    one streamed plane per device fits."""
    if stream not in ("auto", True, False):
        raise ValueError(f"stream: expected 'auto', True or False, got {stream!r}")
    if overlap not in ("auto", True, False):
        raise ValueError(f"overlap: expected 'auto', True or False, got {overlap!r}")
    if lean not in ("auto", True, False):
        raise ValueError(f"lean: expected 'auto', True or False, got {lean!r}")
    if lean is True and stream is True:
        raise InputError("lean and stream: the lean layout keeps every plane on the device, streaming keeps "
                         "them in host memory; ask for one of them")
    terms = {"real_volumes": real_volumes, "nslots": nslots, "planes": planes}
    est = memory_estimate(1, padded_shape, dtype, backend, scratch_per_plane, **terms)
    per, fixed, vols = est["per_plane"], est["fixed"], est["volumes_per_plane"]
    # beside a CPU device's buffers the host keeps the result (the padded x, gathered at the end)
    result = nz * int(np.prod(padded_shape)) * np.dtype(dtype).itemsize
    budgets = [device_budget(rt, max_memory, reserve=result) for rt in runtimes]
    keep = [(rt, r, bud) for rt, r, bud in zip(runtimes, _proportional_runs(nz, budgets), budgets) if r[1] > r[0]]
    runtimes, runs, budgets = [k[0] for k in keep], [k[1] for k in keep], [k[2] for k in keep]
    if stream is not True and lean is not True and all(fixed + (b - a) * per <= bud for (a, b), bud in zip(runs, budgets)):
        return [PartPlan(rt, a, b, False, max_slab_planes, fixed + (b - a) * per, 0)
                for rt, (a, b) in zip(runtimes, runs)]
    if stream is not True and lean is not False:
        slabs = [int(min(LEAN_SLAB_PLANES, b - a, max_slab_planes or LEAN_SLAB_PLANES)) for a, b in runs]
        need = [_lean_bytes(b - a, slab, padded_shape, dtype, backend, scratch_per_plane, terms)
                for (a, b), slab in zip(runs, slabs)]
        if all(n <= bud for n, bud in zip(need, budgets)):
            return [PartPlan(rt, a, b, False, slab, n, 0, lean=True)
                    for rt, (a, b), slab, n in zip(runtimes, runs, slabs, need)]
    if stream is False:   # the need of the leanest resident layout allowed
        need = max(fixed + (b - a) * per if lean is False else
                   _lean_bytes(b - a, int(min(LEAN_SLAB_PLANES, b - a, max_slab_planes or LEAN_SLAB_PLANES)),
                               padded_shape, dtype, backend, scratch_per_plane, terms) for a, b in runs)
        raise DeviceError(
            f"problem too large to keep on the device{'s' if len(runtimes) > 1 else ''}: {nz} planes on a "
            f"{padded_shape[0]} x {padded_shape[1]} padded grid need {size_text(need)} per device, "
            f"{size_text(min(budgets))} available{_of_host(runtimes[0])}; stream depth slabs from host memory "
            "instead")
    out = []
    for rt, (a, b), bud in zip(runtimes, runs, budgets):
        slab = (bud - fixed) // per
        if slab < 1:
            raise DeviceError(
                f"problem too large even streamed: one depth plane of a {padded_shape[0]} x {padded_shape[1]} "
                f"padded grid needs {size_text(fixed + per)} on device '{rt.caps.name}', "
                f"{size_text(bud)} available{_of_host(rt)} (bin the measurement, use support padding or "
                "lateral tiles)")
        slab = int(min(slab, b - a, max_slab_planes or slab))
        double = (bud - fixed) // (per + vols)   # planes per slab with a second set of slab buffers
        dbl = overlap is True or (overlap == "auto" and rt.caps.kind != "CPU")
        if dbl and double >= 1 and b - a > min(slab, double):
            slab = int(min(double, b - a, max_slab_planes or double))
            out.append(PartPlan(rt, a, b, True, slab, fixed + slab * (per + vols), (b - a) * vols, True))
        else:
            out.append(PartPlan(rt, a, b, True, slab, fixed + slab * per, (b - a) * vols))
    return out


def _lean_bytes(planes, slab, padded_shape, dtype, backend, scratch_per_plane, terms) -> int:
    return memory_estimate(planes, padded_shape, dtype, backend, scratch_per_plane, lean_slab=slab, **terms)["total"]


def _proportional_runs(nz, budgets):
    """Contiguous runs of planes, one per device (empty where a device gets none), in proportion to
    the budgets; in equal parts where no device has a budget (the plan is then refused for memory, naming
    the planes each device would hold, not planned from NaN shares)."""
    b = np.maximum(np.asarray(budgets, float), 0.0)
    share = b / b.sum() if b.sum() > 0 else np.full(b.size, 1.0 / b.size)
    edges = (np.concatenate([[0], np.cumsum(share)]) * nz).round().astype(int)
    edges[-1] = nz
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def peak_rss_bytes() -> int:
    """This process's peak resident memory in bytes, on every OS: ``getrusage`` (KiB on Linux, bytes on
    macOS), psutil's peak working set on Windows (no ``resource`` module there)."""
    import sys

    try:
        import resource
    except ImportError:
        import psutil

        return int(getattr(psutil.Process().memory_info(), "peak_wset", 0))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)
