/* clsplat/kernels/common.h — shared maths, types and the named constants of every stage.
 *
 * The Python side prepends this header to each stage's source (it never relies on the
 * compiler's include path, so that the program cache key covers the header's text too).
 * clsplat/constants.py parses the CLS_* defaults below: they are named here, once.
 *
 * Compile-time parameters (all optional unless stated; the builder passes them with -D):
 *   REAL_DOUBLE      1 to compute in double (needs cl_khr_fp64), else float
 *   CHANNELS         feature channels composited per Gaussian (colour and maybe depth)
 *   SH_DEGREE, SH_COEFFS   degree evaluated, and coefficients stored per Gaussian
 *   TILE             tile side in pixels
 *   PIX              pixels per work-item along a tile row in compositing (1 = GPU layout)
 *   ALPHA_MIN, ALPHA_MAX, T_MIN, RADIUS_SIGMA, OPACITY_AWARE_RADIUS   accuracy knobs
 *   (OPACITY_AWARE_RADIUS: gsplat's rule, extent min(RADIUS_SIGMA, sqrt(2 ln(o / ALPHA_MIN))))
 */
#ifndef CLSPLAT_COMMON_H
#define CLSPLAT_COMMON_H

/* ---- named defaults (parsed by clsplat/constants.py) -------------------------------- */
#define CLS_DEFAULT_ALPHA_MIN (1.0 / 255.0)
/* gsplat's clamp; the original 3DGS value 0.99 is RenderConfig(alpha_max=0.99). */
#define CLS_DEFAULT_ALPHA_MAX 0.999
#define CLS_DEFAULT_T_MIN 1e-4
#define CLS_DEFAULT_RADIUS_SIGMA 3.33
#define CLS_DEFAULT_EPS2D 0.3
/* The Jacobian is evaluated at a mean clamped to the view frustum widened by this fraction of
 * tan(fov/2): far off-axis means would otherwise give an exploding, badly conditioned J. */
#define CLS_FRUSTUM_MARGIN 0.3
#define CLS_PIXEL_CENTRE 0.5

#ifndef ALPHA_MIN
#define ALPHA_MIN CLS_DEFAULT_ALPHA_MIN
#endif
#ifndef ALPHA_MAX
#define ALPHA_MAX CLS_DEFAULT_ALPHA_MAX
#endif
#ifndef T_MIN
#define T_MIN CLS_DEFAULT_T_MIN
#endif
#ifndef RADIUS_SIGMA
#define RADIUS_SIGMA CLS_DEFAULT_RADIUS_SIGMA
#endif
#ifndef OPACITY_AWARE_RADIUS
#define OPACITY_AWARE_RADIUS 0
#endif
#ifndef PIX
#define PIX 1
#endif

/* ---- scalar type ------------------------------------------------------------------- */
#if REAL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define REAL double
#define REAL2 double2
#define REAL3 double3
#define REAL4 double4
/* A vector comparison on doubles yields longN, so masks follow the scalar width. */
#define MASK_SCALAR long
#else
#define REAL float
#define REAL2 float2
#define REAL3 float3
#define REAL4 float4
#define MASK_SCALAR int
#endif

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

/* ---- PIX-wide vectors for compositing: PIX pixels of one tile row per work-item ------- */
/* PoCL does not vectorise work-item loops that call exp, so the CPU layout spells the
 * vectors out; PIX=1 is the one-pixel-per-work-item layout that suits GPUs. */
#if PIX == 1
#define VREAL REAL
#define VMASK MASK_SCALAR
#define VRAMP ((REAL)0)
#define VANY(m) (m)
#define VALL(m) (m)
#define VSTORE(v, p) ((p)[0] = (v))
#define VSUM(v) (v)
#else
#define VREAL CAT(REAL, PIX)
#define VMASK CAT(MASK_SCALAR, PIX)
#define VANY(m) any(m)
#define VSTORE(v, p) CAT(vstore, PIX)(v, 0, p)
/* Horizontal sum in a fixed pairwise order, so gradients are bitwise reproducible. */
#define VSUM2(v) ((v).s0 + (v).s1)
#define VSUM4(v) VSUM2((v).lo + (v).hi)
#define VSUM8(v) VSUM4((v).lo + (v).hi)
#define VSUM16(v) VSUM8((v).lo + (v).hi)
#define VSUM(v) CAT(VSUM, PIX)(v)
#define VALL(m) all(m)
#if PIX == 2
#define VRAMP ((VREAL)(0, 1))
#elif PIX == 4
#define VRAMP ((VREAL)(0, 1, 2, 3))
#elif PIX == 8
#define VRAMP ((VREAL)(0, 1, 2, 3, 4, 5, 6, 7))
#elif PIX == 16
#define VRAMP ((VREAL)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#else
#error "PIX must be 1, 2, 4, 8 or 16"
#endif
#endif
/* Comparisons give 1 for a true scalar but -1 for a true vector lane; masks therefore only
 * ever pass through &&, ||, ! and ?:, which treat both the same way. */

