"""Walking the depth planes of a solve: every slab of every part (:mod:`.parts`) with the arrays a
step reads and writes, and the neighbouring planes across slab and part borders (TV's axial
differences), wherever they live."""

from __future__ import annotations

import numpy as np

from ..device.volume import fill, upload


class Walk:
    """The parts of one solve, walked slab by slab (part i, slab j, n planes, arrays ``a``)."""

    def __init__(self, parts):
        self.parts = parts

    def slabs(self, reads=(), writes=(), scratch=(), edges=(), reverse=False):
        """Every slab of every part (the last first with ``reverse``): (i, part, j, n, arrays)."""
        order = range(len(self.parts) - 1, -1, -1) if reverse else range(len(self.parts))
        for i in order:
            for j, n, a in self.parts[i].slabs(reads, writes, scratch, edges, reverse):
                yield i, self.parts[i], j, n, a

    def runs(self, reads=(), writes=()):
        """Every run of planes a kernel that touches no scratch can take in one launch: a resident part
        whose volumes are one allocation each, all its planes at once (fewer, longer launches), else
        each slab: (i, part, first slab, last slab, planes, arrays)."""
        for i, part in enumerate(self.parts):
            whole = part.whole(tuple(reads) + tuple(writes))
            if whole is not None:
                yield i, part, 0, len(part.bounds) - 1, part.z1 - part.z0, whole
                continue
            for j, n, a in part.slabs(reads, writes):
                yield i, part, j, j, n, a

    def has_next(self, i, j) -> bool:
        return j + 1 < len(self.parts[i].bounds) or i + 1 < len(self.parts)

    def next(self, i, j, name):
        """(array, has_next): the plane after slab j of part i, in part i's memory."""
        part = self.parts[i]
        if j + 1 < len(part.bounds):
            return part.neighbour(name, j, "next")[0], True
        if i + 1 < len(self.parts):
            return part.load_halo("next", self.parts[i + 1].edge_plane(name, "first")), True
        return None, False

    def prev(self, i, j, name):
        """(array, planes, has_prev): the plane before slab j of part i, in part i's memory."""
        part = self.parts[i]
        if j > 0:
            return (*part.neighbour(name, j, "prev"), True)
        if i > 0:
            return part.load_halo("prev", self.parts[i - 1].edge_plane(name, "last")), 1, True
        return None, 1, False

    def neighbours(self, i, j0, j1, a, name):
        """The named arguments of a stencil kernel for ``name``'s plane before slab j0 (pz_prev, has_prev,
        prev_planes) and whether a slab follows j1 (has_next)."""
        prev, pn, hp = self.prev(i, j0, name)
        return {f"{name}_prev": prev if hp else a[name], "has_prev": hp, "prev_planes": pn,
                "has_next": self.has_next(i, j1)}

    def fill(self, names, value=0):
        for part in self.parts:
            for n in names:
                if n in part.planes:
                    fill(part.rt, part.planes[n], value)
                else:
                    part.fill(n, value)

    def gather(self, name) -> np.ndarray:
        """Volume ``name`` of all parts in one host array, each part read into its planes (one copy: a
        full frame's volume is gigabytes)."""
        first = self.parts[0]
        plane, dtype = first.plane_of(name)
        out = np.empty((self.parts[-1].z1 - first.z0,) + plane, dtype)
        for part in self.parts:
            part.get(name, out=out[part.z0 - first.z0:part.z1 - first.z0])
        return out

    def scatter(self, name, value):
        for part in self.parts:
            for j, n, a in part.slabs(writes=(name,)):
                z = part.z0 + part.bounds[j][0]
                upload(a[name], np.ascontiguousarray(value[z:z + n], a[name].dtype))

    @property
    def moved_bytes(self) -> int:
        return sum(part.moved_bytes for part in self.parts)


__all__ = ["Walk"]
