/* cm2cl's own FFT: mixed-radix Stockham autosort, batched, 2D as a row pass and a column pass.
 *
 * Plans and the defines come from cm2cl/device/fft_kernels.py.  Conventions:
 *  - forward transforms use exp(-2 pi i jk / N); an inverse is conj(FFT(conj(z))), so every kernel
 *    only runs forward butterflies and conjugates on load/store where asked;
 *  - twiddles are tables computed in double on the host: tw[m] = exp(-2 pi i m / N), m < N, of the
 *    line length N; a radix-R pass with sub-transform length Ns multiplies input r of butterfly j by
 *    tw[r * (j % Ns) * (N / (Ns R))];
 *  - one Stockham pass reads x[j + r N/R] and writes y[(j / Ns) Ns R + j % Ns + r Ns], so after the
 *    passes (Ns = 1, R0, R0 R1, ...) the result is in natural order without a bit-reversal step;
 *  - the odd radices 3, 5 (explicit) and 7, 11, ... (generic, constants from the twiddle table) run as
 *    one radix per pass; radices 2, 4, 8 and 9 (as 3 x 3) are explicit.
 *
 * Line kernels (the whole line in local memory; one read and one write of global memory):
 *   defines FFT_N (complex line length), FFT_NPASS, FFT_R<p> and FFT_S<p> (radix and Ns of pass p).
 * Pass kernels (lines too long for local memory): define FFT_R (radix); N and Ns are arguments.
 */

/* ---- FFT data: FFT_VEC complex values of neighbouring lines side by side ------------------ */

/* fc_t holds FFT_VEC complex numbers (re, im, re, im, ...) of FFT_VEC neighbouring lines that a
 * work-item transforms together: on CPUs the butterflies then run on SIMD vectors; FFT_VEC = 1
 * (fc_t = cplx_t) everywhere else. */
#ifndef FFT_VEC
#define FFT_VEC 1
#endif
#if FFT_VEC == 1
typedef cplx_t fc_t;
#define FC_WIDTH 2
#define FC_RE(a) ((fc_t)((a).x))
#define FC_IM(a) ((fc_t)((a).y))
#define FC_SWAP(a) (a).yx
#define FC_SIGN ((fc_t)(1, -1))
#elif FFT_VEC == 2
typedef CAT(REAL, 4) fc_t;
#define FC_WIDTH 4
#define FC_RE(a) (a).s0022
#define FC_IM(a) (a).s1133
#define FC_SWAP(a) (a).s1032
#define FC_SIGN ((fc_t)(1, -1, 1, -1))
#elif FFT_VEC == 4
typedef CAT(REAL, 8) fc_t;
#define FC_WIDTH 8
#define FC_RE(a) (a).s00224466
#define FC_IM(a) (a).s11335577
#define FC_SWAP(a) (a).s10325476
#define FC_SIGN ((fc_t)(1, -1, 1, -1, 1, -1, 1, -1))
#elif FFT_VEC == 8
typedef CAT(REAL, 16) fc_t;
#define FC_WIDTH 16
#define FC_RE(a) (a).s0022446688aaccee
#define FC_IM(a) (a).s1133557799bbddff
#define FC_SWAP(a) (a).s1032547698badcfe
#define FC_SIGN ((fc_t)(1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1))
#else
#error "FFT_VEC must be 1, 2, 4 or 8"
#endif

/* the FFT_VEC complex values of a fc_t one by one */
typedef union { fc_t v; cplx_t c[FFT_VEC]; } fc_parts;

inline cplx_t mul_mi(cplx_t a) { return (cplx_t)(a.y, -a.x); }  /* -i a */
inline fc_t vmul_mi(fc_t a) { return FC_SWAP(a) * FC_SIGN; }      /* -i a, each value */
inline fc_t vconj(fc_t a) { return a * FC_SIGN; }
/* conj(h) x, each value (FC_RE, FC_IM: each value's real or imaginary part in both of its places) */
inline fc_t vmulc(fc_t h, fc_t x) { return FC_RE(h) * x + FC_IM(h) * vmul_mi(x); }
/* each value times the complex w: (x c - y s, y c + x s), the operations of cmul */
inline fc_t vmul_tw(fc_t a, cplx_t w) { return a * w.x - vmul_mi(a) * w.y; }

/* ---- butterflies on a private array, forward direction ---------------------------------- */

inline void bf2(fc_t *v) {
    const fc_t a = v[0], b = v[1];
    v[0] = a + b; v[1] = a - b;
}

