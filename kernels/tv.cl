/* The TV split of the ADMM: u = prox_{tau TV}(z), z = x + eta/mu_u, tau = lambda_tv/mu_u, by
 * projected-gradient (Chambolle) iterations on the dual p = (px, py, pz), warm-started across
 * outer iterations:  p <- P(p + step grad(div p - z/tau)),  u = z - tau div p.
 * grad: forward differences (Neumann), the axial one weighted by aw; div = -grad^T.
 * P: unit ball per voxel (isotropic) or [-1, 1] per component (anisotropic).
 * Volumes are slab-stored: `*_prev` is the previous slab (its last plane is the z-1 neighbour),
 * `*_next` the next one (its first plane is the z+1 neighbour). */

/* div p at element i (plane z of `planes`) of a slab. */
inline real_t div_at(__global const real_t *px, __global const real_t *py, __global const real_t *pz,
                     __global const real_t *pz_prev, const int has_prev, const int has_next,
                     const size_t i, const int z, const int y, const int x,
                     const int planes, const int prev_planes, const int ny, const int nx,
                     const real_t aw) {
    const size_t plane = (size_t)ny * nx;
    /* unconditional loads at clamped indices, then selects: keeps the x direction vectorisable */
    const real_t pxl = px[i - (size_t)(x > 0)], pyl = py[i - (size_t)(y > 0) * nx];
    real_t d = (x < nx - 1 ? px[i] : (real_t)0) - (x > 0 ? pxl : (real_t)0);
    d += (y < ny - 1 ? py[i] : (real_t)0) - (y > 0 ? pyl : (real_t)0);
    const int last = (z == planes - 1) && !has_next;
    real_t dz = last ? (real_t)0 : pz[i];
    if (z > 0) dz -= pz[i - plane];
    else if (has_prev) dz -= pz_prev[(size_t)(prev_planes - 1) * plane + (i - (size_t)z * plane)];
    return d + aw * dz;
}

/* g = div p - (x + eta/mu_u) / tau  over one slab. */
__kernel void tv_residual(__global real_t *g,
                          __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                          __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                          const int has_next, __global const real_t *x, __global const real_t *eta,
                          const real_t inv_mu_u, const real_t inv_tau, const real_t aw,
                          const int planes, const int ny, const int nx) {
    const int xx = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    if (xx >= nx || y >= ny || z >= planes) return;
    const size_t i = ((size_t)z * ny + y) * nx + xx;
    const real_t d = div_at(px, py, pz, pz_prev, has_prev, has_next, i, z, y, xx,
                            planes, prev_planes, ny, nx, aw);
    g[i] = d - (x[i] + eta[i] * inv_mu_u) * inv_tau;
}

/* p <- P(p + step grad g) over one slab; g_next is the next slab of g when has_next. */
__kernel void tv_dual_step(__global real_t *px, __global real_t *py, __global real_t *pz,
                           __global const real_t *g, __global const real_t *g_next, const int has_next,
                           const real_t step, const real_t aw, const int iso,
                           const int planes, const int ny, const int nx) {
    const int xx = get_global_id(0), y = get_global_id(1), z = get_global_id(2);
    if (xx >= nx || y >= ny || z >= planes) return;
    const size_t i = ((size_t)z * ny + y) * nx + xx;
    real_t gx, gy, gz;
    grad_at(g, g_next, has_next, i, z, y, xx, planes, ny, nx, aw, &gx, &gy, &gz);
    real_t a = px[i] + step * gx, b = py[i] + step * gy, d = pz[i] + step * gz;
    if (iso) {
        const real_t nrm = fmax((real_t)1, sqrt(a * a + b * b + d * d));
        const real_t inv = (real_t)1 / nrm;
        a *= inv; b *= inv; d *= inv;
    } else {
        a = clamp(a, (real_t)-1, (real_t)1);
        b = clamp(b, (real_t)-1, (real_t)1);
        d = clamp(d, (real_t)-1, (real_t)1);
    }
    px[i] = a; py[i] = b; pz[i] = d;
}

/* u' = z - tau div p (tau = 0: u' = z);  eta += mu_u (x - u');  u = u'.
 * Reduces into slots slot0 + (0..3): ||x - u'||^2, ||u' - u||^2, ||u'||^2, ||eta'||^2. */
__kernel void tv_finish(__global real_t *u, __global real_t *eta, __global const real_t *x,
                        __global const real_t *px, __global const real_t *py, __global const real_t *pz,
                        __global const real_t *pz_prev, const int has_prev, const int prev_planes,
                        const int has_next, const real_t mu_u, const real_t tau, const real_t aw,
                        const int planes, const int ny, const int nx,
                        __global real_t *partials, const int pstride, __local real_t *scratch,
                        const int slot0, const int per_item, const int contiguous) {
    const size_t n = (size_t)planes * ny * nx;
    real_t a0 = 0, a1 = 0, a2 = 0, a3 = 0;
    const real_t inv_mu = (real_t)1 / mu_u;
    FOR_EACH_REDUCED(i, n, per_item, contiguous, ny, nx, xx, y, z) {
        const real_t xv = x[i], e = eta[i];
        real_t un = xv + e * inv_mu;
        if (tau > 0)
            un -= tau * div_at(px, py, pz, pz_prev, has_prev, has_next, i, z, y, xx,
                               planes, prev_planes, ny, nx, aw);
        const real_t pu = xv - un, du = un - u[i];
        const real_t en = e + mu_u * pu;
        eta[i] = en;
        u[i] = un;
        a0 += pu * pu;
        a1 += du * du;
        a2 += un * un;
        a3 += en * en;
    }
    const real_t sums[4] = {a0, a1, a2, a3};
    reduce_to(partials, pstride, scratch, sums, 4, slot0);
}