/* ---- compositing maths: library builtins or inline equivalents (CLS_INLINE_MATH) -------- */
/* PoCL's CPU device links builtins (exp, fmin, fabs, any, ...) from a kernel library built for
 * the CPU variant it detects (avx512 on this host), while the kernel itself is compiled for
 * the CPU name LLVM reports (znver3 under LLVM 14 on Zen 4). LLVM does not inline a callee
 * whose target features are not a subset of the caller's, so every builtin in a hot loop is
 * an out-of-line call, and the call spills every vector register (all are caller-saved).
 * With CLS_INLINE_MATH (= CLS_POCL_CPU) the tuned compositing kernels use the inline forms
 * below instead; they give
 * the same values: selects for fmin/fmax/fabs (equal for every non-NaN input), lane
 * reductions for any/all, and for float exp the algorithm of the library's exp (SLEEF's
 * expf_u10: same constants, same operation order, fused where the library fuses). */
/* CLS_POCL_CPU: 1 (set by the host for the tuned compositing kernels) on PoCL's CPU device,
 * whose kernel compiler is the host's clang: there the kernels use the inline maths below
 * and clang builtins (count of trailing/leading zeros, prefetch) that other implementations
 * need not know (Oclgrind rejects llvm.cttz, and llvm.fabs on vectors, which clang makes of
 * the inline fabs); elsewhere the OpenCL builtins, which their compilers inline. */
#ifndef CLS_POCL_CPU
#define CLS_POCL_CPU 0
#endif
#define CLS_INLINE_MATH CLS_POCL_CPU
#ifndef CLS_PREFETCH /* (a -D for side-by-side timings) */
#define CLS_PREFETCH CLS_POCL_CPU
#endif
#if CLS_POCL_CPU
#define CLS_CTZ(m) __builtin_ctz(m)        /* m != 0 */
#define CLS_TOP_BIT(m) (31 - __builtin_clz(m))
#else
#define CLS_CTZ(m) (31 - (int)clz((m) & (0u - (m))))
#define CLS_TOP_BIT(m) (31 - (int)clz(m))
#endif
/* op over the lanes of a vector, pairwise (no builtin) */
#define CLS_LANES2(m, op) ((m).s0 op (m).s1)
#define CLS_LANES4(m, op) CLS_LANES2((m).lo op (m).hi, op)
#define CLS_LANES8(m, op) CLS_LANES4((m).lo op (m).hi, op)
#define CLS_LANES16(m, op) CLS_LANES8((m).lo op (m).hi, op)
#if CLS_INLINE_MATH
/* fmin/fmax for a non-NaN a (a NaN b gives a, as the builtins do) */
#define CLS_FMIN(a, b) ((b) < (a) ? (b) : (a))
#define CLS_FMAX(a, b) ((b) > (a) ? (b) : (a))
#define CLS_FABS(a) ((a) > 0 ? (a) : 0 - (a))   /* 0 - (-0) = +0, as fabs(-0) */
#if PIX == 1
#define CLS_VANY(m) (m)
#define CLS_VALL(m) (m)
#else
/* A true vector lane is -1: OR (AND) the lanes pairwise and test the sign. */
inline int cls_vany(VMASK m) { return CAT(CLS_LANES, PIX)(m, |) < 0; }
inline int cls_vall(VMASK m) { return CAT(CLS_LANES, PIX)(m, &) < 0; }
#define CLS_VANY(m) cls_vany(m)
#define CLS_VALL(m) cls_vall(m)
#endif
/* CLS_INLINE_EXP (default on): the host turns it off where the inline exp does not reproduce
 * this device's library exp bit for bit (clsplat.stages.inline_exp_exact runs exp_probe in
 * composite.cl once per device): another PoCL build or CPU variant may link another exp. */
#ifndef CLS_INLINE_EXP
#define CLS_INLINE_EXP 1
#endif
#if REAL_DOUBLE || PIX == 1 || !CLS_INLINE_EXP
/* float64 keeps the library's exp, and so does the scalar layout: the library's scalar expf
 * is SLEEF's other variant (no fused multiply-adds, rint by adding 0.5 and truncating). */
#define CLS_VEXP(x) exp(x)
#else
#define VINT CAT(int, PIX)
#define VUINT CAT(uint, PIX)
#define CLS_TO_VREAL(k) __builtin_convertvector(k, VREAL)
#define CLS_AS_VINT CAT(as_, VINT)
#define CLS_AS_VUINT CAT(as_, VUINT)
#define CLS_AS_VREAL CAT(as_, VREAL)
/* SLEEF's expf_u10: x = k ln2 + s, exp(s) by a degree-7 polynomial, times 2^k in two steps.
 * k = rint(x / ln2) comes from adding 1.5 * 2^23 (exact for |x / ln2| < 2^22, the only range
 * where the result is not replaced by 0 or inf at the end), so it needs no conversion builtin
 * and survives -cl-fast-relaxed-math. Each a * b + c below is one expression, so clang fuses
 * it (fp-contract on) as the library's code does. */