inline void bf4(fc_t *v) {
    const fc_t t0 = v[0] + v[2], t1 = v[0] - v[2], t2 = v[1] + v[3], t3 = vmul_mi(v[1] - v[3]);
    v[0] = t0 + t2; v[1] = t1 + t3; v[2] = t0 - t2; v[3] = t1 - t3;
}

inline void bf8(fc_t *v) {
    const real_t h = (real_t)0.70710678118654752440084436210484903928;  /* sqrt(1/2) */
    fc_t e[4] = {v[0], v[2], v[4], v[6]}, o[4] = {v[1], v[3], v[5], v[7]};
    bf4(e); bf4(o);
    /* o[k] *= exp(-2 pi i k / 8) */
    o[1] = h * (o[1] + vmul_mi(o[1]));   /* (1 - i) h */
    o[2] = vmul_mi(o[2]);
    o[3] = -h * (o[3] - vmul_mi(o[3]));  /* -(1 + i) h */
    for (int k = 0; k < 4; ++k) { v[k] = e[k] + o[k]; v[k + 4] = e[k] - o[k]; }
}

inline void bf3(fc_t *v) {
    const real_t s = (real_t)0.86602540378443864676372317075293618347;  /* sin(2 pi / 3) */
    const fc_t a = v[1] + v[2], d = v[1] - v[2];
    const fc_t m = v[0] - (real_t)0.5 * a, n = s * vmul_mi(d);
    v[0] = v[0] + a; v[1] = m + n; v[2] = m - n;
}

inline void bf5(fc_t *v) {
    const real_t c1 = (real_t)0.30901699437494742410229341718281905886;   /* cos(2 pi / 5) */
    const real_t c2 = (real_t)-0.80901699437494742410229341718281905886;  /* cos(4 pi / 5) */
    const real_t s1 = (real_t)0.95105651629515357211643933337938214340;   /* sin(2 pi / 5) */
    const real_t s2 = (real_t)0.58778525229247312916870595463907276860;   /* sin(4 pi / 5) */
    const fc_t a1 = v[1] + v[4], b1 = v[1] - v[4], a2 = v[2] + v[3], b2 = v[2] - v[3];
    const fc_t m1 = v[0] + c1 * a1 + c2 * a2, m2 = v[0] + c2 * a1 + c1 * a2;
    const fc_t n1 = vmul_mi(s1 * b1 + s2 * b2), n2 = vmul_mi(s2 * b1 - s1 * b2);
    v[0] = v[0] + a1 + a2;
    v[1] = m1 + n1; v[4] = m1 - n1; v[2] = m2 + n2; v[3] = m2 - n2;
}

/* a exp(-i theta) for c = cos(theta), s = sin(theta): the inner twiddles of bf9 */
inline fc_t vrot(fc_t a, const real_t c, const real_t s) { return vmul_tw(a, (cplx_t)(c, -s)); }

/* Radix 9 as 3 x 3: bf3 on (v[n2], v[n2 + 3], v[n2 + 6]) for n2 = 0..2, the inner twiddles
 * exp(-2 pi i n2 k1 / 9), then bf3 across n2 for each k1; output k1 + 3 k2 (natural order). */
inline void bf9(fc_t *v) {
    const real_t c1 = (real_t)0.76604444311897803520239265055541667394;   /* cos(2 pi / 9) */
    const real_t s1 = (real_t)0.64278760968653932632264340990726343291;   /* sin(2 pi / 9) */
    const real_t c2 = (real_t)0.17364817766693034885171662676931479600;   /* cos(4 pi / 9) */
    const real_t s2 = (real_t)0.98480775301220805936674302458952301367;   /* sin(4 pi / 9) */
    const real_t c4 = (real_t)-0.93969262078590838405410927732473146994;  /* cos(8 pi / 9) */
    const real_t s4 = (real_t)0.34202014332566873304409961468225958076;   /* sin(8 pi / 9) */
    fc_t y[3][3];
    for (int n2 = 0; n2 < 3; ++n2) {
        fc_t t[3] = {v[n2], v[n2 + 3], v[n2 + 6]};
        bf3(t);
        y[n2][0] = t[0]; y[n2][1] = t[1]; y[n2][2] = t[2];
    }
    y[1][1] = vrot(y[1][1], c1, s1); y[1][2] = vrot(y[1][2], c2, s2);
    y[2][1] = vrot(y[2][1], c2, s2); y[2][2] = vrot(y[2][2], c4, s4);
    for (int k1 = 0; k1 < 3; ++k1) {
        fc_t t[3] = {y[0][k1], y[1][k1], y[2][k1]};
        bf3(t);
        v[k1] = t[0]; v[k1 + 3] = t[1]; v[k1 + 6] = t[2];
    }
}

