"""Where the depth planes of one solve live: a list of parts, each a contiguous run of planes on one
device, either resident (every volume in device memory; lean: all but the x spectra, of which it keeps
one slab) or streamed (the volumes in host memory, one slab at a time on the device).

The ADMM iteration couples planes only through sums over depth (the x step's spectral sum and the
scalars of the stopping rule) and through TV's axial neighbours (one plane across each slab border), so
a solve split this way computes the same iterates as the whole solve: the sums are added on the host in
float64 and the border planes are copied into one-plane halo buffers (docs/design.md, 6 Parts, slabs and streaming).

Each step of an iteration visits every slab with the volumes it reads and writes (:meth:`Part.slabs`);
a streamed part copies the slab's read set to the device before the step and its write set back after
it, so the device holds one slab of each volume plus the plane buffers.

Double buffering (``overlap``): a streamed part with two sets of slab buffers copies on a second queue of
its device. While slab j computes in one set, slab j+1's reads go to the other set, and slab j's writes
come back once its work is done; events order each copy after the last work on its set and each slab's
work after its copies. On devices with their own memory the host copies are pinned (mapped buffers
allocated by the driver), which is what lets a GPU copy while it computes.
"""

from __future__ import annotations

import numpy as np
from ..device.volume import Volume, copy_head, fill, slab_bounds
from ..device.transfer import CopyQueue, work_done, wait_before_work, pinned_array
from ..device.fft import get_plan

#: the solver's real volumes on the padded grid and its complex ones (x spectra, PSF spectra): x, the
#: previous x or scratch g, the w split's state s (w and its dual rho derive from it), u, and the TV dual
#: p = (px, py, pz) (the u split's dual eta = tv div p derives from it); ``spec`` also holds the TV prox's
#: argument z as reals while the x spectra are not needed (the lean state: cm2cl/solver/admm.py)
REAL = ("x", "g", "s", "u", "px", "py", "pz")
COMPLEX = ("spec", "hs")
#: the volumes a lean part keeps one slab of (device memory for 7 real volumes, 3 without TV, and the PSF spectra per
#: plane): the x step transforms each slab's rhs twice, once for the spectral sum and once for the solve,
#: and the TV prox keeps z in g and its residual in this slab (cm2cl/solver/admm.py)
LEAN_SCRATCH = ("spec",)

__all__ = ["Part", "split_planes", "REAL", "COMPLEX", "LEAN_SCRATCH"]