inline VREAL cls_vexp(VREAL x) {
    const VREAL t = x * 1.44269502162933349609375f;                 /* 1 / ln 2 */
    const VINT k = CLS_AS_VINT(t + 12582912.0f) - 0x4B400000;       /* rint(t) */
    const VREAL kf = CLS_TO_VREAL(k);
    VREAL s = kf * -0.693145751953125f + x;                         /* ln 2, high part */
    s = kf * -1.428606765330187045e-06f + s;                        /* ln 2, low part */
    VREAL u = (VREAL)0.000198527617612853646278381f;
    u = u * s + 0.00139304355252534151077271f;
    u = u * s + 0.00833336077630519866943359f;
    u = u * s + 0.0416664853692054748535156f;
    u = u * s + 0.166666671633720397949219f;
    u = u * s + 0.5f;
    const VREAL s2 = s * s;
    u = u * s2 + s;
    u = u + 1.0f;
    const VINT q = k >> 1;                                          /* 2^k = 2^q 2^(k-q) */
    u = u * CLS_AS_VREAL((CLS_AS_VUINT(q) << 23) + 0x3f800000u);
    u = u * CLS_AS_VREAL((CLS_AS_VUINT(k - q) << 23) + 0x3f800000u);
    u = x < -104.0f ? (VREAL)0.0f : u;
    return x > 100.0f ? (VREAL)INFINITY : u;
}
#define CLS_VEXP(x) cls_vexp(x)
#endif
#else
#define CLS_FMIN(a, b) fmin(a, b)
#define CLS_FMAX(a, b) fmax(a, b)
#define CLS_FABS(a) fabs(a)
#define CLS_VANY(m) VANY(m)
#define CLS_VALL(m) VALL(m)
#define CLS_VEXP(x) exp(x)
#endif
/* Per-pair maths of the projection, where the same out-of-line builtins cost a third of the
 * kernel on PoCL's CPU device: sqrt, ceil and floor as clang's builtins (one instruction each;
 * ceil and floor are exact, and sqrt is correctly rounded, as the library's is), min and max
 * as CLS_FMIN/CLS_FMAX above, with the argument that cannot be NaN first. */
#if CLS_INLINE_MATH && REAL_DOUBLE
#define CLS_SQRT(x) __builtin_sqrt(x)
#define CLS_CEIL(x) __builtin_ceil(x)
#define CLS_FLOOR(x) __builtin_floor(x)
#elif CLS_INLINE_MATH
#define CLS_SQRT(x) __builtin_sqrtf(x)
#define CLS_CEIL(x) __builtin_ceilf(x)
#define CLS_FLOOR(x) __builtin_floorf(x)
#else
#define CLS_SQRT(x) sqrt(x)
#define CLS_CEIL(x) ceil(x)
#define CLS_FLOOR(x) floor(x)
#endif

/* ---- small linear algebra (row-major 3x3 as REAL[9]) -------------------------------- */
inline void quat_to_rotmat(REAL4 q, REAL *R) {
    /* Unnormalised input is allowed; a zero quaternion is rejected on the host. */
    REAL inv = rsqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    REAL w = q.x * inv, x = q.y * inv, y = q.z * inv, z = q.w * inv;
    R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z);     R[2] = 2 * (x * z + w * y);
    R[3] = 2 * (x * y + w * z);     R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
    R[6] = 2 * (x * z - w * y);     R[7] = 2 * (y * z + w * x);     R[8] = 1 - 2 * (x * x + y * y);
}

/* Depth ordering key: positive float bits sort like the floats. The low word is the
 * (camera, Gaussian) index, so equal depths are ordered by id and the sort is total. */
inline ulong depth_key(REAL depth, uint cg) {
    return ((ulong)as_uint((float)depth) << 32) | (ulong)cg;
}

inline uint key_id(ulong key) { return (uint)(key & 0xffffffffUL); }

/* The backward's gradient slot of pair cg in tile (tx, ty): the pair's first slot plus the
 * tile's position in its row-major tile rectangle (x0, y0, x1, y1), the order in which its
 * tiles were counted. Scalar loads: vload4 is an out-of-line call on PoCL's CPU device (a
 * tenth of the compositing backward's cycles on scene A). */
inline int pair_slot(uint cg, int tx, int ty, __global const int *rects, __global const int *isect_offsets) {
    const int x0 = rects[4 * cg], y0 = rects[4 * cg + 1], x1 = rects[4 * cg + 2];
    return isect_offsets[cg] + (ty - y0) * (x1 - x0) + (tx - x0);
}

/* True when no pixel of a PIX-wide row segment can reach ALPHA_MIN: the nearest pixel is
 * beyond the sample's extent (from project). The margin keeps the test conservative against
 * rounding, so skipping never changes a result; forward and backward share this test, so
 * the backward replays exactly what the forward composited. */
