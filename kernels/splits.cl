/* The w split (l1 + non-negativity) and the v split (crop-aware data term) of the ADMM, each
 * fused with its dual update and with the reductions the log and the stopping rule need: row kernels
 * (common.cl), each work-item adding its sums into the partials that reduce_partials adds up. */

/* After the x step, for one slab of `planes` planes, the w split and its dual from the split's state s
 * (split_w, split_rho in common.cl; l1_s, mu_s: the weight and penalty s was made with):
 *     w = max(s - l1_s l1w[z]/mu_s, 0),  rho = min(mu_s s, l1_s l1w[z])          (the previous ones)
 *     s' = xr + rho/mu_w,   xr = alpha x + (1 - alpha) w   (over-relaxation; alpha = 1: xr = x)
 *     w' = max(s' - l1 l1w[z]/mu_w, 0),  rho' = rho + mu_w (xr - w') = min(mu_w s', l1 l1w[z])
 * (l1w: the weight of each plane of the slab in the l1 term).
 * Reduces into slots slot0 + (0..7): ||x - x_old||^2, ||x||^2, sum l1w|x|, TV(x), ||x - w'||^2, ||w' - w||^2,
 * ||w'||^2, ||rho'||^2 (the last two scale the relative residuals of the stopping rule); TV(x) with
 * forward differences (Neumann boundary), x_next the next slab of x when has_next.
 * A row kernel (common.cl). */
__kernel void update_w(__global const real_t *x, __global const real_t *x_next, const int has_next,
                       __global const real_t *x_old, __global real_t *s,
                       const real_t l1, __global const real_t *l1w, const real_t mu_w,
                       const real_t l1_s, const real_t mu_s, const real_t aw, const int iso, const real_t alpha,
                       const int planes, const int ny, const int nx, const int rows,
                       __global real_t *partials, const int pstride, const int slot0) {
    int xb0, xb1, y0, y1;
    size_t g;
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &g)) return;
    const size_t plane = (size_t)ny * nx;
    realv a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0, a5 = 0, a6 = 0, a7 = 0;
    for (int y = y0; y < y1; y++)
        for (int z = 0; z < planes; z++) {
            const real_t lw = l1w[z];   /* the plane's weight of the l1 term */
            const real_t c = l1 * lw, cs = l1_s * lw;
            realv b0 = 0, b1 = 0, b2 = 0, b3 = 0, b4 = 0, b5 = 0, b6 = 0, b7 = 0;   /* one plane's row */
            for (int xb = xb0; xb < xb1; xb++) {
                const int x0 = xb * VW, cnt = nx - x0;
                const size_t i = slab_index(z, y, x0, ny, nx);
                const realv xi = load_row(x, i, cnt), si = load_row(s, i, cnt);
                const realv wo = split_w(si, cs, mu_s);
                const realv sn = alpha * xi + (1 - alpha) * wo + split_rho(si, cs, mu_s) / mu_w;
                const realv wn = split_w(sn, c, mu_w), rn = split_rho(sn, c, mu_w);
                const realv dx = xi - load_row(x_old, i, cnt), pw = xi - wn, dw = wn - wo;
                store_row(sn, s, i, cnt);
                const realv tv = tv_density(x, x_next, has_next, i, plane, z, planes, cnt, xi, y, ny, nx, aw, iso);
                b0 += lanes_below(dx * dx, cnt);
                b1 += lanes_below(xi * xi, cnt);
                b2 += lanes_below(lw * fabs(xi), cnt);
                b3 += lanes_below(tv, cnt);
                b4 += lanes_below(pw * pw, cnt);
                b5 += lanes_below(dw * dw, cnt);
                b6 += lanes_below(wn * wn, cnt);
                b7 += lanes_below(rn * rn, cnt);
            }
            a0 += b0; a1 += b1; a2 += b2; a3 += b3; a4 += b4; a5 += b5; a6 += b6; a7 += b7;
        }
    const real_t sums[8] = {lanes_sum(a0), lanes_sum(a1), lanes_sum(a2), lanes_sum(a3),
                            lanes_sum(a4), lanes_sum(a5), lanes_sum(a6), lanes_sum(a7)};
    add_partials(partials, pstride, g, slot0, sums, 8);
}

/* w (rho = 0) or rho (rho = 1) of the w split over one slab, from its state s as update_w derives them
 * (state readback). */
__kernel void split_state(__global real_t *out, __global const real_t *s, const int rho,
                          const real_t l1_s, __global const real_t *l1w, const real_t mu_s,
                          const int planes, const int ny, const int nx) {
    const int xx = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    if (xx >= nx || y >= ny || z >= planes) return;
    const size_t i = ((size_t)z * ny + y) * nx + xx;
    const real_t c = l1_s * l1w[z];
    out[i] = rho ? split_rho(s[i], c, mu_s) : split_w(s[i], c, mu_s);
}

/* The v split on the padded plane (py, px), sensor window (my, mx) at (oy, ox), over-relaxed by alpha:
 *   hr = alpha hx + (1 - alpha) v;  v' = (C^T y + mu_v hr + xi) / (C^T C + mu_v);  xi += mu_v (hr - v');  v = v'
 * cty = C^T y (zero outside the window), hx = H x.
 * Reduces into slots slot0 + (0..5): ||hx - v'||^2, ||v' - v||^2, ||C hx - y||^2, ||hx||^2, ||v'||^2,
 * ||xi'||^2. */
__kernel void update_v(__global real_t *v, __global real_t *xi, __global const real_t *hx,
                       __global const real_t *cty, __global const real_t *cw, const real_t mu_v,
                       const real_t alpha, const int py, const int px, const int rows,
                       __global real_t *partials, const int pstride, const int slot0) {
    /* cty: the measurement embedded in the padded grid; cw: each pixel's weight in the data term (1 on
       the sensor, 0 outside it and on masked pixels): v = (cw y + mu_v Hx + xi) / (cw + mu_v).
       A row kernel (common.cl) over the one plane. */
    int xb0, xb1, y0, y1;
    size_t g;
    if (!row_item(px, py, rows, &xb0, &xb1, &y0, &y1, &g)) return;
    realv a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0, a5 = 0;
    for (int y = y0; y < y1; y++)
        for (int xb = xb0; xb < xb1; xb++) {
            const int x0 = xb * VW, cnt = px - x0;
            const size_t i = slab_index(0, y, x0, py, px);
            const realv h = load_row(hx, i, cnt), m = load_row(cw, i, cnt), t = load_row(cty, i, cnt);
            const realv xo = load_row(xi, i, cnt), vo = load_row(v, i, cnt);
            const realv hr = alpha * h + (1 - alpha) * vo;
            const realv vn = (m * t + mu_v * hr + xo) / (m + mu_v);
            const realv pv = h - vn, dv = vn - vo;
            const realv xn = xo + mu_v * (hr - vn);
            const realv d = h - t;
            store_row(xn, xi, i, cnt);
            store_row(vn, v, i, cnt);
            a0 += lanes_below(pv * pv, cnt);
            a1 += lanes_below(dv * dv, cnt);
            a2 += lanes_below(m * d * d, cnt);
            a3 += lanes_below(h * h, cnt);
            a4 += lanes_below(vn * vn, cnt);
            a5 += lanes_below(xn * xn, cnt);
        }
    const real_t sums[6] = {lanes_sum(a0), lanes_sum(a1), lanes_sum(a2), lanes_sum(a3), lanes_sum(a4),
                            lanes_sum(a5)};
    add_partials(partials, pstride, g, slot0, sums, 6);
}