/* Odd radix R (7, 11, ...): X_q = v0 + sum_k cos(2 pi qk/R) a_k - i sum_k sin(2 pi qk/R) b_k with
 * a_k = v_k + v_{R-k}, b_k = v_k - v_{R-k}; exp(-2 pi i m / R) = tw[m * (N / R)] (R divides N). */
#define DEFINE_BF_ODD(R)                                                                        \
inline void bf##R(fc_t *v, __global const cplx_t *tw, const int n) {                          \
    fc_t a[R / 2], b[R / 2], out[R];                                                          \
    fc_t s = v[0];                                                                            \
    for (int k = 1; k <= R / 2; ++k) {                                                          \
        a[k - 1] = v[k] + v[R - k]; b[k - 1] = v[k] - v[R - k]; s += a[k - 1];                  \
    }                                                                                           \
    out[0] = s;                                                                                 \
    for (int q = 1; q <= R / 2; ++q) {                                                          \
        fc_t m = v[0], t = (fc_t)(0);                                                    \
        for (int k = 1; k <= R / 2; ++k) {                                                      \
            const cplx_t w = tw[((q * k) % R) * (n / R)]; /* (cos, -sin) */                     \
            m += w.x * a[k - 1]; t -= w.y * b[k - 1];                                           \
        }                                                                                       \
        out[q] = m + vmul_mi(t); out[R - q] = m - vmul_mi(t);                                     \
    }                                                                                           \
    for (int q = 0; q < R; ++q) v[q] = out[q];                                                  \
}
DEFINE_BF_ODD(7)
DEFINE_BF_ODD(11)
DEFINE_BF_ODD(13)

inline void butterfly(fc_t *v, const int R, __global const cplx_t *tw, const int n) {
    if (R == 2) bf2(v);
    else if (R == 3) bf3(v);
    else if (R == 4) bf4(v);
    else if (R == 5) bf5(v);
    else if (R == 8) bf8(v);
    else if (R == 9) bf9(v);
    else if (R == 7) bf7(v, tw, n);
    else if (R == 11) bf11(v, tw, n);
    else if (R == 13) bf13(v, tw, n);
}

#define MAX_RADIX 13

/* One Stockham pass, butterflies j = j0, j0 + js, ... < n / R, between two lines of an address
 * space (element i of a line at p[i * stride]).  R and ns are compile-time constants in the line
 * kernels, so the divisions fold. */
#define DEFINE_PASS(NAME, SPACE)                                                                \
inline void NAME(SPACE const fc_t *in, SPACE fc_t *out, const int stride, const int n,          \
                 const int R, const int ns, const int j0, const int js,                         \
                 __global const cplx_t *tw) {                                                   \
    const int m = n / R, step = n / (ns * R);                                                   \
    for (int j = j0; j < m; j += js) {                                                          \
        fc_t v[MAX_RADIX];                                                                      \
        const int k = j % ns;                                                                   \
        v[0] = in[j * stride];                                                                  \
        for (int r = 1; r < R; ++r) {                                                           \
            const fc_t a = in[(j + r * m) * stride];                                            \
            v[r] = (ns > 1) ? vmul_tw(a, tw[r * k * step]) : a;                                 \
        }                                                                                       \
        butterfly(v, R, tw, n);                                                                 \
        const int d = (j - k) * R + k;                                                          \
        for (int r = 0; r < R; ++r) out[(d + r * ns) * stride] = v[r];                          \
    }                                                                                           \
}
DEFINE_PASS(pass_local, __local)
DEFINE_PASS(pass_global, __global)

#ifdef FFT_N
/* ---- line kernels: all passes of a line in local memory ---------------------------------- */