#define CLS_EXTENT_MARGIN 1e-3
inline int outside_extent(REAL x, REAL y, REAL ext_x, REAL ext_y, REAL px_first, REAL px_last, REAL py) {
    const REAL dy = CLS_FABS(y - py);
    const REAL dx = CLS_FMAX((REAL)0, CLS_FMAX(px_first - x, x - px_last));
    const REAL m = (REAL)CLS_EXTENT_MARGIN;
    return ext_y < 0 || dy > ext_y * (1 + m) + m || dx > ext_x * (1 + m) + m;
}

#ifdef CCHUNK
/* Copy sample cg's compositing parameters to position i of a batch in local memory (the
 * forward and backward compositing kernels stage batches identically), with nf <= CCHUNK
 * of its CHANNELS features from channel ch0 on (zeros past the last channel). */
inline void stage_sample(int i, uint cg, __global const REAL *means2d, __global const REAL *conics,
                         __global const REAL *opac_cg, __global const REAL *extents,
                         __global const REAL *feats, __local REAL *l_xy, __local REAL *l_conic,
                         __local REAL *l_op, __local REAL *l_ext, __local REAL *l_f,
                         const int ch0, const int nf) {
    l_xy[2 * i] = means2d[2 * cg];
    l_xy[2 * i + 1] = means2d[2 * cg + 1];
    l_conic[3 * i] = conics[3 * cg];
    l_conic[3 * i + 1] = conics[3 * cg + 1];
    l_conic[3 * i + 2] = conics[3 * cg + 2];
    l_op[i] = opac_cg[cg];
    l_ext[2 * i] = extents[2 * cg];
    l_ext[2 * i + 1] = extents[2 * cg + 1];
    for (int ch = 0; ch < nf; ++ch)
        l_f[CCHUNK * i + ch] = ch0 + ch < CHANNELS ? feats[(size_t)cg * CHANNELS + ch0 + ch] : (REAL)0;
}
#endif

#ifdef CCHUNK
/* ---- the tuned compositing kernels' staging (RenderConfig.composite_impl="tuned") ------- */
/* A batch is staged as structure-of-arrays in local memory, padded to whole words of
 * CLS_WORD samples, so that an item tests the extents of a word of samples at once with
 * vector loads and walks only the samples it can see (set bits of a mask) instead of
 * branching on each. l_bx, l_by hold the extent test's bounds, computed as outside_extent
 * computes them (the same expression, so the same rounding and the same decisions); -1
 * marks a pair outside the tile (ext_y < 0) and the padding, which no pixel can see. */
#define CLS_WORD 32
#if REAL_DOUBLE
#define CLS_MV 4 /* lanes of the extent test: one 256-bit vector */
#else
#define CLS_MV 8
#endif
#define NPAD ((BATCH + CLS_WORD - 1) / CLS_WORD * CLS_WORD) /* staged samples, padded */
#define MVREAL CAT(REAL, CLS_MV)
#define MVMASK CAT(MASK_SCALAR, CLS_MV)

inline REAL extent_bound(REAL ext) {
    const REAL m = (REAL)CLS_EXTENT_MARGIN;
    return ext * (1 + m) + m; /* outside_extent's bound, same expression */
}

/* l_sm: a bound on sigma past which o exp(-sigma) < ALPHA_MIN for sure (ln(o / ALPHA_MIN)
 * widened by 0.1% and 1e-3, far beyond the rounding of exp and of the product), so that an
 * item skips the exp of a sample no pixel of its segment can see at ALPHA_MIN; the exact
 * test on alpha still decides for the others. */
#define CLS_SIGMA_MARGIN 1e-3
inline void stage_sample_soa(int i, uint cg, __global const REAL *means2d, __global const REAL *conics,
                             __global const REAL *opac_cg, __global const REAL *extents,
                             __global const REAL *feats, __local REAL *l_x, __local REAL *l_y,
                             __local REAL *l_ca, __local REAL *l_cb, __local REAL *l_cc,
                             __local REAL *l_op, __local REAL *l_sm, __local REAL *l_bx,
                             __local REAL *l_by, __local REAL *l_f, const int ch0, const int nf) {
    l_x[i] = means2d[2 * cg];
    l_y[i] = means2d[2 * cg + 1];
    l_ca[i] = conics[3 * cg];
    l_cb[i] = conics[3 * cg + 1];
    l_cc[i] = conics[3 * cg + 2];
    const REAL op = opac_cg[cg];
    l_op[i] = op;
    l_sm[i] = !((REAL)ALPHA_MIN > 0) ? (REAL)1e30 /* alpha_min = 0: every sigma >= 0 counts */
              : op >= (REAL)ALPHA_MIN
                  ? log(op / (REAL)ALPHA_MIN) * (1 + (REAL)CLS_SIGMA_MARGIN) + (REAL)CLS_SIGMA_MARGIN
                  : (REAL)-1;
    const REAL ex = extents[2 * cg], ey = extents[2 * cg + 1];
    l_bx[i] = extent_bound(ex);
    l_by[i] = ey < 0 ? (REAL)-1 : extent_bound(ey);
    for (int ch = 0; ch < nf; ++ch)
        l_f[CCHUNK * i + ch] = ch0 + ch < CHANNELS ? feats[(size_t)cg * CHANNELS + ch0 + ch] : (REAL)0;
}

