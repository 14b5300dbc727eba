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

/* The w split's state (the lean state, cm2cl/solver/admm.py): s = x + rho/mu, the argument of the l1
 * prox at the last w update, with c = l1 l1w[z] and mu the threshold's weight and the penalty of that
 * update.  Then exactly
 *     w = max(s - c/mu, 0),   rho = min(mu s, c)      (rho' = rho + mu (x - w') = mu s - mu w').
 * Rounding: w = 0 and rho are as accurate as the explicit ones; where w > 0 it carries an absolute
 * error of a few ulps of c/mu (the explicit update's is of x). */
#define split_w(s, c, mu) fmax((s) - (c) / (mu), (real_t)0)
#define split_rho(s, c, mu) fmin((mu) * (s), (c))
/* (s, c, mu: reals or realv vectors alike) */

/* The x step's right-hand side in the object domain, mu_u u - eta + mu_w w - rho, with w and rho from
 * the w split's state s (c = l1 l1w[z], mu_s: as above); rhs_volume (xstep.cl) and tv_finish (tv.cl,
 * for the next x step) both form it. */
#define x_rhs(u, eta, s, mu_u, mu_w, c, mu_s) \
    ((mu_u) * (u) - (eta) + (mu_w) * split_w(s, c, mu_s) - split_rho(s, c, mu_s))

/* ---- Row kernels: the volume kernels of the iteration (stencils and update-and-reduce) ------------
 * A work-item handles VW neighbouring x as one vector (a block of x), for a block of `rows` rows of
 * every plane of the slab; values of the plane below or above (the axial neighbour) are loaded again
 * where needed. The reducing kernels add their sums into one partial per work-item (reduce_partials adds
 * those up): no barriers, no local memory.
 * VW is a build define (cm2cl/device/kernels.py): 32 bytes of reals on CPUs, where PoCL compiles a
 * work-item's vector code to SIMD instructions (work-items with loops or barriers stay scalar, 5x
 * slower: docs/benchmarks.md), and 1 on GPUs, where neighbouring work-items read neighbouring x.
 * The walk (row_item): on CPUs (VW > 1: ROW_WALK) a work-item takes whole rows, every x block of a
 * plane's row before the next plane's, so that the CPU's prefetchers follow a few sequential streams
 * (docs/benchmarks.md, "Access order on CPUs"); global size (row blocks). On GPUs a work-item per x block walks the planes;
 * global size (x blocks, row blocks).
 * Lanes past the row's end (x >= nx: `cnt` = nx - x0 lanes are real) load the row's last element,
 * are never written and are masked out of the sums. */
#ifndef VW
#define VW 1
#endif
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#if VW == 1
typedef real_t realv;
#elif VW == 4 || VW == 8
typedef CAT(REAL, VW) realv;
#ifdef REAL_IS_DOUBLE
typedef CAT(long, VW) maskv;
#else
typedef CAT(int, VW) maskv;
#endif
#else
#error "VW must be 1, 4 or 8"
#endif

/* the VW reals at p[i..): cnt of them real (cnt >= 1), the rest copies of the last */
inline realv load_row(__global const real_t *p, const size_t i, const int cnt) {
#if VW == 1
    return p[i];
#else
    if (cnt >= VW) return CAT(vload, VW)(0, p + i);
    real_t t[VW];
    for (int k = 0; k < VW; k++) t[k] = p[i + min(k, cnt - 1)];
    return CAT(vload, VW)(0, t);
#endif
}

/* p[i..i+min(cnt, VW)) = the first lanes of v */
inline void store_row(const realv v, __global real_t *p, const size_t i, const int cnt) {
#if VW == 1
    p[i] = v;
#else
    if (cnt >= VW) { CAT(vstore, VW)(v, 0, p + i); return; }
    real_t t[VW];
    CAT(vstore, VW)(v, 0, t);
    for (int k = 0; k < cnt; k++) p[i + k] = t[k];
#endif
}

/* v's lanes moved one down, `next` in the last one (each lane's right neighbour) */
inline realv from_right(const realv v, const real_t next) {
#if VW == 1
    return next;
#elif VW == 4
    return (realv)(v.s123, next);
#else
    return (realv)(v.s1234, v.s567, next);
#endif
}

/* v's lanes moved one up, `prev` in the first one (each lane's left neighbour) */
inline realv from_left(const real_t prev, const realv v) {
#if VW == 1
    return prev;
#elif VW == 4
    return (realv)(prev, v.s012);
#else
    return (realv)(prev, v.s0123, v.s456);
#endif
}