def split_planes(nz: int, parts: int) -> list[tuple[int, int]]:
    """nz planes in ``parts`` contiguous runs of near-equal length."""
    edges = np.linspace(0, nz, parts + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


class Part:
    """Planes [z0, z1) of the volume on runtime ``rt``.

    ``slab_planes`` caps the planes per slab (device buffers are also capped by the device's largest
    allocation). ``streamed``: the volumes live in host memory and each slab is copied to one set of
    device buffers for each step."""

    def __init__(self, rt, z0, z1, padded_shape, spec_plane, dtype, cdtype, *, slab_planes=None,
                 streamed=False, overlap=False, pinned=None, lean=False, real=REAL, planes=()):
        self.rt, self.z0, self.z1 = rt, int(z0), int(z1)
        self.P, self.spec_plane = tuple(padded_shape), tuple(spec_plane)
        self.dtype, self.cdtype = np.dtype(dtype), np.dtype(cdtype)
        self.streamed = bool(streamed)
        if lean and self.streamed:
            raise ValueError("lean: a part is lean (one slab of spectra) or streamed, not both")
        self.lean = bool(lean)
        plane_bytes = int(np.prod(self.spec_plane)) * self.cdtype.itemsize
        if 2 * int(np.prod(self.spec_plane)) < int(np.prod(self.P)):   # spec holds a real volume (z) too
            raise ValueError(f"spectrum plane {self.spec_plane} holds fewer reals than a padded plane {self.P}")
        self.bounds = slab_bounds(self.z1 - self.z0, plane_bytes, rt.caps.max_alloc, slab_planes)
        self.max_planes = max(b - a for a, b in self.bounds)
        shapes = {n: (self.P, self.dtype) for n in real} | {n: (self.spec_plane, self.cdtype) for n in COMPLEX}
        self.overlap = self.streamed and bool(overlap) and len(self.bounds) > 1
        self.copy_queue = CopyQueue(rt) if self.overlap else None
        self.busy = [None, None]   # per slab-buffer set: the event of the last work that used it
        self._pinned = []
        if self.streamed:
            pin = rt.caps.kind != "CPU" if pinned is None else bool(pinned)
            self.host = {n: [self._host_array((b - a,) + s, d, pin) for a, b in self.bounds]
                         for n, (s, d) in shapes.items()}
            self.slots = [{n: rt.zeros((self.max_planes,) + s, d) for n, (s, d) in shapes.items()}
                          for _ in range(2 if self.overlap else 1)]
            self.vol = None
        else:
            self.vol = {n: Volume(rt, self.bounds, s, d) for n, (s, d) in shapes.items()
                        if not (self.lean and n in LEAN_SCRATCH)}
        #: lean parts: one slab of each LEAN_SCRATCH volume, whatever slab it serves
        self.scratch = {n: rt.zeros((self.max_planes,) + shapes[n][0], shapes[n][1])
                        for n in (LEAN_SCRATCH if self.lean else ())}
        plane = lambda shape, dt: Volume(rt, [(0, 1)], shape, dt).slabs[0]  # noqa: E731
        self.planes = {n: plane(self.P, self.dtype) for n in ("v", "xi", "hx", "cty", "cw", "r",
                                                              "halo_prev", "halo_next") + tuple(planes)}
        self.planes |= {n: plane(self.spec_plane, self.cdtype) for n in ("R", "S", "comp")}
        self.planes["hn2"] = plane(self.spec_plane, self.dtype)
        if self.lean:   # the first plane of the TV residual of the slab after the one being visited
            self.planes["r_next"] = fill(rt, plane(self.P, self.dtype), 0)
        self.moved_bytes = 0   # host <-> device traffic of the streamed slabs
        #: the solver's kernels on this part (cm2cl.solver.launch.Kernels) and the row kernels' layout
        #: (cm2cl.solver.launch.RowLayout), set by the solver
        self.kernels = None
        self.row = None

    # ---- the kernels and their layout (views for tests and tools) ---------------------------------
    @property
    def k(self) -> dict:
        """The built kernels by name (a test may replace one, e.g. to count its launches)."""
        return self.kernels.k

    @property
    def vw(self) -> int:
        return self.row.vw

    @property
    def rows(self) -> int:
        return self.row.rows

    @property
    def acc_planes(self):
        return self.row.acc_planes

    @acc_planes.setter
    def acc_planes(self, value):
        self.row.acc_planes = value

    def _host_array(self, shape, dtype, pinned: bool) -> np.ndarray:
        """A zeroed host array; ``pinned``: mapped from a buffer the driver allocates in host memory
        (page-locked on GPUs), or a plain one where the driver refuses."""
        if pinned:
            arr, buf = pinned_array(self.rt, shape, dtype)
            if arr is not None:
                self._pinned.append(buf)
                return arr
        return np.zeros(shape, dtype)

    # ---- allocation figures -------------------------------------------------------------------
    @property
    def device_bytes(self) -> int:
        if self.streamed:
            vols = sum(a.nbytes for slot in self.slots for a in slot.values())
        else:
            vols = sum(v.nbytes for v in self.vol.values()) + sum(a.nbytes for a in self.scratch.values())
        return vols + sum(a.nbytes for a in self.planes.values())

    @property
    def host_bytes(self) -> int:
        return sum(a.nbytes for arrs in self.host.values() for a in arrs) if self.streamed else 0

    def plan(self, planes: int, backend: str):
        return get_plan(self.rt, self.P, planes, self.dtype, backend)

    # ---- slab access -------------------------------------------------------------------------------
    def arrays(self, j: int, names) -> dict:
        """Device arrays of slab ``j`` (resident parts: the volumes themselves; streamed: the slots,
        whatever they hold)."""
        a, b = self.bounds[j]
        if self.streamed:
            slot = self.slots[j % len(self.slots)]
            return {n: slot[n][: b - a] for n in names}
        return {n: self.scratch[n][: b - a] if n in self.scratch else self.vol[n].slabs[j] for n in names}

    def whole(self, names):
        """Device arrays of all the part's planes of ``names`` where each is one allocation (resident
        volumes; not the lean scratch, nor the x spectra, whose slabs hold z as reals slab by slab),
        else None."""
        if self.streamed or any(n in self.scratch or n in COMPLEX for n in names):
            return None
        out = {n: self.vol[n].whole for n in names}
        return None if any(a is None for a in out.values()) else out

    def slabs(self, reads=(), writes=(), scratch=(), edges=(), reverse=False):
        """Visit each slab (last first with ``reverse``): yields (j, planes, arrays) with the device
        arrays of ``reads``, ``writes``, ``scratch`` and ``edges``; a streamed part copies ``reads`` in
        before and ``writes`` out after, and of ``edges`` only the first plane (a neighbour's halo)."""
        names = tuple(dict.fromkeys(tuple(reads) + tuple(writes) + tuple(scratch) + tuple(edges)))
        order = range(len(self.bounds) - 1, -1, -1) if reverse else range(len(self.bounds))
        if self.overlap:
            yield from self._overlapped(list(order), names, reads, writes, edges)
            return
        for j in order:
            a, b = self.bounds[j]
            arr = self.arrays(j, names)
            if self.streamed:
                for n in reads:
                    arr[n].set(self.host[n][j])
                    self.moved_bytes += self.host[n][j].nbytes
            yield j, b - a, arr
            if self.streamed:
                for n in writes:
                    arr[n].get(ary=self.host[n][j])
                    self.moved_bytes += self.host[n][j].nbytes
                for n in edges:
                    arr[n][0:1].get(ary=self.host[n][j][0:1])
                    self.moved_bytes += self.host[n][j][0].nbytes

    def _overlapped(self, order, names, reads, writes, edges):
        """:meth:`slabs` with two buffer sets: copies on the copy queue, work on the device's queue."""
        cq = self.copy_queue

        def upload(j):
            arr = self.arrays(j, names)
            wait = [e for e in (self.busy[j % 2],) if e is not None]
            for n in reads:
                cq.upload(arr[n], self.host[n][j], wait)
                self.moved_bytes += self.host[n][j].nbytes
            # complete once these copies and every earlier one (the write-backs of the slab that used
            # this set before) are: the slab's work waits for it even when it reads nothing
            return cq.marker(wait)

        try:
            pending = upload(order[0])
            for k, j in enumerate(order):
                if k + 1 < len(order):   # the next slab's reads, while this one computes
                    nxt = upload(order[k + 1])
                wait_before_work(self.rt, [pending])
                a, b = self.bounds[j]
                arr = self.arrays(j, names)
                yield j, b - a, arr
                done = work_done(self.rt)
                self.busy[j % 2] = done
                for n in writes:
                    cq.download(self.host[n][j], arr[n], [done])
                    self.moved_bytes += self.host[n][j].nbytes
                for n in edges:
                    cq.download(self.host[n][j][0:1], arr[n][0:1], [done])
                    self.moved_bytes += self.host[n][j][0].nbytes
                if k + 1 < len(order):
                    pending = nxt
        finally:
            cq.finish()

    def sync(self):
        """Wait for the copy queue (host copies are current afterwards)."""
        if self.copy_queue is not None:
            self.copy_queue.finish()

    def neighbour(self, name: str, j: int, which: str):
        """The device array holding the plane next to slab ``j`` inside this part (``which`` = 'next':
        the first plane of slab j+1, 'prev': the last plane of slab j-1), with its plane count; a
        streamed part copies that plane into a halo buffer."""
        k = j + 1 if which == "next" else j - 1
        if name in self.scratch:   # lean: only the next slab's first plane is kept, and only of the residual
            assert which == "next", which
            return self.planes["r_next"], 1
        if not self.streamed:
            s = self.vol[name].slabs[k]
            return s, s.shape[0]
        self.sync()
        src = self.host[name][k]
        return self.load_halo(which, src[0] if which == "next" else src[-1]), 1

    def keep_first_plane(self, arr, plane: str):
        """Copy the first plane of ``arr`` (reals of the padded grid; a slab of scratch) to the plane
        buffer ``plane``, on the device."""
        copy_head(self.rt, self.planes[plane], arr)

    def load_halo(self, which: str, plane: np.ndarray):
        buf = self.planes["halo_" + which]
        buf.set(np.ascontiguousarray(plane, self.dtype)[None])
        self.moved_bytes += buf.nbytes
        return buf

    def edge_plane(self, name: str, which: str) -> np.ndarray:
        """The part's first ('first') or last ('last') plane of volume ``name`` on the host."""
        j = 0 if which == "first" else len(self.bounds) - 1
        if name in self.scratch:   # lean: the first plane as the last visit (slab 0, visits in reverse) left it
            assert which == "first", which
            return self.planes["r_next"].get()[0]
        if self.streamed:
            return self.host[name][j][0 if which == "first" else -1]
        s = self.vol[name].slabs[j]
        self.moved_bytes += s[0].nbytes
        return (s[0] if which == "first" else s[s.shape[0] - 1]).get()

    # ---- whole volumes -------------------------------------------------------------------------------
    def fill(self, name: str, value=0):
        if self.streamed:
            for h in self.host[name]:
                h.fill(value)
        else:
            self.vol[name].fill(value)

    def plane_of(self, name: str):
        """(plane shape, dtype) of volume ``name``."""
        a = self.host[name][0] if self.streamed else self.vol[name].slabs[0]
        return tuple(a.shape[1:]), a.dtype

    def get(self, name: str, out=None) -> np.ndarray:
        """Volume ``name`` of this part's planes on the host, into ``out`` where given (no other copy)."""
        if self.streamed:
            return np.concatenate(self.host[name], axis=0, out=out)
        return self.vol[name].get(out=out)

    def swap(self, a: str, b: str):
        """Exchange two volumes' roles (no copy)."""
        store = self.host if self.streamed else self.vol
        store[a], store[b] = store[b], store[a]
        if self.streamed:
            for slot in self.slots:
                slot[a], slot[b] = slot[b], slot[a]

    def scale(self, name: str, factor):
        """Multiply a volume by a real scalar in place (the PSF spectra's normalisation)."""
        if self.streamed:
            for h in self.host[name]:
                h *= self.dtype.type(factor)
        else:
            self.vol[name].scale(factor)
