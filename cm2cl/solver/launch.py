"""Launching the solver's kernels: typed kernels called with named arguments (types read from the
kernel's own declaration in ``kernels/*.cl``), each part's row layout, and named reduction slots."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..device import kernels

#: partials per sum of the row kernels at most: enough work-items for a GPU, few enough that
#: reduce_partials stays small next to a volume's pass (measurements: docs/benchmarks.md)
PARTIALS = 2**18
#: elements per work-item of the row kernels at least, per reduction slot: the partials then take at
#: most 1/32 of the volume they sum (the memory model counts on it)
ELEMENTS_PER_SLOT = 32
#: planes per launch of xstep_accumulate on CPUs: fewer streams than the prefetchers follow
#: (docs/benchmarks.md); GPUs take a slab per launch
ACC_PLANES = 4

_DECL = re.compile(r"__kernel\s+void\s+(\w+)\s*\(([^)]*)\)", re.S)


def _arg_kind(decl: str) -> tuple[str, str]:
    """(name, kind) of one parameter of a kernel declaration: kind 'buf', 'local', 'real', 'int', 'ulong'."""
    words = decl.replace("*", " * ").split()
    name = words[-1]
    if "__local" in words:
        return name, "local"
    if "*" in words:
        return name, "buf"
    base = words[-2]
    kinds = {"real_t": "real", "int": "int", "ulong": "ulong", "uint": "uint"}
    if base not in kinds:
        raise TypeError(f"kernel parameter {decl.strip()!r}: scalar type {base!r} not supported")
    return name, kinds[base]


def signatures(text: str) -> dict[str, tuple[tuple[str, str], ...]]:
    """Every ``__kernel`` of an OpenCL source: its parameters as (name, kind), in order."""
    return {m.group(1): tuple(_arg_kind(a) for a in m.group(2).split(",")) for m in _DECL.finditer(text)}


_CASTS = {"int": np.int32, "ulong": np.uint64, "uint": np.uint32}


class Kernels:
    """One device's kernels by name, called with named arguments: buffers (pyopencl arrays or plain
    buffers), reals (cast to the solve's real type) and ints, typed by each kernel's declaration in
    its .cl file; every parameter must be given and none unknown. ``k`` holds the built kernels (a
    test may replace one)."""

    def __init__(self, rt, dtype, names, defines: dict | None = None):
        self.rt, self.real = rt, np.dtype(dtype).type
        self.k, self.params = {}, {}
        for file, name in names:
            self.k[name] = kernels.kernel(rt, file, name, dtype, defines)
            self.params[name] = rt.cached(("signatures", file), lambda f=file: signatures(kernels.source(f)))[name]

    def add(self, other: "Kernels"):
        self.k.update(other.k)
        self.params.update(other.params)

    def args(self, name: str, kw: dict) -> list:
        params = self.params[name]
        names = [n for n, _ in params]
        missing, unknown = set(names) - set(kw), set(kw) - set(names)
        if missing or unknown:
            raise TypeError(f"kernel {name}: missing {sorted(missing)}, unknown {sorted(unknown)}")
        out = []
        for n, kind in params:
            v = kw[n]
            if kind == "buf":
                out.append(getattr(v, "data", v))
            elif kind == "real":
                out.append(self.real(v))
            elif kind == "local":
                out.append(kernels.local_memory(v))
            else:
                out.append(_CASTS[kind](v))
        return out

    def __call__(self, name: str, global_size, **kw):
        """Run ``name`` over ``global_size`` with the local size of :func:`cm2cl.device.kernels.launch`."""
        return kernels.launch(self.rt, self.k[name], global_size, *self.args(name, kw))

    def run(self, name: str, global_size, local_size, **kw):
        """Run ``name`` with an explicit local size."""
        return self.k[name](self.rt.queue, tuple(global_size), tuple(local_size), *self.args(name, kw))


class Slots:
    """Named reduction slots: each reducing kernel writes a run of consecutive sums, registered here
    under the names it writes them as."""

    def __init__(self):
        self.names: list[str] = []
        self.first: dict[str, int] = {}

    def add(self, key: str, names) -> int:
        """Register ``names`` as the sums of kernel launch ``key``; returns its first slot."""
        if key not in self.first:
            self.first[key] = len(self.names)
            self.names.extend(names)
        return self.first[key]

    def __len__(self):
        return len(self.names)

    def named(self, sums) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, sums)}


@dataclass
class RowLayout:
    """How the row kernels (kernels/common.cl) cover one part's planes: ``vw`` reals per x block (a
    build define: VW > 1 walks whole rows per work-item, VW = 1 one x per work-item), ``rows`` rows per
    work-item, ``items`` work-items per row block, and the partials buffer of the sums."""
    vw: int
    rows: int
    items: int
    pstride: int
    partials: object
    local: int
    acc_planes: int | None

    @classmethod
    def make(cls, rt, dtype, padded_shape, held_planes: int, nslots: int, local: int, vw=None, rows=None):
        """The layout on ``rt``: rows per work-item as few as keep the partials per sum within
        PARTIALS and each work-item at ELEMENTS_PER_SLOT x nslots elements or more over
        ``held_planes`` (the planes one launch covers)."""
        ny, nx = padded_shape
        vw = vw or kernels.row_width(rt, dtype)
        items, width = (1, nx) if vw > 1 else (-(-nx // vw), vw)
        if rows is None:
            elements = nslots * ELEMENTS_PER_SLOT
            rows = min(ny, max(-(-elements // (width * held_planes)), -(-items * ny // PARTIALS)))
        rows = int(rows)
        pstride = items * -(-ny // rows)
        return cls(vw, rows, items, pstride, rt.zeros(max(nslots, 1) * pstride, dtype),
                   local, ACC_PLANES if rt.caps.kind == "CPU" else None)

    @property
    def cw(self) -> int:
        """Complex values per work-item of the spectral row kernels (xstep_accumulate, xstep_solve)."""
        return max(self.vw // 2, 1)

    def range(self, ny: int, rows: int) -> tuple:
        """Global size of a row-kernel launch with ``rows`` rows per work-item."""
        blocks = -(-ny // rows)
        return (blocks,) if self.vw > 1 else (self.items, blocks)

    def reduce(self, ks: Kernels, out, nslots: int):
        """Add each slot's partials into ``out`` (one value per slot)."""
        ks.run("reduce_partials", (nslots * self.local,), (self.local,), partials=self.partials, out=out,
               groups=self.pstride, scratch=self.local * self.partials.dtype.itemsize)


__all__ = ["Kernels", "RowLayout", "Slots", "signatures", "PARTIALS", "ACC_PLANES"]