#define STEP(P, IN, OUT)                                                                        \
    pass_local(IN, OUT, stride, FFT_N, FFT_R##P, FFT_S##P, j0, js, tw);                         \
    barrier(CLK_LOCAL_MEM_FENCE);

/* All passes on the line at a[0], a[stride], ... (b: scratch of the same shape); returns the
 * buffer holding the transform.  Every work-item of the group calls it. */
inline __local fc_t *fft_line(__local fc_t *a, __local fc_t *b, const int stride,
                                const int j0, const int js, __global const cplx_t *tw) {
#if FFT_NPASS > 0
    STEP(0, a, b)
#endif
#if FFT_NPASS > 1
    STEP(1, b, a)
#endif
#if FFT_NPASS > 2
    STEP(2, a, b)
#endif
#if FFT_NPASS > 3
    STEP(3, b, a)
#endif
#if FFT_NPASS > 4
    STEP(4, a, b)
#endif
#if FFT_NPASS > 5
    STEP(5, b, a)
#endif
#if FFT_NPASS > 6
    STEP(6, a, b)
#endif
#if FFT_NPASS > 7
    STEP(7, b, a)
#endif
#if FFT_NPASS > 8
    STEP(8, a, b)
#endif
#if FFT_NPASS > 9
    STEP(9, b, a)
#endif
#if FFT_NPASS > 10
    STEP(10, a, b)
#endif
#if FFT_NPASS > 11
    STEP(11, b, a)
#endif
#if FFT_NPASS > 12
#error "cm2cl fft: more than 12 passes"
#endif
    return (FFT_NPASS % 2) ? b : a;
}

/* Row kernels' global reads and writes (CPUs, FFT_VEC lines per work-item): a work-item's fc_t
 * holds one position of FFT_VEC lines, while a line's neighbouring values are neighbours in global
 * memory.  So the kernels move FFT_VEC x FFT_VEC blocks: FFT_VEC neighbouring values of each line
 * with one vector load or store, turned around in registers by fc_transpose (m[q]'s value t <->
 * m[t]'s value q), instead of FFT_VEC single-value loads or stores per position (docs/benchmarks.md,
 * "FFT row kernels").  Positions past the last whole block, and work-items with fewer than FFT_VEC lines, take
 * one value at a time. */
/* m[t] <- value t of each line q (m[q] held the values of line q): three, two or one stage of
 * exchanging blocks of 1, 2, 4 complex values between rows r and r + B (swizzles, which compile to
 * vector shuffles; element-wise copies through a union compiled to single-value moves on PoCL). */
#if FFT_VEC == 8
#define FC_LO1(x, y) (fc_t)((x).s01, (y).s01, (x).s45, (y).s45, (x).s89, (y).s89, (x).scd, (y).scd)
#define FC_HI1(x, y) (fc_t)((x).s23, (y).s23, (x).s67, (y).s67, (x).sab, (y).sab, (x).sef, (y).sef)
#define FC_LO2(x, y) (fc_t)((x).s0123, (y).s0123, (x).s89ab, (y).s89ab)
#define FC_HI2(x, y) (fc_t)((x).s4567, (y).s4567, (x).scdef, (y).scdef)
#elif FFT_VEC == 4
#define FC_LO1(x, y) (fc_t)((x).s01, (y).s01, (x).s45, (y).s45)
#define FC_HI1(x, y) (fc_t)((x).s23, (y).s23, (x).s67, (y).s67)
#endif
#define FC_LOH(x, y) (fc_t)((x).lo, (y).lo)
#define FC_HIH(x, y) (fc_t)((x).hi, (y).hi)
#define FC_STAGE(B, LO, HI)                                                                     \
    for (int r = 0; r < FFT_VEC; ++r)                                                           \
        if ((r / B) % 2 == 0) { const fc_t x = m[r], y = m[r + B]; m[r] = LO(x, y); m[r + B] = HI(x, y); }
inline void fc_transpose(fc_t *m) {
#if FFT_VEC == 8
    FC_STAGE(1, FC_LO1, FC_HI1) FC_STAGE(2, FC_LO2, FC_HI2) FC_STAGE(4, FC_LOH, FC_HIH)
#elif FFT_VEC == 4
    FC_STAGE(1, FC_LO1, FC_HI1) FC_STAGE(2, FC_LOH, FC_HIH)
#elif FFT_VEC == 2
    FC_STAGE(1, FC_LOH, FC_HIH)
#endif
}
#define FC_LOAD(p) CAT(vload, FC_WIDTH)(0, (__global const real_t *)(p))
#define FC_STORE(v, p) CAT(vstore, FC_WIDTH)((v), 0, (__global real_t *)(p))

/* Rows, real -> spectrum.  src: `lines` lines of `px` reals (row pitch px); dst: lines of px/2 + 1
 * complex.  FFT_HALF: px = 2 FFT_N even, transformed as FFT_N complex points z_i = x_2i + i x_2i+1
 * then untangled with twr[k] = exp(-pi i k / FFT_N), k <= FFT_N; else px = FFT_N (odd), the line is
 * widened to complex.  A work-item transforms FFT_VEC neighbouring lines together (fc_t), FFT_C
 * such work-items per group in local dimension 0; local dimension 1 walks the butterflies (GPUs:
 * FFT_VEC = FFT_C = 1 and a wide dimension 1). */
#define ROW_SETUP                                                                               \
    __local fc_t a_[FFT_N * FFT_C], b_[FFT_N * FFT_C];                                          \
    const int c = get_local_id(0), stride = FFT_C;                                              \
    const int j0 = get_local_id(1), js = get_local_size(1);                                     \
    const size_t first = ((size_t)get_group_id(0) * FFT_C + c) * FFT_VEC;                       \
    size_t line[FFT_VEC];                                                                       \
    int ok[FFT_VEC];                                                                            \
    for (int q = 0; q < FFT_VEC; ++q) {                                                         \
        ok[q] = first + q < (size_t)lines;                                                      \
        line[q] = ok[q] ? first + q : 0;                                                        \
    }                                                                                           \
    __local fc_t *a = a_ + c, *b = b_ + c;                                                      \
    fc_parts u;                                                                                 \
    /* blocks of FFT_VEC values of every line (all lines present) go through fc_transpose */    \
    const int blocked = first + FFT_VEC <= (size_t)lines;

#ifdef FFT_HALF
/* X_k of the real line from the half-length transform z (FFT_HALF): X_k = (e - i w^k o) / 2,
 * e = Z_k + conj Z_{N-k}, o = Z_k - conj Z_{N-k}, w^k = twr[k] */
inline fc_t untangled(__local const fc_t *z, const int stride, const int k, __global const cplx_t *twr) {
    const fc_t zk = z[(k % FFT_N) * stride], zc = vconj(z[((FFT_N - k) % FFT_N) * stride]);
    return (real_t)0.5 * ((zk + zc) + vmul_mi(vmul_tw(zk - zc, twr[k])));
}
/* conj(2 Z_k) for the inverse from the spectrum's X_k and X_{N-k} (FFT_HALF): Z_k = (e + i o) / 2,
 * e = X_k + conj X_{N-k}, o = conj(w^k) (X_k - conj X_{N-k}); the imaginary parts of X_0 and X_N,
 * which a Hermitian line cannot have, are ignored (as numpy's irfft does). */
inline fc_t tangled(fc_t xk, fc_t xnk, const int k, __global const cplx_t *twr) {
    const fc_t re_only = (FC_SIGN + (fc_t)(1)) * (real_t)0.5;   /* (1, 0, 1, 0, ...) */
    const fc_t x0 = (k == 0) ? xk * re_only : xk, xn = vconj((k == 0) ? xnk * re_only : xnk);
    const cplx_t t = twr[k];
    const fc_t o = vmul_tw(x0 - xn, (cplx_t)(t.x, -t.y));
    return vconj((x0 + xn) - vmul_mi(o));
}
#endif

__kernel void rows_r2c(__global cplx_t *dst, __global const real_t *src,
                       __global const cplx_t *tw, __global const cplx_t *twr, const int lines) {
    ROW_SETUP
#ifdef FFT_HALF
    const int px = 2 * FFT_N, w = FFT_N + 1;
    const int nb = blocked ? FFT_N / FFT_VEC : 0;
    for (int ib = j0; ib < nb; ib += js) {
        fc_t m[FFT_VEC];
        for (int q = 0; q < FFT_VEC; ++q) m[q] = FC_LOAD(src + line[q] * px + 2 * ib * FFT_VEC);
        fc_transpose(m);
        for (int t = 0; t < FFT_VEC; ++t) a[(ib * FFT_VEC + t) * stride] = m[t];
    }
    for (int i = nb * FFT_VEC + j0; i < FFT_N; i += js) {
        for (int q = 0; q < FFT_VEC; ++q) u.c[q] = vload2(i, src + line[q] * px);
        a[i * stride] = u.v;
    }
#else
    const int px = FFT_N, w = FFT_N / 2 + 1;
    for (int i = j0; i < FFT_N; i += js) {
        for (int q = 0; q < FFT_VEC; ++q) u.c[q] = (cplx_t)(src[line[q] * px + i], 0);
        a[i * stride] = u.v;
    }
#endif
    barrier(CLK_LOCAL_MEM_FENCE);
    __local const fc_t *z = fft_line(a, b, stride, j0, js, tw);
#ifdef FFT_HALF
    const int nk = blocked ? (FFT_N + 1) / FFT_VEC : 0;
    for (int kb = j0; kb < nk; kb += js) {
        fc_t m[FFT_VEC];
        for (int t = 0; t < FFT_VEC; ++t) m[t] = untangled(z, stride, kb * FFT_VEC + t, twr);
        fc_transpose(m);
        for (int q = 0; q < FFT_VEC; ++q) FC_STORE(m[q], dst + line[q] * w + kb * FFT_VEC);
    }
    for (int k = nk * FFT_VEC + j0; k <= FFT_N; k += js) {
        u.v = untangled(z, stride, k, twr);
        for (int q = 0; q < FFT_VEC; ++q) if (ok[q]) dst[line[q] * w + k] = u.c[q];
    }
#else
    for (int k = j0; k < w; k += js) {
        u.v = z[k * stride];
        for (int q = 0; q < FFT_VEC; ++q) if (ok[q]) dst[line[q] * w + k] = u.c[q];
    }
#endif
}

/* Rows, spectrum -> real, scaled by `scale`: the inverse of rows_r2c (src: lines of px/2 + 1
 * complex, Hermitian; dst: lines of px reals).  The imaginary parts that a Hermitian line cannot
 * have (k = 0, and k = px/2 for even px) are ignored, as numpy's irfft does. */
__kernel void rows_c2r(__global real_t *dst, __global const cplx_t *src,
                       __global const cplx_t *tw, __global const cplx_t *twr, const real_t scale,
                       const int lines) {
    ROW_SETUP
    const fc_t re_only = (FC_SIGN + (fc_t)(1)) * (real_t)0.5;   /* (1, 0, 1, 0, ...) */
#ifdef FFT_HALF
    const int px = 2 * FFT_N, w = FFT_N + 1;
    const int nb = blocked ? FFT_N / FFT_VEC : 0;
    /* X_0 .. X_{N-1} into b (free until the passes), read front to back only: reading X_{N-k} next to
     * X_k from global memory made a second stream running backwards, where this CPU's loads stalled
     * (perf: 20% of rows_c2r's samples on that one load); X_N, which only k = 0 needs, in xn */
    for (int kb = j0; kb < nb; kb += js) {
        fc_t m[FFT_VEC];
        for (int q = 0; q < FFT_VEC; ++q) m[q] = FC_LOAD(src + line[q] * w + kb * FFT_VEC);
        fc_transpose(m);
        for (int t = 0; t < FFT_VEC; ++t) b[(kb * FFT_VEC + t) * stride] = m[t];
    }
    for (int k = nb * FFT_VEC + j0; k < FFT_N; k += js) {
        for (int q = 0; q < FFT_VEC; ++q) u.c[q] = src[line[q] * w + k];
        b[k * stride] = u.v;
    }
    fc_parts xn;
    for (int q = 0; q < FFT_VEC; ++q) xn.c[q] = src[line[q] * w + FFT_N];
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int k = j0; k < FFT_N; k += js)
        a[k * stride] = tangled(b[k * stride], k == 0 ? xn.v : b[(FFT_N - k) * stride], k, twr);
#else
    const int px = FFT_N, w = FFT_N / 2 + 1;
    for (int k = j0; k < FFT_N; k += js) {
        for (int q = 0; q < FFT_VEC; ++q) u.c[q] = src[line[q] * w + ((k < w) ? k : FFT_N - k)];
        const fc_t v = (k == 0) ? u.v * re_only : u.v;
        a[k * stride] = (k < w) ? vconj(v) : v;   /* conj of the Hermitian extension */
    }
#endif
    barrier(CLK_LOCAL_MEM_FENCE);
    __local const fc_t *z = fft_line(a, b, stride, j0, js, tw);
#ifdef FFT_HALF
    const real_t h = (real_t)0.5 * scale;   /* Z_k carried a factor 2 */
    for (int ib = j0; ib < nb; ib += js) {
        fc_t m[FFT_VEC];
        for (int t = 0; t < FFT_VEC; ++t) m[t] = h * vconj(z[(ib * FFT_VEC + t) * stride]);
        fc_transpose(m);
        for (int q = 0; q < FFT_VEC; ++q) FC_STORE(m[q], dst + line[q] * px + 2 * ib * FFT_VEC);
    }
    for (int i = nb * FFT_VEC + j0; i < FFT_N; i += js) {
        u.v = h * vconj(z[i * stride]);
        for (int q = 0; q < FFT_VEC; ++q) if (ok[q]) vstore2(u.c[q], i, dst + line[q] * px);
    }
#else
    for (int i = j0; i < FFT_N; i += js) {
        u.v = scale * z[i * stride];
        for (int q = 0; q < FFT_VEC; ++q) if (ok[q]) dst[line[q] * px + i] = u.c[q].x;
    }
#endif
}