/* v where lane k < lim, else 0 */
inline realv lanes_below(const realv v, const int lim) {
#if VW == 1
    return 0 < lim ? v : (real_t)0;
#elif VW == 4
    return select((realv)0, v, (maskv)(0, 1, 2, 3) < (maskv)lim);
#else
    return select((realv)0, v, (maskv)(0, 1, 2, 3, 4, 5, 6, 7) < (maskv)lim);
#endif
}

/* sum of the lanes (pairwise) */
inline real_t lanes_sum(const realv v) {
#if VW == 1
    return v;
#elif VW == 4
    const CAT(REAL, 2) b = v.lo + v.hi;
    return b.x + b.y;
#else
    const CAT(REAL, 4) a = v.lo + v.hi;
    const CAT(REAL, 2) b = a.lo + a.hi;
    return b.x + b.y;
#endif
}

#if VW > 1
#define ROW_WALK 1
#endif

/* The work-item's place: x blocks [xb0, xb1) (block xb: x0 = xb VW, cnt = nx - x0 real lanes), rows
 * [y0, y1), and its partial index g; returns 0 for the work-items past the last block (the launch pads
 * dimension 0). */
inline int row_item(const int nx, const int ny, const int rows,
                    int *xb0, int *xb1, int *y0, int *y1, size_t *g) {
    const int nxb = (nx + VW - 1) / VW;
#ifdef ROW_WALK
    const int yb = get_global_id(0);
    *xb0 = 0;
    *xb1 = nxb;
    *g = yb;
#else
    const int xb = get_global_id(0), yb = get_global_id(1);
    if (xb >= nxb) return 0;
    *xb0 = xb;
    *xb1 = xb + 1;
    *g = (size_t)xb + (size_t)nxb * (size_t)yb;
#endif
    *y0 = yb * rows;
    *y1 = min(ny, *y0 + rows);
    return *y0 < ny;
}

/* The work-item's place as row_item gives it (xb0, xb1, y0, y1, g declared), or return past the last block */
#define ROW_ITEM(nx, ny, rows) \
    int xb0, xb1, y0, y1; \
    size_t g; \
    if (!row_item(nx, ny, rows, &xb0, &xb1, &y0, &y1, &g)) return

/* Five vector sums into the partials at slot0.. (the reducing kernels' last step) */
#define ADD_SUMS5(a0, a1, a2, a3, a4) do { \
        const real_t sums_[5] = {lanes_sum(a0), lanes_sum(a1), lanes_sum(a2), lanes_sum(a3), lanes_sum(a4)}; \
        add_partials(partials, pstride, g, slot0, sums_, 5); \
    } while (0)

/* The index in a slab of plane z, row y, x0 */
inline size_t slab_index(const int z, const int y, const int x0, const int ny, const int nx) {
    return ((size_t)z * ny + y) * nx + x0;
}

/* partials[(slot0 + j) * stride + g] += v[j] for j < k (zeroed once per iteration; slabs accumulate) */
inline void add_partials(__global real_t *partials, const int stride, const size_t g, const int slot0,
                         const real_t *v, const int k) {
    for (int j = 0; j < k; j++) partials[(size_t)(slot0 + j) * stride + g] += v[j];
}

/* Forward differences of v at the VW elements i.. = (z*ny + y)*nx + x0.. of a slab (vc: v there),
 * Neumann boundary (zero past the last index): the lateral ones here, the axial one
 * aw (next_plane(...) - vc) by the caller. */
inline void grad_xy(__global const real_t *v, const size_t i, const realv vc, const int cnt, const int y,
                    const int ny, const int nx, realv *gx, realv *gy) {
    /* the row's last element is its own right neighbour (clamped load): gx = 0 there */
    *gx = from_right(vc, v[i + min(VW, cnt - 1)]) - vc;
    *gy = y < ny - 1 ? load_row(v, i + nx, cnt) - vc : (realv)0;
}

/* v's plane z+1 at the elements i.. of plane z of a slab of `planes` planes: from the slab, from
 * v_next (the next slab, when has_next) after its last plane, else vc (no axial difference). */
inline realv next_plane(__global const real_t *v, __global const real_t *v_next, const int has_next,
                        const size_t i, const size_t plane, const int z, const int planes, const int cnt,
                        const realv vc) {
    if (z < planes - 1) return load_row(v, i + plane, cnt);
    if (has_next) return load_row(v_next, i - (size_t)z * plane, cnt);
    return vc;
}

/* The TV density at the VW elements i.. of plane z, row y (xv: x there): |grad x| with forward differences
 * (Neumann), the axial one weighted by aw, isotropic or anisotropic; x_next: the next slab when has_next */
