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

/* Write the work-group sum of `v` to partials[slot * groups + group_id]; `first` != 0 overwrites,
 * else adds (to accumulate over the slabs of a volume).  All work-items must call it. */
inline void reduce_to(__global real_t *partials, __local real_t *scratch, real_t v,
                      const int slot, const int first) {
    const real_t t = group_sum(v, scratch);
    if (get_local_id(0) == 0) {
        const size_t j = (size_t)slot * get_num_groups(0) + get_group_id(0);
        partials[j] = first ? t : partials[j] + t;
    }
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

/* The elements [*first, *end) with stride *step that work-item get_global_id(0) reduces over n:
 * contiguous chunks on CPUs (chunked != 0: cache lines used whole), a grid stride on GPUs
 * (coalesced accesses across neighbouring work-items). */
inline void reduction_range(const size_t n, const int chunked, size_t *first, size_t *end, size_t *step) {
    const size_t gid = get_global_id(0), gs = get_global_size(0);
    if (chunked) {
        const size_t chunk = (n + gs - 1) / gs;
        *first = min(n, gid * chunk);
        *end = min(n, *first + chunk);
        *step = 1;
    } else {
        *first = gid;
        *end = n;
        *step = gs;
    }
}
