/* FFT-domain convolution over depth planes (paper Eq. 3 in the Fourier domain).
 * Spectra are stored plane after plane: a slab of `planes` planes of `nfreq` complex values
 * (nfreq = py * (px/2+1) for real-to-complex FFTs, py * px for complex ones). */

/* Multiply-accumulate over the depth planes of one slab:
 *     acc[k] (+)= sum_i H[i, k] * X[i, k]
 * with Kahan compensation `comp` carried across slabs (first != 0 starts from zero).
 * One work-item per frequency k. */
__kernel void spectral_mac(__global cplx_t *acc, __global cplx_t *comp,
                           __global const cplx_t *H, __global const cplx_t *X,
                           const int planes, const ulong nfreq, const int first) {
    const size_t k = get_global_id(0);
    if (k >= nfreq) return;
    cplx_t s = (cplx_t)(0, 0), c = (cplx_t)(0, 0);
    if (!first) { s = acc[k]; c = comp[k]; }
    for (int i = 0; i < planes; ++i) {
        const size_t j = (size_t)i * nfreq + k;
        kahan_add2(&s, &c, cmul(H[j], X[j]));
    }
    acc[k] = s;
    comp[k] = c;
}

/* Conjugate broadcast (the adjoint of spectral_mac):  X[i, k] = conj(H[i, k]) * V[k]. */
__kernel void spectral_conj_bcast(__global cplx_t *X, __global const cplx_t *H,
                                  __global const cplx_t *V, const int planes, const ulong nfreq) {
    const size_t k = get_global_id(0);
    if (k >= nfreq) return;
    const cplx_t v = V[k];
    for (int i = 0; i < planes; ++i) {
        const size_t j = (size_t)i * nfreq + k;
        X[j] = cmulc(H[j], v);
    }
}

/* Spectral power over depths:  hn2[k] (+)= sum_i |H[i, k]|^2  (first != 0 starts from zero). */
__kernel void spectral_power(__global real_t *hn2, __global const cplx_t *H,
                             const int planes, const ulong nfreq, const int first) {
    const size_t k = get_global_id(0);
    if (k >= nfreq) return;
    real_t s = first ? (real_t)0 : hn2[k];
    for (int i = 0; i < planes; ++i) {
        const cplx_t h = H[(size_t)i * nfreq + k];
        s += h.x * h.x + h.y * h.y;
    }
    hn2[k] = s;
}