inline realv tv_density(__global const real_t *x, __global const real_t *x_next, const int has_next,
                        const size_t i, const size_t plane, const int z, const int planes, const int cnt,
                        const realv xv, const int y, const int ny, const int nx, const real_t aw, const int iso) {
    const realv xn = next_plane(x, x_next, has_next, i, plane, z, planes, cnt, xv);
    realv gx, gy;
    grad_xy(x, i, xv, cnt, y, ny, nx, &gx, &gy);
    const realv gz = aw * (xn - xv);
    return iso ? sqrt(gx * gx + gy * gy + gz * gz) : fabs(gx) + fabs(gy) + fabs(gz);
}

/* pz of the plane before a slab's first plane at its elements i0.. (0 when has_prev is 0) */
inline realv plane_before(__global const real_t *pz_prev, const int has_prev, const int prev_planes,
                          const size_t plane, const size_t i0, const int cnt) {
    return has_prev ? load_row(pz_prev, (size_t)(prev_planes - 1) * plane + i0, cnt) : (realv)0;
}

/* div p = -grad^T p at the VW elements i.. of plane z, row y of a slab of `planes` planes, p = (px, py,
 * pz) the TV dual: backward differences, p taken as 0 past the last index (the slab's last plane is
 * the last when has_next is 0); pz of the plane before from the slab, or for its first plane from
 * pz_prev (plane_before). Always inlined: PoCL 3.1 kept it an out-of-line call per vector
 * (docs/benchmarks.md, "Access order on CPUs"). */
inline __attribute__((always_inline)) realv div_step(
        __global const real_t *px, __global const real_t *py, __global const real_t *pz,
        __global const real_t *pz_prev, const int has_prev, const int prev_planes, const size_t i,
        const size_t plane, const int x0, const int cnt, const int y, const int z, const int planes,
        const int has_next, const int ny, const int nx, const real_t aw) {
    const realv pxv = load_row(px, i, cnt);
    realv d = lanes_below(pxv, cnt - 1) - from_left(x0 > 0 ? px[i - 1] : (real_t)0, pxv);
    if (y < ny - 1) d += load_row(py, i, cnt);
    if (y > 0) d -= load_row(py, i - nx, cnt);
    const realv pzb = z > 0 ? load_row(pz, i - plane, cnt) : plane_before(pz_prev, has_prev, prev_planes, plane, i, cnt);
    d += aw * ((z == planes - 1 && !has_next ? (realv)0 : load_row(pz, i, cnt)) - pzb);
    return d;
}

/* ---- Complex row vectors: CW = max(VW/2, 1) neighbouring complex values per work-item -------------
 * (the spectral kernels of xstep.cl): stored as 2 CW reals (re, im, re, im, ...), computed on as
 * their real parts and imaginary parts (chalf_t: CW reals each), so that a CPU work-item's
 * arithmetic runs on SIMD vectors. `cnt`: the complex values from p[k] on that are real (>= 1). */
#if VW == 1
#define CW 1
typedef cplx_t cvec_t;
typedef real_t chalf_t;
inline cvec_t cjoin(const chalf_t re, const chalf_t im) { return (cvec_t)(re, im); }
#elif VW == 4
#define CW 2
typedef CAT(REAL, 4) cvec_t;
typedef CAT(REAL, 2) chalf_t;
inline cvec_t cjoin(const chalf_t re, const chalf_t im) { return (cvec_t)(re.s0, im.s0, re.s1, im.s1); }
#else
#define CW 4
typedef CAT(REAL, 8) cvec_t;
typedef CAT(REAL, 4) chalf_t;
inline cvec_t cjoin(const chalf_t re, const chalf_t im) {
    return (cvec_t)(re.s0, im.s0, re.s1, im.s1, re.s2, im.s2, re.s3, im.s3);
}
#endif

inline void cload(__global const cplx_t *p, const size_t k, const size_t cnt, chalf_t *re, chalf_t *im) {
    cvec_t v;
#if CW == 1
    v = p[k];
#else
    if (cnt >= CW) {
        v = CAT(vload, VW)(0, (__global const real_t *)(p + k));
    } else {
        cplx_t t[CW];
        for (int q = 0; q < CW; q++) t[q] = p[k + min((size_t)q, cnt - 1)];
        v = CAT(vload, VW)(0, (const real_t *)t);
    }
#endif
    *re = v.even;
    *im = v.odd;
}

inline void cstore(const chalf_t re, const chalf_t im, __global cplx_t *p, const size_t k, const size_t cnt) {
    const cvec_t v = cjoin(re, im);
#if CW == 1
    p[k] = v;
#else
    if (cnt >= CW) {
        CAT(vstore, VW)(v, 0, (__global real_t *)(p + k));
    } else {
        cplx_t t[CW];
        CAT(vstore, VW)(v, 0, (real_t *)t);
        for (size_t q = 0; q < cnt; q++) p[k + q] = t[q];
    }
#endif
}