/* Columns, in place: the (ny = FFT_N, w) complex planes of `data`.  A work-item transforms
 * FFT_VEC neighbouring columns together, FFT_C such work-items per group in local dimension 0
 * (neighbouring work-items on neighbouring columns: coalesced global reads and writes); local
 * dimension 1 walks the butterflies.  conj_io != 0 conjugates on load and store (the inverse,
 * unnormalised).  With FFT_XSTEP (the inverse only) the data are the x step's T_i and the kernel
 * applies that step's last stage to them as it loads them (xstep_solve in xstep.cl). */
__kernel void cols(__global cplx_t *data, const int w, const int conj_io,
                   __global const cplx_t *tw
#ifdef FFT_XSTEP
                   , __global const cplx_t *hs, __global const cplx_t *hr, __global const cplx_t *hx,
                   const real_t mu_v, const real_t inv_c
#endif
                   ) {
    __local fc_t a_[FFT_N * FFT_C], b_[FFT_N * FFT_C];
    const int c = get_local_id(0), col = (get_group_id(0) * FFT_C + c) * FFT_VEC;
    const int j0 = get_local_id(1), js = get_local_size(1);
    const int full = col + FFT_VEC <= w;
    __global cplx_t *p = data + (size_t)get_group_id(2) * FFT_N * w + min(col, w - 1);
    __local fc_t *a = a_ + c, *b = b_ + c;
    const fc_t sign = conj_io ? FC_SIGN : (fc_t)(1);
    fc_parts u;
    for (int i = j0; i < FFT_N; i += js) {
        __global cplx_t *pi = p + (size_t)i * w;
        if (full) {
            u.v = FC_LOAD(pi);
        } else {
            for (int q = 0; q < FFT_VEC; ++q) u.c[q] = (col + q < w) ? pi[q] : (cplx_t)(0, 0);
        }
#ifdef FFT_XSTEP
        {   /* the x step's last stage on the way in (xstep_solve in xstep.cl, fused):
               X_i = (B_i - mu_v conj(H_i) HX) * inv_c, B_i = conj(H_i) R + T_i; H_i: hs at T's place,
               R and HX: the planes hr and hx (py, w) */
            const size_t at = (size_t)i * w + min(col, w - 1);
            __global const cplx_t *hi = hs + (pi - data), *ri = hr + at, *xi = hx + at;
            if (full) {
                const fc_t h = FC_LOAD(hi), r = FC_LOAD(ri), x = FC_LOAD(xi);
                u.v = ((vmulc(h, r) + u.v) - mu_v * vmulc(h, x)) * inv_c;
            } else {
                for (int q = 0; q < FFT_VEC; ++q)
                    if (col + q < w) u.c[q] = ((cmulc(hi[q], ri[q]) + u.c[q]) - mu_v * cmulc(hi[q], xi[q])) * inv_c;
            }
        }
#endif
        a[i * FFT_C] = u.v * sign;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    __local const fc_t *z = fft_line(a, b, FFT_C, j0, js, tw);
    if (col >= w) return;
    for (int i = j0; i < FFT_N; i += js) {
        __global cplx_t *pi = p + (size_t)i * w;
        u.v = z[i * FFT_C] * sign;
        if (full) {
            FC_STORE(u.v, pi);
        } else {
            for (int q = 0; q < FFT_VEC; ++q) if (col + q < w) pi[q] = u.c[q];
        }
    }
}
#endif /* FFT_N */

#ifdef FFT_R
/* ---- pass kernels: one radix-FFT_R pass through global memory ------------------------------ */

/* Lines of n contiguous complex values (line l at l * n), in -> out.  Global size (n / R, lines). */
__kernel void pass_rows(__global cplx_t *out, __global const cplx_t *in, const int n, const int ns,
                        __global const cplx_t *tw) {
    const size_t base = (size_t)get_global_id(1) * n;
    const int j = get_global_id(0);
    if (j < n / FFT_R) pass_global(in + base, out + base, 1, n, FFT_R, ns, j, n, tw);
}

/* Columns of (n, w) planes: element i of column c of plane q at (q n + i) w + c, in -> out.
 * Global size (w, n / R, planes): neighbouring work-items on neighbouring columns.  conj_in and
 * conj_out conjugate the values read and written (the first and last pass of an inverse). */
__kernel void pass_cols(__global cplx_t *out, __global const cplx_t *in, const int n, const int w,
                        const int ns, const int conj_in, const int conj_out,
                        __global const cplx_t *tw) {
    const int c = get_global_id(0), j = get_global_id(1);
    if (c >= w || j >= n / FFT_R) return;
    const size_t base = (size_t)get_global_id(2) * n * w + c;
    const int m = n / FFT_R, step = n / (ns * FFT_R), k = j % ns;
    cplx_t v[FFT_R];
    for (int r = 0; r < FFT_R; ++r) {
        cplx_t a = in[base + (size_t)(j + r * m) * w];
        if (conj_in) a.y = -a.y;
        v[r] = (r > 0 && ns > 1) ? cmul(a, tw[r * k * step]) : a;
    }
    butterfly(v, FFT_R, tw, n);
    const int d = (j - k) * FFT_R + k;
    for (int r = 0; r < FFT_R; ++r) {
        cplx_t a = v[r];
        if (conj_out) a.y = -a.y;
        out[base + (size_t)(d + r * ns) * w] = a;
    }
}
#endif /* FFT_R */

/* ---- packing for the pass path: real lines <-> complex lines in global memory ------------- */

/* z (lines of n complex) <- real lines of px: half (px = 2n): z_i = x_2i + i x_2i+1; else
 * (px = n) z_i = x_i.  Global size (n, lines). */
__kernel void pack_real(__global cplx_t *z, __global const real_t *src, const int n, const int even) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t line = get_global_id(1);
    if (even) z[line * n + i] = vload2(i, src + line * 2 * n);
    else z[line * n + i] = (cplx_t)(src[line * n + i], 0);
}