/* Slot i of the last extent-bit word past the batch's end: a sample no pixel sees (its extent
 * bounds are negative), so the word-wide extent tests need no bounds check. */
inline void pad_sample_soa(int i, __local REAL *l_x, __local REAL *l_y, __local REAL *l_bx, __local REAL *l_by) {
    l_x[i] = 0;
    l_y[i] = 0;
    l_bx[i] = -1;
    l_by[i] = -1;
}

/* Prefetch (on PoCL's CPU device, CLS_POCL_CPU; elsewhere nothing) the compositing parameters
 * of sample cg and nf of its features from channel ch0 on. A batch's samples are random Gaussians, each a cache miss per array; prefetched while the
 * batch before is composited, their staging no longer waits on memory. */
inline void prefetch_sample(uint cg, __global const REAL *means2d, __global const REAL *conics,
                            __global const REAL *opac_cg, __global const REAL *extents,
                            __global const REAL *feats, const int ch0, const int nf) {
#if CLS_PREFETCH
    __builtin_prefetch(means2d + 2 * cg);
    __builtin_prefetch(conics + 3 * cg);
    __builtin_prefetch(opac_cg + cg);
    __builtin_prefetch(extents + 2 * cg);
    if (nf > 0) __builtin_prefetch(feats + (size_t)cg * CHANNELS + ch0);
#endif
}

/* Bit j set: sample w0 + j may reach ALPHA_MIN somewhere in the row segment [px_first,
 * px_last] x pyc, i.e. !outside_extent (for non-NaN inputs the same comparisons). */
inline uint extent_bits(int w0, __local const REAL *l_x, __local const REAL *l_y,
                        __local const REAL *l_bx, __local const REAL *l_by,
                        REAL px_first, REAL px_last, REAL pyc) {
    uint m = 0;
#if CLS_POCL_CPU
    for (int j = 0; j < CLS_WORD / CLS_MV; ++j) {
        const int o = (w0 + j * CLS_MV) / CLS_MV;
        const MVREAL x = ((__local const MVREAL *)l_x)[o], y = ((__local const MVREAL *)l_y)[o];
        const MVREAL dy = CLS_FABS(y - pyc);
        const MVREAL dx = CLS_FMAX((MVREAL)0, CLS_FMAX(px_first - x, x - px_last));
        const MVMASK vis = dy <= ((__local const MVREAL *)l_by)[o] && dx <= ((__local const MVREAL *)l_bx)[o];
#if CLS_MV == 8
        const MVMASK bit = vis & (MVMASK)(1, 2, 4, 8, 16, 32, 64, 128);
#else
        const MVMASK bit = vis & (MVMASK)(1, 2, 4, 8);
#endif
        m |= (uint)CAT(CLS_LANES, CLS_MV)(bit, |) << (j * CLS_MV);
    }
#else
    /* Elsewhere one sample at a time: Oclgrind 21.10's uninitialised-value checker crashes on
     * the vector form, and a GPU runs one pixel per item anyway. */
    for (int j = 0; j < CLS_WORD; ++j) {
        const REAL dy = fabs(l_y[w0 + j] - pyc);
        const REAL dx = fmax((REAL)0, fmax(px_first - l_x[w0 + j], l_x[w0 + j] - px_last));
        m |= (uint)(dy <= l_by[w0 + j] && dx <= l_bx[w0 + j]) << j;
    }
#endif
    return m;
}
#endif

#ifdef TILE
/* Tile rectangle [x0, x1) x [y0, y1) touched by a screen-space box of half-size radius. */
inline int4 tile_rect(REAL2 mean2d, int2 radius, int tiles_x, int tiles_y) {
    REAL tx = mean2d.x / TILE, ty = mean2d.y / TILE;
    REAL rx = (REAL)radius.x / TILE, ry = (REAL)radius.y / TILE;
    /* Clamp before converting: a far off-screen mean would overflow int. */
    int4 r;
    r.x = (int)CLS_FMIN((REAL)tiles_x, CLS_FMAX((REAL)0, CLS_FLOOR(tx - rx)));
    r.y = (int)CLS_FMIN((REAL)tiles_y, CLS_FMAX((REAL)0, CLS_FLOOR(ty - ry)));
    r.z = (int)CLS_FMIN((REAL)tiles_x, CLS_FMAX((REAL)0, CLS_CEIL(tx + rx)));
    r.w = (int)CLS_FMIN((REAL)tiles_y, CLS_FMAX((REAL)0, CLS_CEIL(ty + ry)));
    return r;
}
#endif

