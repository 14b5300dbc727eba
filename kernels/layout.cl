/* Moving data between the layouts of cm2cl: real <-> complex, sensor grid <-> padded grid.
 * All arrays are C-contiguous; a "plane" of the padded grid is py x px reals. */

/* dst[i] = (src[i], 0) for i < n. */
__kernel void real_to_complex(__global cplx_t *dst, __global const real_t *src, const ulong n) {
    const size_t i = get_global_id(0);
    if (i < n) dst[i] = (cplx_t)(src[i], (real_t)0);
}

/* dst[i] = Re(src[i]) for i < n. */
__kernel void complex_real_part(__global real_t *dst, __global const cplx_t *src, const ulong n) {
    const size_t i = get_global_id(0);
    if (i < n) dst[i] = src[i].x;
}

/* Crop C: sensor (my, mx) <- padded (py, px) window at (oy, ox), for `planes` planes.
 * Global size (mx, my, planes). */
__kernel void crop(__global real_t *dst, __global const real_t *src,
                   const int my, const int mx, const int py, const int px,
                   const int oy, const int ox) {
    const int c = get_global_id(0), r = get_global_id(1), k = get_global_id(2);
    if (c >= mx || r >= my) return;
    dst[((size_t)k * my + r) * mx + c] = src[((size_t)k * py + (r + oy)) * px + (c + ox)];
}

/* Adjoint of the crop, C^T: zero padded (py, px) grid with the sensor window filled.
 * Global size (px, py, planes). */
__kernel void embed(__global real_t *dst, __global const real_t *src,
                    const int my, const int mx, const int py, const int px,
                    const int oy, const int ox) {
    const int c = get_global_id(0), r = get_global_id(1), k = get_global_id(2);
    if (c >= px || r >= py) return;
    const int sr = r - oy, sc = c - ox;
    real_t v = (real_t)0;
    if (sr >= 0 && sr < my && sc >= 0 && sc < mx) v = src[((size_t)k * my + sr) * mx + sc];
    dst[((size_t)k * py + r) * px + c] = v;
}

/* dst[i] = src[i]: a plain copy, used to measure the device's memory bandwidth. */
__kernel void copy_real(__global real_t *dst, __global const real_t *src, const ulong n) {
    const size_t i = get_global_id(0);
    if (i < n) dst[i] = src[i];
}

/* a[i] *= c for i < n reals, in place (a complex array is 2n reals: both parts scaled). */
__kernel void scale_real(__global real_t *a, const real_t c, const ulong n) {
    const size_t i = get_global_id(0);
    if (i < n) a[i] = c * a[i];
}
