/* Kernels of the generic terms (cm2cl/solver/terms): each regulariser of a split z = x keeps its
 * split variable and its unscaled dual as volumes of their own, so that a new term needs no change to
 * another's kernels. (The default set's fused kernels, splits.cl and tv.cl, derive them instead.)
 * All are row kernels (common.cl); the reducing ones add their sums into the partials at slot0. */

/* Reduces ||x - x_old||^2 and ||x||^2 over one slab (the change of the iterate, the stopping rule). */
__kernel void x_change(__global const real_t *x, __global const real_t *x_old,
                       const int planes, const int ny, const int nx, const int rows,
                       __global real_t *partials, const int pstride, const int slot0) {
    ROW_ITEM(nx, ny, rows);
    realv a0 = 0, a1 = 0;
    for (int y = y0; y < y1; y++)
        for (int z = 0; z < planes; z++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(z, y, x0, ny, nx);
                const realv xi = load_row(x, i, cnt), dx = xi - load_row(x_old, i, cnt);
                a0 += lanes_below(dx * dx, cnt);
                a1 += lanes_below(xi * xi, cnt);
            }
    const real_t sums[2] = {lanes_sum(a0), lanes_sum(a1)};
    add_partials(partials, pstride, g, slot0, sums, 2);
}

/* out = (add ? out : 0) + a p + b q over one slab: an identity split's part of the x step's right-hand
 * side (a = mu, p = z, b = -1, q = dual), the TV prox's argument x + eta / mu (add = 0, b = 1/mu). */
__kernel void combine(__global real_t *out, __global const real_t *p, __global const real_t *q,
                      const real_t a, const real_t b, const int add, const int planes, const int ny,
                      const int nx, const int rows) {
    ROW_ITEM(nx, ny, rows);
    for (int y = y0; y < y1; y++)
        for (int zz = 0; zz < planes; zz++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(zz, y, x0, ny, nx);
                const realv r = a * load_row(p, i, cnt) + b * load_row(q, i, cnt);
                store_row(add ? load_row(out, i, cnt) + r : r, out, i, cnt);
            }
}

/* The l1 + non-negativity split w = x with weights c = l1 l1w[z] (l1w: each plane's weight), times lw[i]
 * per voxel when `voxel` (reweighted l1):
 *     w' = max(x + rho/mu - c/mu, 0),   rho' = rho + mu (x - w')
 * Reduces sum c/l1 |x|, ||x - w'||^2, ||w' - w||^2, ||w'||^2, ||rho'||^2. */
__kernel void l1_update(__global const real_t *x, __global real_t *w, __global real_t *rho,
                        const real_t l1, __global const real_t *l1w, __global const real_t *lw, const int voxel,
                        const real_t mu, const real_t alpha, const int planes, const int ny, const int nx,
                        const int rows, __global real_t *partials, const int pstride, const int slot0) {
    ROW_ITEM(nx, ny, rows);
    realv a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0;
    for (int y = y0; y < y1; y++)
        for (int z = 0; z < planes; z++) {
            const real_t pw = l1w[z];
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(z, y, x0, ny, nx);
                const realv xi = load_row(x, i, cnt), wo = load_row(w, i, cnt), ro = load_row(rho, i, cnt);
                const realv wt = voxel ? pw * load_row(lw, i, cnt) : (realv)pw, c = l1 * wt;
                const realv xr = alpha * xi + (1 - alpha) * wo;   /* over-relaxed x */
                const realv wn = fmax(xr + ro / mu - c / mu, (real_t)0);
                const realv rn = ro + mu * (xr - wn);
                const realv pr = xi - wn, dw = wn - wo;
                store_row(wn, w, i, cnt);
                store_row(rn, rho, i, cnt);
                a0 += lanes_below(wt * fabs(xi), cnt);
                a1 += lanes_below(pr * pr, cnt);
                a2 += lanes_below(dw * dw, cnt);
                a3 += lanes_below(wn * wn, cnt);
                a4 += lanes_below(rn * rn, cnt);
            }
        }
    ADD_SUMS5(a0, a1, a2, a3, a4);
}

/* The TV split u = x after the dual iterations (tv.cl) on p:
 *     u' = z - tau div p (u' = z with tau = 0: TV off),   eta' = eta + mu (x - u')
 * Reduces TV(x) (forward differences, Neumann; x_next: the next slab of x when has_next),
 * ||x - u'||^2, ||u' - u||^2, ||u'||^2, ||eta'||^2. */
__kernel void tv_update(__global real_t *u, __global real_t *eta, __global const real_t *x,
                        __global const real_t *x_next, const int has_next, __global const real_t *z,
                        __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                        __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                        const real_t tau, const real_t mu, const real_t aw, const int iso,
                        const int planes, const int ny, const int nx, const int rows,
                        __global real_t *partials, const int pstride, const int slot0) {
    ROW_ITEM(nx, ny, rows);
    const size_t plane = (size_t)ny * nx;
    realv a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0;
    for (int y = y0; y < y1; y++)
        for (int zz = 0; zz < planes; zz++)
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(zz, y, x0, ny, nx);
                const realv xv = load_row(x, i, cnt), zv = load_row(z, i, cnt);
                realv un = zv;
                if (tau > 0)
                    un -= tau * div_step(px, py, pz, pz_prev, has_prev, prev_planes, i, plane, x0, cnt, y, zz,
                                         planes, has_next, ny, nx, aw);
                /* eta + mu (xr - u') with z = xr + eta / mu (xr: the over-relaxed x) */
                const realv en = mu * (zv - un);
                const realv pu = xv - un, du = un - load_row(u, i, cnt);
                store_row(un, u, i, cnt);
                store_row(en, eta, i, cnt);
                const realv tv = tv_density(x, x_next, has_next, i, plane, zz, planes, cnt, xv, y, ny, nx, aw, iso);
                a0 += lanes_below(tv, cnt);
                a1 += lanes_below(pu * pu, cnt);
                a2 += lanes_below(du * du, cnt);
                a3 += lanes_below(un * un, cnt);
                a4 += lanes_below(en * en, cnt);
            }
    ADD_SUMS5(a0, a1, a2, a3, a4);
}