/* ---- real spherical harmonics up to degree 4 (gsplat's constants and sign convention) --- */
#ifdef SH_DEGREE
#define SH_BASIS_LEN ((SH_DEGREE + 1) * (SH_DEGREE + 1))
inline void sh_basis(REAL3 d, REAL *b) {
    b[0] = (REAL)0.2820947917738781;
#if SH_DEGREE >= 1
    b[1] = (REAL)-0.48860251190292 * d.y;
    b[2] = (REAL)0.48860251190292 * d.z;
    b[3] = (REAL)-0.48860251190292 * d.x;
#endif
#if SH_DEGREE >= 2
    REAL z2 = d.z * d.z, fC1 = d.x * d.x - d.y * d.y, fS1 = 2 * d.x * d.y;
    REAL fTmp0B = (REAL)-1.092548430592079 * d.z;
    b[4] = (REAL)0.5462742152960395 * fS1;
    b[5] = fTmp0B * d.y;
    b[6] = (REAL)0.9461746957575601 * z2 - (REAL)0.3153915652525201;
    b[7] = fTmp0B * d.x;
    b[8] = (REAL)0.5462742152960395 * fC1;
#endif
#if SH_DEGREE >= 3
    REAL fTmp0C = (REAL)-2.285228997322329 * z2 + (REAL)0.4570457994644658;
    REAL fTmp1B = (REAL)1.445305721320277 * d.z;
    REAL fC2 = d.x * fC1 - d.y * fS1, fS2 = d.x * fS1 + d.y * fC1;
    b[9] = (REAL)-0.5900435899266435 * fS2;
    b[10] = fTmp1B * fS1;
    b[11] = fTmp0C * d.y;
    b[12] = d.z * ((REAL)1.865881662950577 * z2 - (REAL)1.119528997770346);
    b[13] = fTmp0C * d.x;
    b[14] = fTmp1B * fC1;
    b[15] = (REAL)-0.5900435899266435 * fC2;
#endif
#if SH_DEGREE >= 4
    const REAL fC3 = d.x * fC2 - d.y * fS2, fS3 = d.x * fS2 + d.y * fC2;
    const REAL fTmp0D = d.z * ((REAL)-4.683325804901025 * z2 + (REAL)2.007139630671868);
    const REAL fTmp1D = (REAL)3.31161143515146 * z2 - (REAL)0.47308734787878;
    const REAL fTmp2D = (REAL)-1.770130769779931 * d.z;
    b[16] = (REAL)0.6258357354491763 * fS3;
    b[17] = fTmp2D * fS2;
    b[18] = fTmp1D * fS1;
    b[19] = fTmp0D * d.y;
    b[20] = (REAL)1.984313483298443 * d.z * b[12] - (REAL)1.006230589874905 * b[6];
    b[21] = fTmp0D * d.x;
    b[22] = fTmp1D * fC1;
    b[23] = fTmp2D * fC2;
    b[24] = (REAL)0.6258357354491763 * fC3;
#endif
}
#endif

/* The EWA splat of one Gaussian in one camera. project and project_bwd both call this, so
 * the backward differentiates exactly the arithmetic of the forward. */
typedef struct {
    REAL V[9];                     /* Rv M: V V^T is the camera-frame covariance */
    REAL j00, j02, j11, j12;       /* J = [[j00, 0, j02], [0, j11, j12]] */
    REAL tx, ty;                   /* the frustum-clamped mean J is evaluated at (times z) */
    int clip_x, clip_y;            /* whether that clamp was active */
    REAL T0[3], T1[3];             /* rows of J V */
    REAL a, b, d;                  /* 2D covariance J V V^T J^T, before eps2d */
} Ewa;

/* The Jacobian clamp's bounds on x/z (right, left) and y/z (down, up) of camera K: the view
 * frustum widened by CLS_FRUSTUM_MARGIN of tan(fov/2) on each side. */
inline REAL4 frustum_limits(__global const REAL *K, int width, int height) {
    const REAL fx = K[0], fy = K[4], cx = K[2], cy = K[5];
    const REAL tan_fovx = (REAL)0.5 * width / fx, tan_fovy = (REAL)0.5 * height / fy;
    return (REAL4)((width - cx) / fx + (REAL)CLS_FRUSTUM_MARGIN * tan_fovx,
                   cx / fx + (REAL)CLS_FRUSTUM_MARGIN * tan_fovx,
                   (height - cy) / fy + (REAL)CLS_FRUSTUM_MARGIN * tan_fovy,
                   cy / fy + (REAL)CLS_FRUSTUM_MARGIN * tan_fovy);
}

