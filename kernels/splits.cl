/* The w split (l1 + non-negativity) and the v split (crop-aware data term) of the ADMM, each
 * fused with its dual update and with the reductions the log and the stopping rule need.
 * Reductions use a grid-stride loop over the slab (global size = groups * local size); `scratch`
 * holds (number of sums) x local size values (reduce_to in common.cl). */

/* TV integrand of x at element i of a slab (forward differences, Neumann boundary). */
inline real_t tv_at(__global const real_t *x, __global const real_t *x_next, const int has_next,
                    const size_t i, const int z, const int y, const int xx,
                    const int planes, const int ny, const int nx, const real_t aw, const int iso) {
    real_t gx, gy, gz;
    grad_at(x, x_next, has_next, i, z, y, xx, planes, ny, nx, aw, &gx, &gy, &gz);
    return iso ? sqrt(gx * gx + gy * gy + gz * gz) : fabs(gx) + fabs(gy) + fabs(gz);
}

/* After the x step, for one slab of `planes` planes, the w split and its dual from the split's state s
 * (split_w, split_rho in common.cl; l1_s, mu_s: the weight and penalty s was made with):
 *     w = max(s - l1_s l1w[z]/mu_s, 0),  rho = min(mu_s s, l1_s l1w[z])          (the previous ones)
 *     s' = x + rho/mu_w
 *     w' = max(s' - l1 l1w[z]/mu_w, 0),  rho' = rho + mu_w (x - w') = min(mu_w s', l1 l1w[z])
 * (l1w: the weight of each plane of the slab in the l1 term).
 * Reduces into slots slot0 + (0..7): ||x - x_old||^2, ||x||^2, sum l1w|x|, TV(x), ||x - w'||^2, ||w' - w||^2,
 * ||w'||^2, ||rho'||^2 (the last two scale the relative residuals of the stopping rule).
 * x_next is the next slab of x (for the axial difference across slabs) when has_next. */
__kernel void update_w(__global const real_t *x, __global const real_t *x_next, const int has_next,
                       __global const real_t *x_old, __global real_t *s,
                       const real_t l1, __global const real_t *l1w, const real_t mu_w,
                       const real_t l1_s, const real_t mu_s, const real_t aw, const int iso,
                       const int planes, const int ny, const int nx,
                       __global real_t *partials, const int pstride, __local real_t *scratch,
                       const int slot0, const int per_item, const int contiguous) {
    const size_t n = (size_t)planes * ny * nx;
    real_t a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0, a5 = 0, a6 = 0, a7 = 0;
    FOR_EACH_REDUCED(i, n, per_item, contiguous, ny, nx, xx, y, z) {
        const real_t xi = x[i], si = s[i];
        const real_t lw = l1w[z];   /* the plane's weight of the l1 term */
        const real_t c = l1 * lw;
        const real_t cs = l1_s * lw;
        const real_t sn = xi + split_rho(si, cs, mu_s) / mu_w;
        const real_t wn = split_w(sn, c, mu_w), rn = split_rho(sn, c, mu_w);
        const real_t dx = xi - x_old[i], pw = xi - wn, dw = wn - split_w(si, cs, mu_s);
        s[i] = sn;
        a0 += dx * dx;
        a1 += xi * xi;
        a2 += lw * fabs(xi);
        a3 += tv_at(x, x_next, has_next, i, z, y, xx, planes, ny, nx, aw, iso);
        a4 += pw * pw;
        a5 += dw * dw;
        a6 += wn * wn;
        a7 += rn * rn;
    }
    const real_t sums[8] = {a0, a1, a2, a3, a4, a5, a6, a7};
    reduce_to(partials, pstride, scratch, sums, 8, slot0);
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

/* The v split on the padded plane (py, px), sensor window (my, mx) at (oy, ox):
 *   v' = (C^T y + mu_v hx + xi) / (C^T C + mu_v);  xi += mu_v (hx - v');  v = v'
 * cty = C^T y (zero outside the window), hx = H x.
 * Reduces into slots slot0 + (0..5): ||hx - v'||^2, ||v' - v||^2, ||C hx - y||^2, ||hx||^2, ||v'||^2,
 * ||xi'||^2. */
__kernel void update_v(__global real_t *v, __global real_t *xi, __global const real_t *hx,
                       __global const real_t *cty, __global const real_t *cw, const real_t mu_v,
                       const int py, const int px,
                       __global real_t *partials, const int pstride, __local real_t *scratch, const int slot0,
                       const int per_item, const int contiguous) {
    /* cty: the measurement embedded in the padded grid; cw: each pixel's weight in the data term (1 on
       the sensor, 0 outside it and on masked pixels): v = (cw y + mu_v Hx + xi) / (cw + mu_v) */
    const size_t n = (size_t)py * px;
    real_t a0 = 0, a1 = 0, a2 = 0, a3 = 0, a4 = 0, a5 = 0;
    size_t i0, i1, di;
    reduction_range(n, per_item, contiguous, &i0, &i1, &di);
    for (size_t i = i0; i < i1; i += di) {
        const real_t h = hx[i], m = cw[i];
        const real_t vn = (m * cty[i] + mu_v * h + xi[i]) / (m + mu_v);
        const real_t pv = h - vn, dv = vn - v[i];
        const real_t xn = xi[i] + mu_v * pv;
        const real_t d = h - cty[i];
        xi[i] = xn;
        v[i] = vn;
        a2 += m * d * d;
        a0 += pv * pv;
        a1 += dv * dv;
        a3 += h * h;
        a4 += vn * vn;
        a5 += xn * xn;
    }
    const real_t sums[6] = {a0, a1, a2, a3, a4, a5};
    reduce_to(partials, pstride, scratch, sums, 6, slot0);
}
