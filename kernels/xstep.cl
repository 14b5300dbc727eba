/* The closed-form x step of the ADMM (docs/design.md, 3.1 The x step):
 *     (mu_v H^T H + c I) x = H^T (mu_v v - xi) + (mu_u u - eta) + (mu_w w - rho),  c = mu_u + mu_w
 * Per lateral frequency k, H^T H = a a^H with a_i = conj(H_i(k)), so by Sherman-Morrison
 *     X_i = (B_i - mu_v conj(H_i) HX) / c,   HX = (sum_i H_i B_i) / (c + mu_v sum_i |H_i|^2)
 * and HX is also the spectrum of H x.  Spectra: `planes` planes of `nfreq` complex values. */

/* Right-hand side in the object domain over one slab:  t = mu_u u - eta + mu_w w - rho,  with the duals
 * and w derived from the state the iteration keeps: eta = tv div p (tv.cl), w = max(s - c/mu_s, 0) and
 * rho = min(mu_s s, c) with c = l1_s l1w[z] (splits.cl); pz_prev: the previous slab of pz when has_prev.
 * The solver needs it only where tv_finish's copy (made for the penalties of the iteration before)
 * does not apply: the first iteration, and after the penalties change. */
__kernel void rhs_volume(__global real_t *t, __global const real_t *u, __global const real_t *s,
                         __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                         __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                         const int has_next, const real_t mu_u, const real_t mu_w, const real_t tv,
                         const real_t l1_s, __global const real_t *l1w, const real_t mu_s, const real_t aw,
                         const int planes, const int ny, const int nx, const int rows) {
    /* a row kernel (common.cl) */
    int xb0, xb1, y0, y1;
    size_t item;
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &item)) return;
    const size_t plane = (size_t)ny * nx;
    for (int y = y0; y < y1; y++)
        for (int z = 0; z < planes; z++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(z, y, x0, ny, nx);
                realv eta = 0;
                if (tv > 0) {
                    eta = tv * div_step(px, py, pz, pz_prev, has_prev, prev_planes, i, plane, x0, cnt, y, z,
                                        planes, has_next, ny, nx, aw);
                }
                store_row(x_rhs(load_row(u, i, cnt), eta, load_row(s, i, cnt), mu_u, mu_w, l1_s * l1w[z], mu_s),
                          t, i, cnt);
            }
}

/* Right-hand side of the v split (one padded plane):  r = mu_v v - xi. */
__kernel void rhs_plane(__global real_t *r, __global const real_t *v, __global const real_t *xi,
                        const real_t mu_v, const ulong n) {
    const size_t i = get_global_id(0);
    if (i < n) r[i] = mu_v * v[i] - xi[i];
}

/* S (+)= sum_i H_i B_i over planes i in [p0, p1) with B_i = conj(H_i) R + T_i (Kahan, carried in comp);
 * B is not stored: the solve forms it again from T, H and R (one spectrum volume less written per
 * iteration). A launch may take a run of planes only: it continues from the S and comp the previous one
 * stored (not `first`), the same additions as in one launch, bit for bit. On CPUs the solver launches
 * runs of ACC_PLANES (cm2cl/solver/admm.py): a work-item reading 2 x 16 planes at once streams from 32
 * places, more than the CPU's prefetchers follow.
 * CW frequencies per work-item (complex row vectors, common.cl): global size ceil(nfreq / CW). */
__kernel void xstep_accumulate(__global const cplx_t *T, __global const cplx_t *H, __global const cplx_t *R,
                               __global cplx_t *S, __global cplx_t *comp,
                               const int p0, const int p1, const ulong nfreq, const int first) {
    const size_t k = get_global_id(0) * CW;
    if (k >= nfreq) return;
    const size_t cnt = nfreq - k;
    chalf_t rr, ri, sr = 0, si = 0, cr = 0, ci = 0;
    cload(R, k, cnt, &rr, &ri);
    if (!first) {
        cload(S, k, cnt, &sr, &si);
        cload(comp, k, cnt, &cr, &ci);
    }
    for (int i = p0; i < p1; ++i) {
        const size_t j = (size_t)i * nfreq + k;
        chalf_t hr, hi, tr, ti;
        cload(H, j, cnt, &hr, &hi);
        cload(T, j, cnt, &tr, &ti);
        const chalf_t br = (hr * rr + hi * ri) + tr, bi = (hr * ri - hi * rr) + ti;   /* cmulc(h, r) + t */
        /* Kahan: s += h * b (cmul), carried in c (kahan_add2) */
        const chalf_t yr = (hr * br - hi * bi) - cr, yi = (hr * bi + hi * br) - ci;
        const chalf_t ur = sr + yr, ui = si + yi;
        cr = (ur - sr) - yr;
        ci = (ui - si) - yi;
        sr = ur;
        si = ui;
    }
    cstore(sr, si, S, k, cnt);
    cstore(cr, ci, comp, k, cnt);
}

/* HX = S / (c + mu_v hn2), in place over S. */
__kernel void xstep_hx(__global cplx_t *S, __global const real_t *hn2,
                       const real_t c, const real_t mu_v, const ulong nfreq) {
    const size_t k = get_global_id(0);
    if (k < nfreq) S[k] = S[k] / (c + mu_v * hn2[k]);
}

/* X_i = (B_i - mu_v conj(H_i) HX) / c with B_i = conj(H_i) R + T_i (as xstep_accumulate formed it),
 * in place over T; CW frequencies per work-item (as xstep_accumulate). */
__kernel void xstep_solve(__global cplx_t *T, __global const cplx_t *H, __global const cplx_t *R,
                          __global const cplx_t *HX, const real_t c, const real_t mu_v, const int planes,
                          const ulong nfreq) {
    const size_t k = get_global_id(0) * CW;
    if (k >= nfreq) return;
    const size_t cnt = nfreq - k;
    chalf_t rr, ri, xr, xi;
    cload(R, k, cnt, &rr, &ri);
    cload(HX, k, cnt, &xr, &xi);
    const real_t inv_c = (real_t)1 / c;
    for (int i = 0; i < planes; ++i) {
        const size_t j = (size_t)i * nfreq + k;
        chalf_t hr, hi, tr, ti;
        cload(H, j, cnt, &hr, &hi);
        cload(T, j, cnt, &tr, &ti);
        const chalf_t br = (hr * rr + hi * ri) + tr, bi = (hr * ri - hi * rr) + ti;   /* cmulc(h, r) + t */
        /* (b - mu_v cmulc(h, hx)) * inv_c */
        cstore((br - mu_v * (hr * xr + hi * xi)) * inv_c, (bi - mu_v * (hr * xi - hi * xr)) * inv_c, T, j, cnt);
    }
}
