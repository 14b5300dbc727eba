"""The CM2 forward operator on the device (paper Eq. 3) and its adjoint.

    y = C sum_i h_i (*) x_i

Depth planes i, PSF h_i on the sensor grid M = (My, Mx) with the optical axis at pixel
(My//2, Mx//2); object x on the padded grid P = (Py, Px) >= 2M - 1, so that light from emitters
outside the field of view is modelled (unknown boundary); (*) is circular convolution on P by
FFT; C crops P to the sensor window [oy:oy+My, ox:ox+Mx], oy = (Py-My)//2, ox = (Px-Mx)//2.
With P >= 2M - 1 no wrapped-around light reaches the window.
"""

from __future__ import annotations

import numpy as np

from .. import validate
from ..device import fft, kernels
from ..device.runtime import get_runtime
from ..errors import InputError
from ..device.volume import Volume, slab_bounds


def min_padded_shape(sensor_shape, psf=None):
    """Smallest padded grid without wrap-around into the sensor: M + K - 1, K the span of the PSF stack's
    nonzero entries (its exact support); 2M - 1 for a PSF that may fill the whole sensor (``psf`` None).
    (Entries past the array centre's reach wrap into the grid's end: the span counts in array order.)"""
    if psf is None:
        return tuple(2 * int(m) - 1 for m in sensor_shape)
    (y0, y1), (x0, x1) = psf_support(psf, 1.0)
    return tuple(int(m) + k - 1 for m, k in zip(sensor_shape, (y1 - y0 + 1, x1 - x0 + 1)))


def choose_padded_shape(sensor_shape, backend: str):
    """The padded grid a backend is fast on for a sensor (2M - 1 at least; :func:`fast_grid`)."""
    return fast_grid(min_padded_shape(sensor_shape), backend)


#: planes of at least this many voxels avoid the strides that fast_grid avoids
FAST_GRID_MIN_PLANE = 1 << 16
#: ... the largest power of two a plane's voxel count may hold (float32: 32 KiB; measured fine at 2^13,
#: slower at 2^15 and above)
FAST_GRID_MAX_POW2 = 1 << 13
#: ... and the multiple of which a row's length is (the CPU row kernels' 8 float32 / 4 float64, 32 bytes)
FAST_GRID_ROW_MULTIPLE = 8


def fast_grid(need, backend: str) -> tuple[int, int]:
    """The grid (Py, Px) >= ``need`` to pad to: powers of two for reikna; for cl and vkfft ('auto'
    resolves as on a CPU device) even 2/3/5/7-smooth sizes (fft.good_size), and for planes of
    FAST_GRID_MIN_PLANE voxels or more the pair of the fewest voxels among the first few such sizes per
    axis whose plane holds no power of two above FAST_GRID_MAX_POW2 and whose rows are a multiple of
    FAST_GRID_ROW_MULTIPLE long. Why: the volume kernels walk the planes of a slab at a stride of one
    plane, and a plane of a multiple of 64 KiB puts every plane in the same sets of the cache; rows that
    are not whole vectors cost the row kernels a partial vector on every row (measured: docs/benchmarks.md,
    "Padded grid choice")."""
    backend = fft.resolve_backend(backend)
    ny, nx = (max(int(n), 1) for n in need)
    first = (fft.good_size(ny, backend), fft.good_size(nx, backend))
    if backend == "reikna" or ny * nx < FAST_GRID_MIN_PLANE:
        return first

    def sizes(n, multiple, count=8):
        out, m = [], n
        while len(out) < count:
            m = fft.good_size(m, backend)
            if m % multiple == 0:
                out.append(m)
            m += 1
        return out

    def pow2(n):
        return n & -n

    pairs = [(py * px, px, py) for py in sizes(ny, 1) for px in sizes(nx, FAST_GRID_ROW_MULTIPLE)
             if pow2(py * px) <= FAST_GRID_MAX_POW2]
    if not pairs:
        return first
    _, px, py = min(pairs)
    return py, px


