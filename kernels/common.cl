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

/* Add the work-group sum of `v` to partials[slot * stride + group_id] (the buffer is
 * zeroed once per iteration; slabs of a volume accumulate).  All work-items must call it. */
inline void reduce_to(__global real_t *partials, const int stride, __local real_t *scratch,
                      const real_t v, const int slot) {
    const real_t t = group_sum(v, scratch);
    if (get_local_id(0) == 0) partials[(size_t)slot * stride + get_group_id(0)] += t;
}

/* Coordinates (x, y, z) of element i = (z*ny + y)*nx + x of a slab of ny x nx planes, and their
 * advance by a fixed stride: grid-stride loops then need no integer division per element. */
typedef struct { int x, y, z; } coord_t;

inline coord_t coords_of(const size_t i, const int ny, const int nx) {
    coord_t c;
    c.x = (int)(i % (size_t)nx);
    c.y = (int)((i / (size_t)nx) % (size_t)ny);
    c.z = (int)(i / ((size_t)nx * (size_t)ny));
    return c;
}

inline void coords_advance(coord_t *c, const coord_t s, const int ny, const int nx) {
    c->x += s.x;
    if (c->x >= nx) { c->x -= nx; c->y += 1; }
    c->y += s.y;
    if (c->y >= ny) { c->y -= ny; c->z += 1; }
    c->z += s.z;
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
