/* Shared definitions, prepended to every cm2cl kernel file by cm2cl/kernels.py.
 *
 * The real type comes from the build: -D REAL=float -D REAL2=float2 (or double/double2 with
 * -D REAL_IS_DOUBLE).  Complex numbers are REAL2 (x = real part, y = imaginary part).
 * No fast-math options are ever used, so NaN/Inf checks and IEEE rounding hold.
 */
#ifdef REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

typedef REAL real_t;
typedef REAL2 cplx_t;

inline cplx_t cmul(cplx_t a, cplx_t b) {
    return (cplx_t)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

/* conj(a) * b */
inline cplx_t cmulc(cplx_t a, cplx_t b) {
    return (cplx_t)(a.x * b.x + a.y * b.y, a.x * b.y - a.y * b.x);
}

/* Kahan-compensated accumulation: sum += v with running compensation c. */
inline void kahan_add(real_t *sum, real_t *c, real_t v) {
    real_t y = v - *c;
    real_t t = *sum + y;
    *c = (t - *sum) - y;
    *sum = t;
}

inline void kahan_add2(cplx_t *sum, cplx_t *c, cplx_t v) {
    cplx_t y = v - *c;
    cplx_t t = *sum + y;
    *c = (t - *sum) - y;
    *sum = t;
}

/* Tree reduction of one value per work-item over the work-group, in local memory `scratch`
 * (size = local size, a power of two).  Returns the group sum in work-item 0. */
inline real_t group_sum(real_t v, __local real_t *scratch) {
    const size_t lid = get_local_id(0);
    const size_t n = get_local_size(0);
    scratch[lid] = v;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (size_t s = n / 2; s > 0; s >>= 1) {
        if (lid < s) scratch[lid] += scratch[lid + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    real_t r = scratch[0];
    barrier(CLK_LOCAL_MEM_FENCE);
    return r;
}

/* Add the work-group sums of the k values v[0..k) to partials[(slot0 + j) * stride + group_id]
 * (the buffer is zeroed once per iteration; slabs of a volume accumulate).  `scratch` holds
 * k * local size values.  All work-items must call it.  The k sums share one tree (one loop of
 * barriers): each sum's additions are those of group_sum, but PoCL compiles one tree loop in
 * 0.2 s where eight trees in sequence (update_w) took 18 s at the first launch. */
inline void reduce_to(__global real_t *partials, const int stride, __local real_t *scratch,
                      const real_t *v, const int k, const int slot0) {
    const size_t lid = get_local_id(0), n = get_local_size(0);
    for (int j = 0; j < k; j++) scratch[j * n + lid] = v[j];
    barrier(CLK_LOCAL_MEM_FENCE);
    for (size_t s = n / 2; s > 0; s >>= 1) {
        if (lid < s)
            for (int j = 0; j < k; j++) scratch[j * n + lid] += scratch[j * n + lid + s];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0)
        for (int j = 0; j < k; j++) partials[(size_t)(slot0 + j) * stride + get_group_id(0)] += scratch[j * n];
}

/* Coordinates (x, y, z) of element i = (z*ny + y)*nx + x of a slab of ny x nx planes, and their
 * advance by a fixed stride: grid-stride loops then need no integer division per element. */
typedef struct { int cx, cy, cz; } coord_t;

inline coord_t coords_of(const size_t i, const int ny, const int nx) {
    coord_t c;
    c.cx = (int)(i % (size_t)nx);
    c.cy = (int)((i / (size_t)nx) % (size_t)ny);
    c.cz = (int)(i / ((size_t)nx * (size_t)ny));
    return c;
}

inline void coords_advance(coord_t *c, const coord_t s, const int ny, const int nx) {
    c->cx += s.cx;
    if (c->cx >= nx) { c->cx -= nx; c->cy += 1; }
    c->cy += s.cy;
    if (c->cy >= ny) { c->cy -= ny; c->cz += 1; }
    c->cz += s.cz;
}

/* The elements [*first, *end) with stride *step that a work-item reduces (it sums K values; the
 * sums are then combined by a tree in the work-group and by reduce_partials: pairwise-like
 * summation, error O(log n) roundings rather than O(n)).  Work-group g covers
 * the contiguous block [g*L*K, (g+1)*L*K) of the n elements (L = local size, K = elements per
 * work-item).  Inside the block, `contiguous` != 0 gives each work-item K neighbouring elements
 * (CPUs: work-items run one after the other, so the block is walked in order), else the work-items
 * interleave with stride L (GPUs: neighbouring work-items read neighbouring elements, coalesced). */
inline void reduction_range(const size_t n, const int K, const int contiguous,
                            size_t *first, size_t *end, size_t *step) {
    const size_t L = get_local_size(0), lid = get_local_id(0);
    const size_t block = (size_t)get_group_id(0) * L * (size_t)K;
    if (contiguous) {
        *first = block + lid * (size_t)K;
        *end = min(n, *first + (size_t)K);
        *step = 1;
    } else {
        *first = block + lid;
        *end = min(n, block + L * (size_t)K);
        *step = L;
    }
}

/* Forward differences (gx, gy, aw * gz) at element i = (z*ny + y)*nx + x of a slab of `planes`
 * planes, Neumann boundary (zero past the last index); v_next is the next slab of the volume
 * (its first plane is the z+1 neighbour of the last plane) when has_next.  The lateral loads use
 * clamped indices and selects, so the x direction stays vectorisable. */
inline void grad_at(__global const real_t *v, __global const real_t *v_next, const int has_next,
                    const size_t i, const int z, const int y, const int x,
                    const int planes, const int ny, const int nx, const real_t aw,
                    real_t *gx, real_t *gy, real_t *gz) {
    const size_t plane = (size_t)ny * nx;
    const real_t c = v[i];
    const real_t r = v[i + (size_t)(x < nx - 1)], d = v[i + (size_t)(y < ny - 1) * nx];
    *gx = (x < nx - 1) ? r - c : (real_t)0;
    *gy = (y < ny - 1) ? d - c : (real_t)0;
    *gz = 0;
    if (z < planes - 1) *gz = aw * (v[i + plane] - c);
    else if (has_next) *gz = aw * (v_next[i - (size_t)z * plane] - c);
}

/* div p = -grad^T p at element i (plane z of `planes`) of a slab, p = (px, py, pz) the TV dual: backward
 * differences, p taken as 0 past the last index; pz_prev is the previous slab of pz (its last plane is
 * the z-1 neighbour) when has_prev, and has_next says whether a plane follows the slab's last one. */
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

/* The w split's state (the lean state, cm2cl/solver/admm.py): s = x + rho/mu, the argument of the l1
 * prox at the last w update, with c = l1 l1w[z] and mu the threshold's weight and the penalty of that
 * update.  Then exactly
 *     w = max(s - c/mu, 0),   rho = min(mu s, c)      (rho' = rho + mu (x - w') = mu s - mu w').
 * Rounding: w = 0 and rho are as accurate as the explicit ones; where w > 0 it carries an absolute
 * error of a few ulps of c/mu (the explicit update's is of x). */
inline real_t split_w(const real_t s, const real_t c, const real_t mu) { return fmax(s - c / mu, (real_t)0); }
inline real_t split_rho(const real_t s, const real_t c, const real_t mu) { return fmin(mu * s, c); }

/* Loop over the elements a work-item reduces (see reduction_range), with their coordinates
 * (x, y, z) kept up to date without divisions.  Use: FOR_EACH_REDUCED(i, n, ...) { body } */
#define FOR_EACH_REDUCED(i, n, K, contiguous, ny, nx, x, y, z)                                  \
    size_t i##_first, i##_end, i##_step;                                                        \
    reduction_range(n, K, contiguous, &i##_first, &i##_end, &i##_step);                         \
    coord_t i##_c = coords_of(i##_first, ny, nx);                                               \
    const coord_t i##_s = coords_of(i##_step, ny, nx);                                          \
    for (size_t i = i##_first; i < i##_end; i += i##_step, coords_advance(&i##_c, i##_s, ny, nx)) \
        for (int x = i##_c.cx, y = i##_c.cy, z = i##_c.cz, i##_once = 1; i##_once; i##_once = 0)