def psf_support(psf, fraction: float = 1 - 1e-6) -> tuple[tuple[int, int], tuple[int, int]]:
    """((y0, y1), (x0, x1)): per lateral axis, the smallest index range holding ``fraction`` of the PSF
    stack's light (all planes), the rest split between the two tails."""
    h = psf[None] if np.ndim(psf) == 2 else psf
    # the profiles plane by plane in float64 (no copy of the stack: a full frame's is gigabytes)
    profs = [np.zeros(h.shape[1]), np.zeros(h.shape[2])]
    for plane in h:
        a = np.abs(np.asarray(plane, np.float64))
        profs[0] += a.sum(axis=1)
        profs[1] += a.sum(axis=0)
    tail = (1.0 - fraction) / 2.0
    out = []
    for prof in profs:
        nz = np.flatnonzero(prof)
        if nz.size == 0:
            out.append((0, prof.size - 1))
            continue
        if tail <= 0:
            out.append((int(nz[0]), int(nz[-1])))
            continue
        c = np.cumsum(prof) / prof.sum()
        lo = int(np.searchsorted(c, tail, side="right"))
        hi = min(int(np.searchsorted(c, 1.0 - tail, side="left")), int(nz[-1]))
        out.append((max(min(lo, hi), int(nz[0])), hi))
    return out[0], out[1]


def support_padding(psf, backend: str, fraction: float = 1 - 1e-6):
    """(psf, padded_shape, info) for padding to M + K - 1 instead of 2M - 1, K the PSF stack's support
    (:func:`psf_support`): circular convolution on that grid equals the linear one on the sensor for a PSF
    zero outside its support, so the PSF is truncated there (the light dropped is ``info['light_dropped']``,
    at most 1 - fraction). ``info`` also has the support K and the voxels saved against 2M - 1."""
    h = np.asarray(psf)   # in its own dtype: a copy of a full frame's stack in float64 is gigabytes
    h = h[None] if h.ndim == 2 else h
    M = h.shape[1:]
    (y0, y1), (x0, x1) = psf_support(h, fraction)
    K = (y1 - y0 + 1, x1 - x0 + 1)
    backend = fft.resolve_backend(backend)
    P = fast_grid([min(m + k - 1, 2 * m - 1) for m, k in zip(M, K)], backend)
    if (y0, y1, x0, x1) == (0, M[0] - 1, 0, M[1] - 1):
        t = h   # the support is the whole sensor: nothing to truncate, no copy
    else:
        t = np.zeros_like(h)
        t[:, y0:y1 + 1, x0:x1 + 1] = h[:, y0:y1 + 1, x0:x1 + 1]
    full = choose_padded_shape(M, backend)
    info = {"support_px": list(K), "padded_shape": list(P), "full_padded_shape": list(full),
            "voxel_fraction": float(np.prod(P) / np.prod(full)),
            "light_dropped": float(1.0 - t.sum(dtype=np.float64) / max(h.sum(dtype=np.float64), 1e-300))}
    return t, P, info


