/* Flat grey erosion / dilation along lines, van Herk / Gil-Werman: per line, running minima (maxima)
   forward within blocks of the window length L and backward, then each output is the min (max) of two
   values, so the cost per pixel does not depend on L. One work-item per line; line `line` of direction
   `dir` (0: rows, 1: columns, 2: diagonals (1, 1), 3: anti-diagonals (1, -1)). Outputs within `hw`
   of a line's ends are copies of the input (the host pads the image and crops them away).
   g and h are scratch images of the same size. */

static inline void line_start(const int dir, const int line, const int ny, const int nx,
                              int *y0, int *x0, int *dy, int *dx, int *n) {
    if (dir == 0) { *y0 = line; *x0 = 0; *dy = 0; *dx = 1; *n = nx; }
    else if (dir == 1) { *y0 = 0; *x0 = line; *dy = 1; *dx = 0; *n = ny; }
    else if (dir == 2) {              /* lines start on the left column (bottom up), then the top row */
        if (line < ny) { *y0 = ny - 1 - line; *x0 = 0; } else { *y0 = 0; *x0 = line - ny + 1; }
        *dy = 1; *dx = 1; *n = min(ny - *y0, nx - *x0);
    } else {                          /* start on the top row, then the right column */
        if (line < nx) { *y0 = 0; *x0 = line; } else { *y0 = line - nx + 1; *x0 = nx - 1; }
        *dy = 1; *dx = -1; *n = min(ny - *y0, *x0 + 1);
    }
}

__kernel void line_minmax(__global real_t *dst, __global const real_t *src, __global real_t *g,
                          __global real_t *h, const int ny, const int nx, const int dir, const int hw,
                          const int is_max) {
    const int line = get_global_id(0);
    const int nlines = dir == 0 ? ny : (dir == 1 ? nx : ny + nx - 1);
    if (line >= nlines) return;
    int y0, x0, dy, dx, n;
    line_start(dir, line, ny, nx, &y0, &x0, &dy, &dx, &n);
    const int L = 2 * hw + 1;
    #define AT(t) (((size_t)(y0 + (t) * dy)) * (size_t)nx + (size_t)(x0 + (t) * dx))
    #define OP(a, b) (is_max ? fmax((a), (b)) : fmin((a), (b)))
    for (int t = 0; t < n; ++t) {                       /* forward running op within blocks */
        const real_t v = src[AT(t)];
        g[AT(t)] = (t % L == 0) ? v : OP(g[AT(t - 1)], v);
    }
    for (int t = n - 1; t >= 0; --t) {                  /* backward running op within blocks */
        const real_t v = src[AT(t)];
        h[AT(t)] = (t % L == L - 1 || t == n - 1) ? v : OP(h[AT(t + 1)], v);
    }
    for (int t = 0; t < n; ++t) {
        dst[AT(t)] = (t < hw || t >= n - hw) ? src[AT(t)] : OP(h[AT(t - hw)], g[AT(t + hw)]);
    }
    #undef AT
    #undef OP
}
