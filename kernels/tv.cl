/* The TV split of the ADMM: u = prox_{tau TV}(z), z = x + eta/mu_u, tau = lambda_tv/mu_u, by
 * projected-gradient (Chambolle) iterations on the dual p = (px, py, pz), warm-started across
 * outer iterations:  p <- P(p + step grad(div p - z/tau)),  u = z - tau div p.
 * grad: forward differences (Neumann), the axial one weighted by aw; div = -grad^T (grad_xy, div_step in common.cl).
 * P: unit ball per voxel (isotropic) or [-1, 1] per component (anisotropic).
 * The dual eta is not stored: eta' = eta + mu_u (x - u') = mu_u tau div p = lambda_tv div p, with p as
 * the last dual iterations left it (eta = 0 while p = 0, at the start and with TV off).
 * Volumes are slab-stored: `*_prev` is the previous slab (its last plane is the z-1 neighbour),
 * `*_next` the next one (its first plane is the z+1 neighbour). */

/* g = div p - z / tau over one slab.  z = xr + eta/mu_u = xr + tau div p (xr = alpha x + (1 - alpha) u,
 * the over-relaxed x) is constant over the dual iterations of one outer iteration: the first (`first`,
 * p still the previous outer iteration's) computes it and stores it in `z`, the later ones read it from
 * there (u is read only when alpha != 1).
 * This and the other kernels of this file are row kernels (common.cl), `rows` rows per work-item. */
__kernel void tv_residual(__global real_t *g,
                          __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                          __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                          const int has_next, __global const real_t *x, __global real_t *z, const int first,
                          __global const real_t *u, const real_t alpha,
                          const real_t tau, const real_t inv_tau, const real_t aw,
                          const int planes, const int ny, const int nx, const int rows) {
    int xb0, xb1, y0, y1;
    size_t item;
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &item)) return;
    const size_t plane = (size_t)ny * nx;
    for (int y = y0; y < y1; y++)
        for (int zz = 0; zz < planes; zz++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(zz, y, x0, ny, nx);
                const realv d = div_step(px, py, pz, pz_prev, has_prev, prev_planes, i, plane, x0, cnt, y, zz,
                                         planes, has_next, ny, nx, aw);
                realv zv;
                if (first) {   /* over-relaxed: xr = alpha x + (1 - alpha) u (u: the previous u') */
                    const realv xv = load_row(x, i, cnt);
                    zv = (alpha == 1 ? xv : alpha * xv + (1 - alpha) * load_row(u, i, cnt)) + tau * d;
                    store_row(zv, z, i, cnt);
                } else {
                    zv = load_row(z, i, cnt);
                }
                store_row(d - zv * inv_tau, g, i, cnt);
            }
}

/* p <- P(p + step grad g) over one slab; g_next is the next slab of g when has_next. */
__kernel void tv_dual_step(__global real_t *px, __global real_t *py, __global real_t *pz,
                           __global const real_t *g, __global const real_t *g_next, const int has_next,
                           const real_t step, const real_t aw, const int iso,
                           const int planes, const int ny, const int nx, const int rows) {
    int xb0, xb1, y0, y1;
    size_t item;
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &item)) return;
    const size_t plane = (size_t)ny * nx;
    for (int y = y0; y < y1; y++)
        for (int z = 0; z < planes; z++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(z, y, x0, ny, nx);
                const realv gc = load_row(g, i, cnt);
                const realv gn = next_plane(g, g_next, has_next, i, plane, z, planes, cnt, gc);
                realv gx, gy;
                grad_xy(g, i, gc, cnt, y, ny, nx, &gx, &gy);
                realv a = load_row(px, i, cnt) + step * gx, b = load_row(py, i, cnt) + step * gy;
                realv d = load_row(pz, i, cnt) + step * aw * (gn - gc);
                if (iso) {
                    const realv inv = (real_t)1 / fmax((realv)1, sqrt(a * a + b * b + d * d));
                    a *= inv; b *= inv; d *= inv;
                } else {
                    a = clamp(a, (real_t)-1, (real_t)1);
                    b = clamp(b, (real_t)-1, (real_t)1);
                    d = clamp(d, (real_t)-1, (real_t)1);
                }
                store_row(a, px, i, cnt);
                store_row(b, py, i, cnt);
                store_row(d, pz, i, cnt);
            }
}