/* Spectrum lines of w complex <- transformed z lines of n complex (see rows_r2c).
 * Global size (w, lines). */
__kernel void untangle(__global cplx_t *dst, __global const cplx_t *z, const int n, const int even,
                       __global const cplx_t *twr) {
    const int k = get_global_id(0), w = even ? n + 1 : n / 2 + 1;
    if (k >= w) return;
    const size_t line = get_global_id(1);
    __global const cplx_t *zl = z + line * n;
    if (!even) { dst[line * w + k] = zl[k]; return; }
    const cplx_t zk = zl[k % n], zc = zl[(n - k) % n];
    const cplx_t e = (cplx_t)(zk.x + zc.x, zk.y - zc.y), o = (cplx_t)(zk.x - zc.x, zk.y + zc.y);
    dst[line * w + k] = (real_t)0.5 * (e + mul_mi(cmul(twr[k], o)));
}

/* Conjugated z lines (n complex) to inverse-transform <- spectrum lines of w complex (see
 * rows_c2r).  Global size (n, lines). */
__kernel void tangle(__global cplx_t *z, __global const cplx_t *src, const int n, const int even,
                     __global const cplx_t *twr) {
    const int k = get_global_id(0);
    if (k >= n) return;
    const size_t line = get_global_id(1);
    if (even) {
        __global const cplx_t *X = src + line * (n + 1);
        const cplx_t xk = X[k], xc = X[n - k];
        const cplx_t x0 = (k == 0) ? (cplx_t)(xk.x, 0) : xk, xn = (k == 0) ? (cplx_t)(xc.x, 0) : xc;
        const cplx_t e = (cplx_t)(x0.x + xn.x, x0.y - xn.y), d = (cplx_t)(x0.x - xn.x, x0.y + xn.y);
        const cplx_t o = cmulc(twr[k], d);
        z[line * n + k] = (cplx_t)(e.x - o.y, -(e.y + o.x));
    } else {
        const int w = n / 2 + 1;
        __global const cplx_t *X = src + line * w;
        cplx_t v = (k < w) ? X[k] : X[n - k];
        if (k == 0) v.y = 0;
        z[line * n + k] = (k < w) ? (cplx_t)(v.x, -v.y) : v;
    }
}

/* Real lines of px <- conjugated inverse-transformed z lines, times `scale` (see rows_c2r).
 * Global size (n, lines). */
__kernel void unpack_real(__global real_t *dst, __global const cplx_t *z, const int n, const int even,
                          const real_t scale) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t line = get_global_id(1);
    const cplx_t v = z[line * n + i];
    if (even) vstore2((REAL2)((real_t)0.5 * scale * v.x, (real_t)-0.5 * scale * v.y), i, dst + line * 2 * n);
    else dst[line * n + i] = scale * v.x;
}