/* Upper bounds on the pixel radii (x, y) that project gives a pair with camera-frame mean p
 * (z > 0), from the scales' squared norm s2 = |s|^2 alone, before any EWA work. The 2D
 * covariance's xx entry is |[j00, 0, j02] Rv M|^2 + eps2d <= (fx/z)^2 (1 + Lx^2) |Rv|_F^2 s2 +
 * eps2d, with Lx the clamp's bound on |x/z| and |M|_F = |s| (R(q) is a rotation); the radius is
 * RADIUS_SIGMA (the largest extent either radius rule allows) times its square root, rounded
 * up. The factor and the added 2 px cover that rounding and the arithmetic's, so a pair these
 * bounds put off-screen is one the full computation culls too: the culled set, and with it
 * every output, is unchanged (tests/test_project.py, the off-screen case). */
inline REAL2 radius_bounds(REAL3 p, const REAL *Rv, REAL s2, REAL eps2d, __global const REAL *K,
                           REAL4 lim) {
    const REAL rz = 1 / p.z;
    const REAL w2 = Rv[0] * Rv[0] + Rv[1] * Rv[1] + Rv[2] * Rv[2] + Rv[3] * Rv[3] + Rv[4] * Rv[4]
                    + Rv[5] * Rv[5] + Rv[6] * Rv[6] + Rv[7] * Rv[7] + Rv[8] * Rv[8];
    /* (squares: a principal point outside the image makes one limit negative) */
    const REAL lx2 = CLS_FMAX(lim.x * lim.x, lim.y * lim.y), ly2 = CLS_FMAX(lim.z * lim.z, lim.w * lim.w);
    const REAL e = CLS_FMAX(eps2d, (REAL)0);
    const REAL jx = K[0] * rz, jy = K[4] * rz;
    const REAL ax = jx * jx * (1 + lx2) * w2 * s2 + e;
    const REAL ay = jy * jy * (1 + ly2) * w2 * s2 + e;
    const REAL f = (REAL)RADIUS_SIGMA * (REAL)1.001;
    return (REAL2)(f * CLS_SQRT(ax) + 2, f * CLS_SQRT(ay) + 2);
}

/* p: camera-frame mean (z > 0); Rv: row-major world-to-camera rotation; M = R(q) S. */
inline Ewa ewa_splat(REAL3 p, const REAL *Rv, const REAL *M, __global const REAL *K,
                     int width, int height) {
    Ewa e;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            e.V[3 * i + j] = Rv[3 * i] * M[j] + Rv[3 * i + 1] * M[3 + j] + Rv[3 * i + 2] * M[6 + j];
    const REAL fx = K[0], fy = K[4];
    const REAL4 lim = frustum_limits(K, width, height);
    const REAL lim_xp = lim.x, lim_xn = lim.y, lim_yp = lim.z, lim_yn = lim.w;
    const REAL rz = 1 / p.z, ux = p.x * rz, uy = p.y * rz;
    e.clip_x = ux > lim_xp || ux < -lim_xn;
    e.clip_y = uy > lim_yp || uy < -lim_yn;
    e.tx = p.z * CLS_FMIN(lim_xp, CLS_FMAX(-lim_xn, ux));
    e.ty = p.z * CLS_FMIN(lim_yp, CLS_FMAX(-lim_yn, uy));
    e.j00 = fx * rz;
    e.j02 = -fx * e.tx * rz * rz;
    e.j11 = fy * rz;
    e.j12 = -fy * e.ty * rz * rz;
    for (int j = 0; j < 3; ++j) {
        e.T0[j] = e.j00 * e.V[j] + e.j02 * e.V[6 + j];
        e.T1[j] = e.j11 * e.V[3 + j] + e.j12 * e.V[6 + j];
    }
    /* Forming J V before squaring keeps needle Gaussians positive semi-definite. */
    e.a = e.T0[0] * e.T0[0] + e.T0[1] * e.T0[1] + e.T0[2] * e.T0[2];
    e.b = e.T0[0] * e.T1[0] + e.T0[1] * e.T1[1] + e.T0[2] * e.T1[2];
    e.d = e.T1[0] * e.T1[0] + e.T1[1] * e.T1[1] + e.T1[2] * e.T1[2];
    return e;
}

/* Camera centre in world coordinates from a row-major world-to-camera matrix: -R^T t. */
inline REAL3 camera_centre(__global const REAL *vm) {
    REAL3 t = (REAL3)(vm[3], vm[7], vm[11]);
    return -(REAL3)(vm[0] * t.x + vm[4] * t.y + vm[8] * t.z,
                    vm[1] * t.x + vm[5] * t.y + vm[9] * t.z,
                    vm[2] * t.x + vm[6] * t.y + vm[10] * t.z);
}

/* ---- the compositors' batch staging (composite.cl, composite_bwd.cl) ------------------ */
/* CLS_TUNED (RenderConfig.composite_impl): 1, the default and the CPU build, stages a batch of
 * Gaussians in local memory as structure-of-arrays, one array per field, so that the extent
 * tests load whole vectors; 0 (the baseline, the GPU default) as array-of-structures (x, y
 * pairs and conic triples). S_X .. S_CC read sample k of the staged batch in either layout, so
 * the compositing loops, forward and backward, are written once for both; each kernel declares
 * the arrays the macros name. */