/* u' = z - tau div p and eta' = lambda_tv div p (tau = 0, TV off: u' = x, eta' = 0); z as tv_residual
 * stored it.  Reduces into slots slot0 + (0..3): ||x - u'||^2, ||u' - u||^2, ||u'||^2, ||eta'||^2.
 * With `rhs`, also writes the next x step's right-hand side t = mu_u u' - eta' + mu_w w - rho (as
 * rhs_volume in xstep.cl, w and rho from s with c = l1_s l1w[z] and mu_s) for the penalties mu_u, mu_w
 * it is given: the solver uses it when they still hold at that x step, which then skips rhs_volume
 * (reads u, s and p, writes t) for this kernel's extra read of s and write of t. */
__kernel void tv_finish(__global real_t *u, __global const real_t *x, __global const real_t *z,
                        __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                        __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                        const int has_next, const real_t tv, const real_t tau, const real_t aw,
                        __global real_t *t, __global const real_t *s, const int rhs, const real_t mu_u,
                        const real_t mu_w, const real_t l1_s, __global const real_t *l1w, const real_t mu_s,
                        const int planes, const int ny, const int nx, const int rows,
                        __global real_t *partials, const int pstride, const int slot0) {
    int xb0, xb1, y0, y1;
    size_t g;
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &g)) return;
    const size_t plane = (size_t)ny * nx;
    realv a0 = 0, a1 = 0, a2 = 0, a3 = 0;
    for (int y = y0; y < y1; y++)
        for (int zz = 0; zz < planes; zz++) {
            realv b0 = 0, b1 = 0, b2 = 0, b3 = 0;   /* the sums of one plane's row, then added up */
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(zz, y, x0, ny, nx);
                const realv xv = load_row(x, i, cnt);
                realv un = xv, en = 0;
                if (tau > 0) {
                    const realv d = div_step(px, py, pz, pz_prev, has_prev, prev_planes, i, plane, x0, cnt, y,
                                             zz, planes, has_next, ny, nx, aw);
                    un = load_row(z, i, cnt) - tau * d;
                    en = tv * d;
                }
                const realv pu = xv - un, du = un - load_row(u, i, cnt);
                store_row(un, u, i, cnt);
                if (rhs) store_row(x_rhs(un, en, load_row(s, i, cnt), mu_u, mu_w, l1_s * l1w[zz], mu_s), t, i, cnt);
                b0 += lanes_below(pu * pu, cnt);
                b1 += lanes_below(du * du, cnt);
                b2 += lanes_below(un * un, cnt);
                b3 += lanes_below(en * en, cnt);
            }
            a0 += b0; a1 += b1; a2 += b2; a3 += b3;
        }
    const real_t sums[4] = {lanes_sum(a0), lanes_sum(a1), lanes_sum(a2), lanes_sum(a3)};
    add_partials(partials, pstride, g, slot0, sums, 4);
}

/* eta = lambda_tv div p over one slab: the TV split's dual as the iteration derives it (state readback). */
__kernel void tv_eta(__global real_t *eta,
                     __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                     __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                     const int has_next, const real_t tv, const real_t aw,
                     const int planes, const int ny, const int nx, const int rows) {
    int xb0, xb1, y0, y1;
    size_t item;
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &item)) return;
    const size_t plane = (size_t)ny * nx;
    for (int y = y0; y < y1; y++)
        for (int zz = 0; zz < planes; zz++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(zz, y, x0, ny, nx);
                store_row(tv * div_step(px, py, pz, pz_prev, has_prev, prev_planes, i, plane, x0, cnt, y, zz,
                                        planes, has_next, ny, nx, aw), eta, i, cnt);
            }
}