def crop_offsets(sensor_shape, padded_shape):
    return tuple((int(p) - int(m)) // 2 for m, p in zip(sensor_shape, padded_shape))


def centered_psf(psf: np.ndarray, padded_shape) -> np.ndarray:
    """PSF planes embedded in the padded grid with the optical axis moved to index (0, 0)."""
    nz, my, mx = psf.shape
    py, px = padded_shape
    out = np.zeros((nz, py, px), psf.dtype)
    out[:, :my, :mx] = psf
    return np.roll(out, (-(my // 2), -(mx // 2)), axis=(1, 2))


class ForwardModel:
    """H (and its adjoint) for one PSF stack on one OpenCL device.

    Parameters
    ----------
    psf : (nz, My, Mx) or (My, Mx) float array
        PSF per depth plane on the sensor grid (camera offset already removed).
    dtype : float32 (default) or float64 (needs a device with fp64).
    backend : 'auto', 'cl', 'vkfft' or 'reikna' (see cm2cl.device.fft).
    device : device index, name fragment, pyopencl Device or Runtime; default per cm2cl.device.
    padded_shape : (Py, Px) >= 2M - 1; default the backend's fast size.
    max_slab_planes : cap on depth planes per device buffer (default: as the device allows).
    """

    def __init__(self, psf, *, dtype=np.float32, backend="auto", device=None,
                 padded_shape=None, max_slab_planes=None):
        psf = validate.psf_stack(psf, "psf")
        self.rt = get_runtime(device)
        self.dtype = self.rt.check_dtype(dtype)
        self.cdtype = fft.complex_dtype(self.dtype)
        self.backend = fft.resolve_backend(backend, self.rt)
        self.nz = psf.shape[0]
        self.sensor_shape = tuple(psf.shape[1:])
        if padded_shape is None:
            padded_shape = choose_padded_shape(self.sensor_shape, self.backend)
        padded_shape = tuple(int(p) for p in padded_shape)
        need = min_padded_shape(self.sensor_shape, psf)
        if len(padded_shape) != 2 or any(p < n for p, n in zip(padded_shape, need)) \
                or any(p < m for p, m in zip(padded_shape, self.sensor_shape)):
            raise InputError(f"padded_shape: {padded_shape} is smaller than sensor + PSF support - 1 = {need} "
                             f"for sensor {self.sensor_shape}")
        self.padded_shape = padded_shape
        self.offsets = crop_offsets(self.sensor_shape, padded_shape)
        oy, ox = self.offsets
        my, mx = self.sensor_shape
        self.crop = (slice(oy, oy + my), slice(ox, ox + mx))

        plan1 = fft.get_plan(self.rt, padded_shape, 1, self.dtype, self.backend)
        self.spec_plane = plan1.spec_shape[1:]
        self.nfreq = int(np.prod(self.spec_plane))
        plane_bytes = self.nfreq * self.cdtype.itemsize
        self.bounds = slab_bounds(self.nz, plane_bytes, self.rt.caps.max_alloc, max_slab_planes)
        self._plan2d = plan1

        # PSF spectra, computed on the device once.
        self.psf_spectra = self.new_spectrum_volume()
        hc = centered_psf(psf, padded_shape)
        for (z0, z1), hs in self.psf_spectra:
            tmp = Volume(self.rt, [(0, z1 - z0)], padded_shape, self.dtype).set(hc[z0:z1])
            self.plan(z1 - z0).forward(tmp.slabs[0], hs)
        self._k_mac = kernels.kernel(self.rt, "fft_conv.cl", "spectral_mac", self.dtype)
        self._k_bcast = kernels.kernel(self.rt, "fft_conv.cl", "spectral_conj_bcast", self.dtype)
        self._k_crop = kernels.kernel(self.rt, "layout.cl", "crop", self.dtype)
        self._k_embed = kernels.kernel(self.rt, "layout.cl", "embed", self.dtype)
        self._scratch = {}

    # ---- allocation helpers -------------------------------------------------------------
    def plan(self, planes: int):
        return fft.get_plan(self.rt, self.padded_shape, planes, self.dtype, self.backend)

    def new_volume(self) -> Volume:
        """A real (nz, Py, Px) volume with this model's slab bounds."""
        return Volume(self.rt, self.bounds, self.padded_shape, self.dtype)

    def new_spectrum_volume(self) -> Volume:
        return Volume(self.rt, self.bounds, self.spec_plane, self.cdtype)

    def new_plane(self, spectrum: bool = False) -> Volume:
        shape = self.spec_plane if spectrum else self.padded_shape
        return Volume(self.rt, [(0, 1)], shape, self.cdtype if spectrum else self.dtype)

    def _scratch_get(self, name, factory):
        if name not in self._scratch:
            self._scratch[name] = factory()
        return self._scratch[name]

    # ---- device-level building blocks (arrays stay on the device) ------------------------
    def mac(self, spectra: Volume, out, comp):
        """out = sum_i H_i X_i over all depth planes (Kahan-compensated); out, comp: plane arrays."""
        n = np.uint64(self.nfreq)
        for first, ((z0, z1), xs), hs in zip([1] + [0] * len(self.bounds), spectra, self.psf_spectra.slabs):
            kernels.launch(self.rt, self._k_mac, (self.nfreq,), out.data, comp.data, hs.data, xs.data,
                           np.int32(z1 - z0), n, np.int32(first))
        return out

    def conj_bcast(self, v, spectra: Volume):
        """spectra_i = conj(H_i) v for every depth plane."""
        n = np.uint64(self.nfreq)
        for ((z0, z1), xs), hs in zip(spectra, self.psf_spectra.slabs):
            kernels.launch(self.rt, self._k_bcast, (self.nfreq,), xs.data, hs.data, v.data, np.int32(z1 - z0), n)
        return spectra

    def crop_to_sensor(self, padded, out):
        my, mx = self.sensor_shape
        py, px = self.padded_shape
        planes = padded.shape[0] if padded.ndim == 3 else 1
        kernels.launch(self.rt, self._k_crop, (mx, my, planes), out.data, padded.data,
                       *map(np.int32, (my, mx, py, px, *self.offsets)))
        return out

    def embed_from_sensor(self, sensor, out):
        my, mx = self.sensor_shape
        py, px = self.padded_shape
        planes = sensor.shape[0] if sensor.ndim == 3 else 1
        kernels.launch(self.rt, self._k_embed, (px, py, planes), out.data, sensor.data,
                       *map(np.int32, (my, mx, py, px, *self.offsets)))
        return out

    def convolve_device(self, x: Volume, out_plane):
        """out_plane (1, Py, Px) = sum_i h_i (*) x_i, without the crop."""
        acc = self._scratch_get("acc", lambda: self.new_plane(True))
        comp = self._scratch_get("comp", lambda: self.new_plane(True))
        spec = self._scratch_get("spec", self.new_spectrum_volume)
        for ((z0, z1), xs), (_, ss) in zip(x, spec):
            self.plan(z1 - z0).forward(xs, ss)
        self.mac(spec, acc.slabs[0], comp.slabs[0])
        self._plan2d.inverse(acc.slabs[0], out_plane)
        return out_plane

    def adjoint_padded_device(self, v_plane, out: Volume):
        """out = H^T v for a padded-grid plane v (1, Py, Px)."""
        vs = self._scratch_get("acc", lambda: self.new_plane(True))
        spec = self._scratch_get("spec", self.new_spectrum_volume)
        self._plan2d.forward(v_plane, vs.slabs[0])
        self.conj_bcast(vs.slabs[0], spec)
        for ((z0, z1), xs), (_, ss) in zip(out, spec):
            self.plan(z1 - z0).inverse(ss, xs)
        return out

    # ---- numpy in, numpy out -------------------------------------------------------------
    def _volume_arg(self, x, name="x"):
        x = validate.real_array(x, name, ndims=(2, 3))
        if x.ndim == 2:
            x = x[None]
        want = (self.nz,) + self.padded_shape
        if x.shape != want:
            raise InputError(f"{name}: shape {x.shape} does not fit the model: expected "
                             f"(nz, Py, Px) = {want} (padded grid)")
        return x

    def _sensor_arg(self, y, name="y"):
        y = validate.real_array(y, name, ndims=(2,))
        if y.shape != self.sensor_shape:
            raise InputError(f"{name}: shape {y.shape} does not match the PSF's sensor grid {self.sensor_shape}")
        return y

    def convolve(self, x) -> np.ndarray:
        """sum_i h_i (*) x_i on the padded grid (no crop); x is (nz, Py, Px)."""
        x = self._volume_arg(x)
        xv = self._scratch_get("x", self.new_volume).set(x)
        out = self._scratch_get("plane", self.new_plane)
        return self.convolve_device(xv, out.slabs[0]).get()[0]

    def forward(self, x) -> np.ndarray:
        """y = C H x: the (My, Mx) sensor image of a (nz, Py, Px) object."""
        x = self._volume_arg(x)
        xv = self._scratch_get("x", self.new_volume).set(x)
        plane = self._scratch_get("plane", self.new_plane)
        self.convolve_device(xv, plane.slabs[0])
        y = self._scratch_get("sensor", lambda: Volume(self.rt, [(0, 1)], self.sensor_shape, self.dtype))
        self.crop_to_sensor(plane.slabs[0], y.slabs[0])
        return y.get()[0]

    def adjoint(self, y) -> np.ndarray:
        """x = H^T C^T y: the (nz, Py, Px) back-projection of a (My, Mx) sensor image."""
        y = self._sensor_arg(y)
        ys = self._scratch_get("sensor", lambda: Volume(self.rt, [(0, 1)], self.sensor_shape, self.dtype))
        ys.set(y[None])
        plane = self._scratch_get("plane", self.new_plane)
        self.embed_from_sensor(ys.slabs[0], plane.slabs[0])
        xv = self._scratch_get("x", self.new_volume)
        self.adjoint_padded_device(plane.slabs[0], xv)
        return xv.get()