#ifndef CLS_TUNED
#define CLS_TUNED 1
#endif
#if CLS_TUNED
#define S_X(k) l_x[k]
#define S_Y(k) l_y[k]
#define S_CA(k) l_ca[k]
#define S_CB(k) l_cb[k]
#define S_CC(k) l_cc[k]
#else
#define S_X(k) l_xy[2 * (k)]
#define S_Y(k) l_xy[2 * (k) + 1]
#define S_CA(k) l_conic[3 * (k)]
#define S_CB(k) l_conic[3 * (k) + 1]
#define S_CC(k) l_conic[3 * (k) + 2]
#endif

/* ---- the backward compositors' common interface (composite_bwd*.cl; reduce.cl reads the slots) */
/* RenderConfig.backward_impl picks one of two kernels with one argument list (the runtime sets
 * the same arguments for either) and one slot layout (reduce.cl sums it), declared here once. G_GEOM:
 * geometry values per slot (v_xy, v_conic, v_opacity, |v_xy| with ABSGRAD) in the geometry
 * launch; WIDE: channels come from global memory when they do not fit in one chunk. */
#define G_GEOM (GEOM_GRAD ? (ABSGRAD ? 8 : 6) : 0)
#define WIDE (CHANNELS > CCHUNK)
#define COMPOSITE_BWD_ARGS                                                                   \
    const int width, const int height, const int tiles_x, const int tiles_per_cam,          \
    const int N, const int ch0,                                                             \
    __global const int *tile_offsets,  /* [C * tiles_per_cam + 1] */                        \
    __global const ulong *keys,        /* [M] sorted per segment */                         \
    __global const int *rects,         /* [C, N, 4] */                                      \
    __global const int *isect_offsets, /* [C * N] first slot of each pair */                \
    __global const REAL *means2d,      /* [C, N, 2] */                                      \
    __global const REAL *conics,       /* [C, N, 3] */                                      \
    __global const REAL *opac_cg,      /* [C, N] */                                         \
    __global const REAL *extents,      /* [C, N, 2] */                                      \
    __global const REAL *feats,        /* [C, N, CHANNELS] */                               \
    __global const REAL *out_feats,    /* [C, H, W, CHANNELS] forward result */             \
    __global const REAL *out_T,        /* [C, H, W] */                                      \
    __global const int *out_last,      /* [C, H, W] */                                      \
    __global const REAL *v_out,        /* [C, H, W, CHANNELS] */                            \
    __global const REAL *v_T,          /* [C, H, W] */                                      \
    __global REAL *slots               /* [M, SLOT_G] */

/* ---- each pair's sum of its slots (reduce.cl; composite_bwd_gauss.cl with FUSED_REDUCE) ---- */
/* REDUCE_G: values per slot of the layout above (geometry, then colour when COLOR_GRAD). Pair
 * cg's slots are contiguous (isect_offsets[cg] onwards, one per tile of its rectangle), so its
 * sum is a short loop in a fixed order: deterministic without float atomics, and the same bits
 * in either kernel. Outputs follow the slot layout, each only when built in. */
#define REDUCE_G (G_GEOM + (COLOR_GRAD ? CHANNELS : 0))
#define REDUCE_OUT_ARGS                                                                      \
    __global REAL *v_means2d,          /* [C, N, 2] */                                      \
    __global REAL *v_conics,           /* [C, N, 3] */                                      \
    __global REAL *v_opac,             /* [C, N] */                                         \
    __global REAL *absgrad,            /* [C, N, 2] */                                      \
    __global REAL *v_feats             /* [C, N, CHANNELS] */

#ifdef COLOR_GRAD /* (the programs that sum slots: the others lack CHANNELS) */
inline void reduce_pair(const int cg, __global const int *rects, __global const int *isect_offsets,
                        __global const REAL *slots, REDUCE_OUT_ARGS) {
    /* scalar loads: vload4 is an out-of-line call on PoCL's CPU device (see pair_slot) */
    const int n = (rects[4 * cg + 2] - rects[4 * cg]) * (rects[4 * cg + 3] - rects[4 * cg + 1]);
    __global const REAL *s = slots + (size_t)isect_offsets[cg] * REDUCE_G;
    /* One column at a time, summed in tile order: no private array, so any REDUCE_G fits. */
    for (int j = 0; j < REDUCE_G; ++j) {
        REAL acc = 0;
        for (int i = 0; i < n; ++i) acc += s[(size_t)i * REDUCE_G + j];
#if GEOM_GRAD
        if (j < 2) v_means2d[2 * cg + j] = acc;
        else if (j < 5) v_conics[3 * cg + j - 2] = acc;
        else if (j == 5) v_opac[cg] = acc;
        else if (j < G_GEOM) absgrad[2 * cg + j - 6] = acc;
        else
#endif
            v_feats[(size_t)cg * CHANNELS + j - G_GEOM] = acc;
    }
}
#endif

#endif /* CLSPLAT_COMMON_H */
