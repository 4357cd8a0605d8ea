/* project_bwd.cl — backward of project: screen-space gradients to the 3D parameters.
 *
 * One work-item per Gaussian, looping over cameras in order (a fixed summation order, no
 * atomics). Inputs are the gradients of means2d, conics, depths and the compositing opacity;
 * outputs are the gradients of means, quats (unnormalised, through the normalisation),
 * scales and opacities, and with VIEWMAT_GRAD each pair's contribution to its view matrix
 * (rotation rows and translation, [C, N, 12]) for the host to sum over Gaussians.
 * The forward quantities are recomputed: that costs less than storing them per pair.
 * Where the Jacobian's mean was clamped to the widened frustum, the clamped coordinate is a
 * constant and passes no gradient to the mean, exactly as the forward computed it.
 *
 * Build parameters: REAL_DOUBLE, ANTIALIASED, VIEWMAT_GRAD, CLS_POCL_CPU (common.h's inline maths).
 */

__kernel void project_bwd(const int C, const int N,
                          __global const REAL *means, __global const REAL *quats,
                          __global const REAL *scales, __global const REAL *opacities,
                          __global const REAL *viewmats, __global const REAL *Ks,
                          const int width, const int height, const REAL eps2d,
                          __global const int *radii,        /* [C, N, 2] */
                          __global const REAL *v_means2d,   /* [C, N, 2] */
                          __global const REAL *v_conics,    /* [C, N, 3] */
                          __global const REAL *v_depths,    /* [C, N] */
                          __global const REAL *v_opac_cg,   /* [C, N] */
                          __global REAL *v_means,           /* [N, 3] */
                          __global REAL *v_quats,           /* [N, 4] */
                          __global REAL *v_scales,          /* [N, 3] */
                          __global REAL *v_opacities        /* [N] */
#if VIEWMAT_GRAD
                          , __global REAL *v_view           /* [C, N, 12] */
#endif
) {
    const int g = get_global_id(0);
    if (g >= N) return;
    const REAL3 m = (REAL3)(means[3 * g], means[3 * g + 1], means[3 * g + 2]);
    const REAL4 q = (REAL4)(quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]);
    const REAL s[3] = {scales[3 * g], scales[3 * g + 1], scales[3 * g + 2]};
    const REAL o = opacities[g];
    REAL Rq[9];
    quat_to_rotmat(q, Rq);
    REAL M[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) M[3 * i + j] = Rq[3 * i + j] * s[j];

    REAL3 vm_acc = (REAL3)(0, 0, 0);
    REAL vM[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    REAL vo_acc = 0;

    for (int c = 0; c < C; ++c) {
        const size_t cg = (size_t)c * N + g;
        __global const REAL *vm = viewmats + 16 * c;
        __global const REAL *K = Ks + 9 * c;
        const REAL Rv[9] = {vm[0], vm[1], vm[2], vm[4], vm[5], vm[6], vm[8], vm[9], vm[10]};
        const REAL3 p = (REAL3)(Rv[0] * m.x + Rv[1] * m.y + Rv[2] * m.z + vm[3],
                                Rv[3] * m.x + Rv[4] * m.y + Rv[5] * m.z + vm[7],
                                Rv[6] * m.x + Rv[7] * m.y + Rv[8] * m.z + vm[11]);
        REAL3 vp = (REAL3)(0, 0, v_depths[cg]);
        REAL vRv[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};

        if (radii[2 * cg] != 0 || radii[2 * cg + 1] != 0) {
            const Ewa e = ewa_splat(p, Rv, M, K, width, height);
            const REAL fx = K[0], fy = K[4];
            const REAL rz = 1 / p.z, rz2 = rz * rz, rz3 = rz2 * rz;
            const REAL tx = e.tx, ty = e.ty, j00 = e.j00, j02 = e.j02, j11 = e.j11, j12 = e.j12;
            const REAL *V = e.V, *T0 = e.T0, *T1 = e.T1;
            REAL a = e.a, d = e.d;
            const REAL b = e.b;
            const REAL det_o = a * d - b * b;
            a += eps2d;
            d += eps2d;
            const REAL det = a * d - b * b, inv_det = 1 / det;
            const REAL A = d * inv_det, B = -b * inv_det, Cc = a * inv_det;

            /* conic = inverse(cov2d): d conic = -conic (d cov2d) conic. The off-diagonal conic
             * entry is shared by both symmetric positions, hence the halves. */
            const REAL vA = v_conics[3 * cg], vB = (REAL)0.5 * v_conics[3 * cg + 1], vC = v_conics[3 * cg + 2];
            const REAL P00 = A * vA + B * vB, P01 = A * vB + B * vC;
            const REAL P10 = B * vA + Cc * vB, P11 = B * vB + Cc * vC;
            REAL va = -(P00 * A + P01 * B);
            REAL vb = -2 * (P00 * B + P01 * Cc);
            REAL vd = -(P10 * B + P11 * Cc);
            const REAL vop = v_opac_cg[cg];
#if ANTIALIASED
            const REAL comp2 = fmax((REAL)0, det_o * inv_det), comp = sqrt(comp2);
            vo_acc += vop * comp;
            /* d comp = d(comp^2) / (2 comp), with gsplat's floor comp + 1e-6 in the
             * denominator; d(comp^2)/d cov2d = (1 - comp^2) conic - eps2d det(conic) I. */
            const REAL vsq = vop * o * (REAL)0.5 / (comp + (REAL)1e-6);
            const REAL one_m = 1 - comp2;
            va += vsq * (one_m * A - eps2d * inv_det);
            vd += vsq * (one_m * Cc - eps2d * inv_det);
            vb += vsq * 2 * one_m * B;
#else
            vo_acc += vop;
#endif
            /* cov2d = T T^T, T = J V. */
            REAL vT0[3], vT1[3];
            for (int j = 0; j < 3; ++j) {
                vT0[j] = 2 * va * T0[j] + vb * T1[j];
                vT1[j] = vb * T0[j] + 2 * vd * T1[j];
            }
            REAL vj00 = 0, vj02 = 0, vj11 = 0, vj12 = 0;
            REAL vV[9];
            for (int j = 0; j < 3; ++j) {
                vj00 += vT0[j] * V[j];
                vj02 += vT0[j] * V[6 + j];
                vj11 += vT1[j] * V[3 + j];
                vj12 += vT1[j] * V[6 + j];
                vV[j] = j00 * vT0[j];
                vV[3 + j] = j11 * vT1[j];
                vV[6 + j] = j02 * vT0[j] + j12 * vT1[j];
            }
            /* V = Rv M */
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j) {
                    vM[3 * i + j] += Rv[i] * vV[j] + Rv[3 + i] * vV[3 + j] + Rv[6 + i] * vV[6 + j];
                    vRv[3 * i + j] += vV[3 * i] * M[3 * j] + vV[3 * i + 1] * M[3 * j + 1] + vV[3 * i + 2] * M[3 * j + 2];
                }
            /* J(p) */
            vp.z += -fx * rz2 * vj00 - fy * rz2 * vj11;
            if (e.clip_x) vp.z += fx * tx * rz3 * vj02;
            else { vp.x += -fx * rz2 * vj02; vp.z += 2 * fx * p.x * rz3 * vj02; }
            if (e.clip_y) vp.z += fy * ty * rz3 * vj12;
            else { vp.y += -fy * rz2 * vj12; vp.z += 2 * fy * p.y * rz3 * vj12; }
            /* means2d = (fx x / z + cx, fy y / z + cy) */
            const REAL vx2 = v_means2d[2 * cg], vy2 = v_means2d[2 * cg + 1];
            vp.x += fx * rz * vx2;
            vp.y += fy * rz * vy2;
            vp.z += -fx * p.x * rz2 * vx2 - fy * p.y * rz2 * vy2;
        }
        /* p = Rv m + t */
        vm_acc += (REAL3)(Rv[0] * vp.x + Rv[3] * vp.y + Rv[6] * vp.z,
                          Rv[1] * vp.x + Rv[4] * vp.y + Rv[7] * vp.z,
                          Rv[2] * vp.x + Rv[5] * vp.y + Rv[8] * vp.z);
#if VIEWMAT_GRAD
        __global REAL *out = v_view + 12 * cg;
        const REAL vpa[3] = {vp.x, vp.y, vp.z};
        for (int i = 0; i < 3; ++i) {
            out[4 * i] = vRv[3 * i] + vpa[i] * m.x;
            out[4 * i + 1] = vRv[3 * i + 1] + vpa[i] * m.y;
            out[4 * i + 2] = vRv[3 * i + 2] + vpa[i] * m.z;
            out[4 * i + 3] = vpa[i];
        }
#endif
    }

    /* M = R(q) S */
    REAL vR[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) vR[3 * i + j] = vM[3 * i + j] * s[j];
    for (int j = 0; j < 3; ++j)
        v_scales[3 * g + j] = Rq[j] * vM[j] + Rq[3 + j] * vM[3 + j] + Rq[6 + j] * vM[6 + j];
    const REAL inv_n = rsqrt(dot(q, q));
    const REAL w = q.x * inv_n, x = q.y * inv_n, y = q.z * inv_n, z = q.w * inv_n;
    const REAL4 vqn = 2 * (REAL4)(
        x * (vR[7] - vR[5]) + y * (vR[2] - vR[6]) + z * (vR[3] - vR[1]),
        -2 * x * (vR[4] + vR[8]) + y * (vR[3] + vR[1]) + z * (vR[6] + vR[2]) + w * (vR[7] - vR[5]),
        x * (vR[3] + vR[1]) - 2 * y * (vR[0] + vR[8]) + z * (vR[7] + vR[5]) + w * (vR[2] - vR[6]),
        x * (vR[6] + vR[2]) + y * (vR[7] + vR[5]) - 2 * z * (vR[0] + vR[4]) + w * (vR[3] - vR[1]));
    const REAL4 qn = (REAL4)(w, x, y, z);
    const REAL4 vq = (vqn - qn * dot(qn, vqn)) * inv_n;
    v_quats[4 * g] = vq.x;
    v_quats[4 * g + 1] = vq.y;
    v_quats[4 * g + 2] = vq.z;
    v_quats[4 * g + 3] = vq.w;
    v_means[3 * g] = vm_acc.x;
    v_means[3 * g + 1] = vm_acc.y;
    v_means[3 * g + 2] = vm_acc.z;
    v_opacities[g] = vo_acc;
}
