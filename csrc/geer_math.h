// 3DGEER math shared by the CUDA kernels and a CPU build (tests/test_csrc_math.py).
//
// Every function here is the per-Gaussian, per-pair or per-ray step of the PyTorch twin in
// geer_ns/render/ (the specification), written to round the same way where that matters:
//   transforms.py  quat_to_rotmat, whitening (W = S^-1 R_v^T, MIN_SCALE clamp), o_u = -W mu_c
//   pbf.py         lambda^2 rule, _plane_bounds (rotated-frame tangent solve), mirror_tangent
//   (association, tile pyramid and pair keys: geer_associate.h)
//   transmittance  ray frame, D^2 = |m_u / |d_u||^2, t*, the half-line rule q(max(t*, 0)), alpha =
//                  min(0.99, sigma exp(-q/2)) kept where q <= 2 ln(255 sigma)
//   composite.py   front-to-back blending, stop before T < 1e-4
//   sh.py          real SH up to degree 3 (capped per Gaussian: gaussian_sh_degree), +0.5, clamp at 0
// One rule at every clamp (subgradients.py): a value exactly on its clamp gets the clamped side's
// derivative, 0; max(x, lo) passes the gradient where x > lo, min(x, hi) where x < hi (torch's rule).
// and the analytic backward of each (paper App. C, two-stage layout: the per-pair part runs in the
// render kernel, the per-Gaussian part in the preprocess backward).
//
// Plain C++ (no CUDA or torch headers); GEER_HD marks functions for both host and device.
#pragma once

#include <math.h>
#include <stdint.h>

#if defined(__CUDACC__)
#define GEER_HD __host__ __device__ __forceinline__
#elif defined(__GNUC__)
// Inlined on the CPU as on the GPU: the per-pair functions return structs the caller only partly reads.
#define GEER_HD inline __attribute__((always_inline))
#else
#define GEER_HD inline
#endif

namespace geer {

// ---------------------------------------------------------------------------------- constants
// Python floats cast to the compute type, exactly as torch does with scalar operands.
constexpr double kPi = 3.14159265358979323846;
constexpr double kAlphaMin = 1.0 / 255.0;      // pbf.ALPHA_MIN
constexpr double kAlphaMax = 0.99;             // transmittance.ALPHA_MAX
constexpr double kTMin = 1e-4;                 // composite.T_MIN
constexpr double kMinScale = 1e-12;            // transforms.MIN_SCALE
constexpr double kPaperLambda = 3.0;           // pbf.PAPER_LAMBDA
constexpr double kLamSqRelSlack = 1e-3;        // pbf._LAMBDA_SQ_REL_SLACK
constexpr double kLamSqAbsSlack = 1e-4;        // pbf._LAMBDA_SQ_ABS_SLACK

template <typename T> struct Limits;
template <> struct Limits<float> {
    GEER_HD static float tiny() { return 1.17549435082228750797e-38f; }  // torch.finfo(float32).tiny
    GEER_HD static float inf() { return INFINITY; }
};
template <> struct Limits<double> {
    GEER_HD static double tiny() { return 2.22507385850720138309e-308; }
    GEER_HD static double inf() { return double(INFINITY); }
};

// Overloads so that float code stays in float (no silent promotion to double).
GEER_HD float g_sqrt(float x) { return sqrtf(x); }
GEER_HD double g_sqrt(double x) { return sqrt(x); }
GEER_HD float g_atan2(float y, float x) { return atan2f(y, x); }
GEER_HD double g_atan2(double y, double x) { return atan2(y, x); }
GEER_HD float g_tan(float x) { return tanf(x); }
GEER_HD double g_tan(double x) { return tan(x); }
GEER_HD float g_exp(float x) { return expf(x); }
GEER_HD double g_exp(double x) { return exp(x); }
GEER_HD float g_log(float x) { return logf(x); }
GEER_HD double g_log(double x) { return log(x); }
// |x| with the sign bit cleared (also of -0: the render's absolute sums start from +0 in every path).
GEER_HD float g_fabs(float x) { return fabsf(x); }
GEER_HD double g_fabs(double x) { return fabs(x); }
// Per-pair intrinsics. float32 on the GPU: rsqrtf (2 ulp) and __expf (2 + 1.2 |x| ulp, |x| <= 5.6 where a
// pair is kept: < 1e-6 relative), within the 1e-5 float32 forward tolerance; float64 stays IEEE, and the
// CPU build (what the tests run) uses the IEEE functions in both precisions.
GEER_HD float g_rsqrt(float x) {
#if defined(__CUDA_ARCH__)
    return rsqrtf(x);
#else
    return 1.0f / sqrtf(x);
#endif
}
GEER_HD double g_rsqrt(double x) { return 1.0 / sqrt(x); }
GEER_HD float g_exp_pair(float x) {
#if defined(__CUDA_ARCH__)
    return __expf(x);
#else
    return expf(x);
#endif
}
GEER_HD double g_exp_pair(double x) { return exp(x); }
// Products and sums that are never contracted into FMAs. nvcc contracts a * b + c by default, and after
// inlining into the forward and the backward kernel it may do so differently, so that the two would take
// different pair decisions; the _rn intrinsics are never contracted (the CPU build: -ffp-contract=off).
#if defined(__CUDA_ARCH__)
GEER_HD float x_mul(float a, float b) { return __fmul_rn(a, b); }
GEER_HD double x_mul(double a, double b) { return __dmul_rn(a, b); }
GEER_HD float x_add(float a, float b) { return __fadd_rn(a, b); }
GEER_HD double x_add(double a, double b) { return __dadd_rn(a, b); }
GEER_HD float x_sub(float a, float b) { return __fsub_rn(a, b); }
GEER_HD double x_sub(double a, double b) { return __dsub_rn(a, b); }
#else
template <typename T> GEER_HD T x_mul(T a, T b) { return a * b; }
template <typename T> GEER_HD T x_add(T a, T b) { return a + b; }
template <typename T> GEER_HD T x_sub(T a, T b) { return a - b; }
#endif
template <typename T> GEER_HD T g_abs(T x) { return x < T(0) ? -x : x; }
// torch.maximum / clamp semantics for ordinary numbers (inputs here are never NaN).
template <typename T> GEER_HD T g_max(T a, T b) { return a > b ? a : b; }
template <typename T> GEER_HD T g_min(T a, T b) { return a < b ? a : b; }

// ---------------------------------------------------------------------------------- vectors
template <typename T> struct Vec3 {
    T x, y, z;
};
// Row-major 3x3: m[3 * row + col].
template <typename T> struct Mat3 {
    T m[9];
};

template <typename T> GEER_HD Vec3<T> v3(T x, T y, T z) { return Vec3<T>{x, y, z}; }
template <typename T> GEER_HD Vec3<T> load3(const T* p) { return Vec3<T>{p[0], p[1], p[2]}; }
template <typename T> GEER_HD void store3(T* p, const Vec3<T>& v) { p[0] = v.x; p[1] = v.y; p[2] = v.z; }
template <typename T> GEER_HD Vec3<T> operator+(const Vec3<T>& a, const Vec3<T>& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <typename T> GEER_HD Vec3<T> operator-(const Vec3<T>& a, const Vec3<T>& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <typename T> GEER_HD Vec3<T> operator*(T s, const Vec3<T>& a) { return {s * a.x, s * a.y, s * a.z}; }
template <typename T> GEER_HD T dot(const Vec3<T>& a, const Vec3<T>& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename T> GEER_HD Vec3<T> cross(const Vec3<T>& a, const Vec3<T>& b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
// The same, never contracted (x_mul / x_add): for the pair decisions.
template <typename T> GEER_HD T x_dot(const Vec3<T>& a, const Vec3<T>& b) {
    return x_add(x_add(x_mul(a.x, b.x), x_mul(a.y, b.y)), x_mul(a.z, b.z));
}
template <typename T> GEER_HD Vec3<T> x_cross(const Vec3<T>& a, const Vec3<T>& b) {
    return {x_sub(x_mul(a.y, b.z), x_mul(a.z, b.y)), x_sub(x_mul(a.z, b.x), x_mul(a.x, b.z)),
            x_sub(x_mul(a.x, b.y), x_mul(a.y, b.x))};
}
template <typename T> GEER_HD Vec3<T> matvec(const Mat3<T>& a, const Vec3<T>& v) {
    return {a.m[0] * v.x + a.m[1] * v.y + a.m[2] * v.z, a.m[3] * v.x + a.m[4] * v.y + a.m[5] * v.z,
            a.m[6] * v.x + a.m[7] * v.y + a.m[8] * v.z};
}
// a^T v
template <typename T> GEER_HD Vec3<T> matTvec(const Mat3<T>& a, const Vec3<T>& v) {
    return {a.m[0] * v.x + a.m[3] * v.y + a.m[6] * v.z, a.m[1] * v.x + a.m[4] * v.y + a.m[7] * v.z,
            a.m[2] * v.x + a.m[5] * v.y + a.m[8] * v.z};
}
template <typename T> GEER_HD Mat3<T> matmul(const Mat3<T>& a, const Mat3<T>& b) {
    Mat3<T> c;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            c.m[3 * i + j] = a.m[3 * i] * b.m[j] + a.m[3 * i + 1] * b.m[3 + j] + a.m[3 * i + 2] * b.m[6 + j];
    return c;
}
// a^T b
template <typename T> GEER_HD Mat3<T> matTmul(const Mat3<T>& a, const Mat3<T>& b) {
    Mat3<T> c;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            c.m[3 * i + j] = a.m[i] * b.m[j] + a.m[3 + i] * b.m[3 + j] + a.m[6 + i] * b.m[6 + j];
    return c;
}
// Element-wise conversion between compute types (the Gaussian frame is made in float64: canonical_frame).
template <typename U, typename T> GEER_HD Vec3<U> convert3(const Vec3<T>& a) { return Vec3<U>{U(a.x), U(a.y), U(a.z)}; }
template <typename U, typename T> GEER_HD Mat3<U> convert_mat3(const Mat3<T>& a) {
    Mat3<U> c;
    for (int i = 0; i < 9; ++i) c.m[i] = U(a.m[i]);
    return c;
}
template <typename T> GEER_HD Mat3<T> load_mat3(const T* p) {
    Mat3<T> a;
    for (int i = 0; i < 9; ++i) a.m[i] = p[i];
    return a;
}
template <typename T> GEER_HD void store_mat3(T* p, const Mat3<T>& a) {
    for (int i = 0; i < 9; ++i) p[i] = a.m[i];
}

// ---------------------------------------------------------------------------------- lanes
// The per-ray functions (geer_ray.h) take their ray quantities as a lane type L: one ray, L = T (a GPU
// thread), or in the CPU build a pack of rays at once (geer_packs.h: GCC vectors, the same IEEE operations
// lane by lane, so the same bits). Lane<L> names the scalar, the per-lane mask and integer types and
// broadcasts; the lane_* helpers are the scalar forms, which geer_packs.h overloads for packs.
template <typename L> struct Lane;
template <typename T> struct ScalarLane {
    using Scalar = T;
    using Mask = bool;
    using Int = int;
    static constexpr int width = 1;
    GEER_HD static T splat(T x) { return x; }
    GEER_HD static int splat_int(int x) { return x; }
};
template <> struct Lane<float> : ScalarLane<float> {};
template <> struct Lane<double> : ScalarLane<double> {};
template <typename L> GEER_HD L splat(typename Lane<L>::Scalar x) { return Lane<L>::splat(x); }
template <typename L> GEER_HD Vec3<L> splat3(const typename Lane<L>::Scalar* p) {
    return Vec3<L>{splat<L>(p[0]), splat<L>(p[1]), splat<L>(p[2])};
}
GEER_HD bool lane_any(bool m) { return m; }
GEER_HD bool lane_not(bool m) { return !m; }
// Lane i of a value or mask (a scalar is a one-lane pack).
GEER_HD float lane_get(float v, int) { return v; }
GEER_HD double lane_get(double v, int) { return v; }
GEER_HD int lane_get(int v, int) { return v; }
template <typename S> GEER_HD void lane_set(S& v, int, S x) { v = x; }
template <typename V> GEER_HD V lane_select(bool m, V a, V b) { return m ? a : b; }
// Scalar forms of the per-pair intrinsics with a lane mask: exp where kept, 0 elsewhere.
GEER_HD float exp_where(bool keep, float x) { return keep ? g_exp_pair(x) : 0.0f; }
GEER_HD double exp_where(bool keep, double x) { return keep ? g_exp_pair(x) : 0.0; }

// ================================================================================ forward: Gaussian
// transforms.quat_to_rotmat: wxyz, any norm (normalised with the norm clamped at tiny).
// transforms.normalize_quats: divide by the largest |component| first, so the squares stay in range (a
// float32 quaternion of norm 1e19 or 1e-25 normalises exactly). norm_out = |q|.
template <typename T> GEER_HD void normalize_quat(const T* q, T* qn, T* norm_out) {
    const T m = g_max(g_max(g_max(g_abs(q[0]), g_abs(q[1])), g_max(g_abs(q[2]), g_abs(q[3]))), Limits<T>::tiny());
    T s[4];
    for (int i = 0; i < 4; ++i) s[i] = q[i] / m;
    const T n = g_sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2] + s[3] * s[3]);
    *norm_out = n * m;
    const T nc = g_max(n, Limits<T>::tiny());
    for (int i = 0; i < 4; ++i) qn[i] = s[i] / nc;
}

template <typename T> GEER_HD Mat3<T> quat_to_rotmat(const T* quat) {
    T q[4], n;
    normalize_quat(quat, q, &n);
    const T w = q[0], x = q[1], y = q[2], z = q[3];
    Mat3<T> r;
    r.m[0] = T(1) - T(2) * (y * y + z * z); r.m[1] = T(2) * (x * y - w * z); r.m[2] = T(2) * (x * z + w * y);
    r.m[3] = T(2) * (x * y + w * z); r.m[4] = T(1) - T(2) * (x * x + z * z); r.m[5] = T(2) * (y * z - w * x);
    r.m[6] = T(2) * (x * z - w * y); r.m[7] = T(2) * (y * z + w * x); r.m[8] = T(1) - T(2) * (x * x + y * y);
    return r;
}

template <typename T> GEER_HD T clamp_scale(T s) { return g_max(s, T(kMinScale)); }

// W = S^-1 R_v^T: W[i][j] = R_v[j][i] / s_i (transforms.whitening).
template <typename T> GEER_HD Mat3<T> whitening(const Mat3<T>& rot_v, const T* scales) {
    Mat3<T> w;
    for (int i = 0; i < 3; ++i) {
        const T inv_s = T(1) / clamp_scale(scales[i]);
        for (int j = 0; j < 3; ++j) w.m[3 * i + j] = inv_s * rot_v.m[3 * j + i];
    }
    return w;
}

// o_u = W (o - mu_c) with the camera at the origin of the view frame.
template <typename T> GEER_HD Vec3<T> camera_in_canonical(const Mat3<T>& w, const Vec3<T>& mean_c) {
    const Vec3<T> p = matvec(w, mean_c);
    return Vec3<T>{-p.x, -p.y, -p.z};
}

// pbf.pbf_lambda_sq: (lambda^2 with slack, alive).
template <typename T> GEER_HD T pbf_lambda_sq(T opacity, bool paper_lambda) {
    T lam2 = paper_lambda ? T(kPaperLambda * kPaperLambda)
                          : T(2.0) * g_log(g_max(T(255.0) * opacity, T(1.0)));
    return lam2 * T(1.0 + kLamSqRelSlack) + T(kLamSqAbsSlack);
}
template <typename T> GEER_HD bool pbf_alive(T opacity) { return opacity >= T(kAlphaMin); }

// pbf._plane_bounds: angular interval (lo, hi), angle = atan2(a, z), of the ellipse with mean
// (mu_a, mu_z) and covariance factor rows row_a, row_z, seen from the origin of the (a, z) plane.
// Solved in the frame rotated so that the mean lies on +z (no mu mu^T - lambda^2 Sigma cancellation).
template <typename T>
GEER_HD void plane_bounds(T mu_a, T mu_z, const Vec3<T>& row_a, const Vec3<T>& row_z, T lam2, bool force_full,
                          T* lo_out, T* hi_out) {
    const T tiny = Limits<T>::tiny();
    const T pi = T(kPi);
    const T r = g_sqrt(mu_a * mu_a + mu_z * mu_z);
    const T r_safe = g_max(r, tiny);
    const T theta_mu = g_atan2(mu_a, mu_z);
    const T cos_t = mu_z / r_safe, sin_t = mu_a / r_safe;
    const Vec3<T> row_x = cos_t * row_a - sin_t * row_z;   // across the mean's direction
    const Vec3<T> row_zp = sin_t * row_a + cos_t * row_z;  // along it
    const T s_xx = dot(row_x, row_x), s_xz = dot(row_x, row_zp), s_zz = dot(row_zp, row_zp);
    const Vec3<T> c = cross(row_x, row_zp);
    const T det = dot(c, c);  // Lagrange identity: det(S')
    const T disc = lam2 * (r * r) * s_xx - lam2 * lam2 * det;
    const T t00 = lam2 * s_xx, t02 = lam2 * s_xz, t22 = lam2 * s_zz - r * r;
    const T sq = g_sqrt(g_max(disc, T(0)));

    T low = 0, high = 0, last_mag = 0;
    for (int k = 0; k < 2; ++k) {
        const T sign = k == 0 ? T(1) : T(-1);
        // The same tangent line written two ways; take the better-conditioned one.
        const T va0 = t02 + sign * sq, va1 = t22;
        const T vb0 = t00, vb1 = t02 - sign * sq;
        const T mag_a = g_abs(va0) + g_abs(va1), mag_b = g_abs(vb0) + g_abs(vb1);
        const bool use_a = mag_a >= mag_b;
        const T delta = use_a ? g_atan2(va0, va1) : g_atan2(vb0, vb1);  // relative to the mean, (-pi, pi]
        const T l = delta > T(0) ? delta - pi : delta;
        const T h = delta < T(0) ? delta + pi : delta;
        low = k == 0 ? l : g_max(low, l);
        high = k == 0 ? h : g_min(high, h);
        last_mag = g_max(mag_a, mag_b);  // the twin tests degeneracy on the second (sign = -1) line
    }
    const bool degenerate = (last_mag <= tiny) || (r <= tiny);
    const bool full = force_full || (disc < T(0)) || degenerate;
    *lo_out = full ? -pi : theta_mu + low;
    *hi_out = full ? pi : theta_mu + high;
}

// pbf.mirror_tangent with xi = 1: tan(theta / 2), +-inf at +-pi.
template <typename T> GEER_HD T mirror_tangent(T theta) {
    const T pi = T(kPi);
    if (theta >= pi) return Limits<T>::inf();
    if (theta <= -pi) return -Limits<T>::inf();
    return g_tan(T(0.5) * theta);
}

// associate._interval_pieces: unwrapped [lo, hi] split at the +-pi seam into two mirror-tangent pieces.
// The second piece is empty (lo = +inf, hi = -inf) when there is no wrap.
template <typename T> struct MirrorPieces {
    T a_lo, a_hi, b_lo, b_hi;
};

template <typename T> GEER_HD MirrorPieces<T> interval_pieces(T lo, T hi) {
    const T pi = T(kPi), two_pi = T(2 * kPi);
    const T a_lo = g_min(g_max(lo, -pi), pi), a_hi = g_min(g_max(hi, -pi), pi);
    const bool wraps_up = hi > pi, wraps_down = lo < -pi;
    const T b_lo = wraps_up ? -pi : lo + two_pi;
    const T b_hi = wraps_up ? hi - two_pi : pi;
    const bool has_b = wraps_up || wraps_down;
    MirrorPieces<T> p;
    p.a_lo = mirror_tangent(a_lo);
    p.a_hi = mirror_tangent(a_hi);
    p.b_lo = has_b ? mirror_tangent(b_lo) : Limits<T>::inf();
    p.b_hi = has_b ? mirror_tangent(b_hi) : -Limits<T>::inf();
    return p;
}

// associate._overlaps for one tile interval [t_lo, t_hi] (mirror domain), per lane. One ray: short-circuit (the
// GPU loads no more bounds than it needs).
template <typename T, typename L>
GEER_HD typename Lane<L>::Mask pieces_overlap(const MirrorPieces<T>& p, L t_lo, L t_hi) {
    if constexpr (Lane<L>::width == 1) {
        return (p.a_lo <= t_hi && t_lo <= p.a_hi) || (p.b_lo <= t_hi && t_lo <= p.b_hi);
    } else {
        return ((p.a_lo <= t_hi) & (t_lo <= p.a_hi)) | ((p.b_lo <= t_hi) & (t_lo <= p.b_hi));
    }
}

// A PBF as the association tests it: theta and phi pieces (mirror domain).
template <typename T> struct PbfPieces {
    MirrorPieces<T> theta, phi;
};

template <typename T> GEER_HD PbfPieces<T> pbf_pieces(const T* pbf_bounds) {
    return PbfPieces<T>{interval_pieces(pbf_bounds[0], pbf_bounds[1]), interval_pieces(pbf_bounds[2], pbf_bounds[3])};
}

// Whether a ray (or a tile) with mirror-domain bounds b = (theta lo, hi, phi lo, hi) meets the PBF, per lane.
template <typename T, typename L> GEER_HD typename Lane<L>::Mask pbf_overlaps(const PbfPieces<T>& p, const L* b) {
    if constexpr (Lane<L>::width == 1) {
        return pieces_overlap(p.theta, b[0], b[1]) && pieces_overlap(p.phi, b[2], b[3]);
    } else {
        return pieces_overlap(p.theta, b[0], b[1]) & pieces_overlap(p.phi, b[2], b[3]);
    }
}

// Everything the preprocess stage produces for one Gaussian.
template <typename T> struct GaussianForward {
    Mat3<T> w;        // whitening matrix
    Vec3<T> o_u;      // camera centre in the canonical frame
    T bounds[4];      // PBF (theta_lo, theta_hi, phi_lo, phi_hi), unwrapped angles
    T lam2;
    bool alive;
    bool camera_inside;
};

// A Gaussian's frame for one view (transforms.canonical_frame): R_v = R_c R(q), W = S^-1 R_v^T and o_u = -W mu_c,
// made in float64 from the inputs and rounded once to T. Why: q = D^2 is ill-conditioned in W and o_u by about
// |o_u|^2 / D^2, so the few roundings of a float32 chain move q by ~1e-6 relative, enough to put a pair on the
// other side of the 1/255 threshold (docs/cuda.md, "The frame in float64").
template <typename T> struct CanonicalFrame {
    Mat3<T> rot_v;
    Mat3<T> w;
    Vec3<T> o_u;
};
template <typename T>
GEER_HD CanonicalFrame<T> canonical_frame(const Vec3<T>& mean_c, const T* quat, const T* scales, const Mat3<T>& rot_c) {
    const double q[4] = {double(quat[0]), double(quat[1]), double(quat[2]), double(quat[3])};
    const double s[3] = {double(scales[0]), double(scales[1]), double(scales[2])};
    const Mat3<double> rot_v = matmul(convert_mat3<double>(rot_c), quat_to_rotmat(q));
    const Mat3<double> w = whitening(rot_v, s);
    return CanonicalFrame<T>{convert_mat3<T>(rot_v), convert_mat3<T>(w),
                             convert3<T>(camera_in_canonical(w, convert3<double>(mean_c)))};
}

// The per-Gaussian forward of rasterize.preprocess (without colour): view rotation, whitening, o_u, PBF.
template <typename T>
GEER_HD GaussianForward<T> preprocess_gaussian(const Vec3<T>& mean_c, const T* quat, const T* scales, T opacity,
                                               const Mat3<T>& rot_c, bool paper_lambda) {
    GaussianForward<T> g;
    const CanonicalFrame<T> frame = canonical_frame(mean_c, quat, scales, rot_c);
    const Mat3<T>& rot_v = frame.rot_v;
    g.w = frame.w;
    g.o_u = frame.o_u;
    g.lam2 = pbf_lambda_sq(opacity, paper_lambda);
    g.alive = pbf_alive(opacity);
    g.camera_inside = dot(g.o_u, g.o_u) <= g.lam2;
    // Covariance factor M = R_v S (rows), Sigma_c = M M^T.
    Vec3<T> rows[3];
    for (int i = 0; i < 3; ++i)
        rows[i] = Vec3<T>{rot_v.m[3 * i] * clamp_scale(scales[0]), rot_v.m[3 * i + 1] * clamp_scale(scales[1]),
                          rot_v.m[3 * i + 2] * clamp_scale(scales[2])};
    plane_bounds(mean_c.x, mean_c.z, rows[0], rows[2], g.lam2, g.camera_inside, &g.bounds[0], &g.bounds[1]);
    plane_bounds(mean_c.y, mean_c.z, rows[1], rows[2], g.lam2, g.camera_inside, &g.bounds[2], &g.bounds[3]);
    return g;
}

// ---------------------------------------------------------------------------------- SH colour
// Real SH constants (sh.py), in the compute type.
#define GEER_SH_C0 0.28209479177387814
#define GEER_SH_C1 0.4886025119029199
#define GEER_SH_C2_0 1.0925484305920792
#define GEER_SH_C2_1 -1.0925484305920792
#define GEER_SH_C2_2 0.31539156525252005
#define GEER_SH_C2_3 -1.0925484305920792
#define GEER_SH_C2_4 0.5462742152960396
#define GEER_SH_C3_0 -0.5900435899266435
#define GEER_SH_C3_1 2.890611442640554
#define GEER_SH_C3_2 -0.4570457994644658
#define GEER_SH_C3_3 0.3731763325901154
#define GEER_SH_C3_4 -0.4570457994644658
#define GEER_SH_C3_5 1.445305721320277
#define GEER_SH_C3_6 -0.5900435899266435

GEER_HD constexpr int num_sh_bases(int degree) { return (degree + 1) * (degree + 1); }

// The degree Gaussian i's colour is evaluated at: the active degree (the training schedule's), capped by the
// Gaussian's own where `degrees` ([N], each Gaussian's kept degree) is given. The bands above it are neither read
// nor written, forward or backward: their coefficients are zero and frozen (geer_ns/sh_degrees).
GEER_HD int gaussian_sh_degree(int active, const uint8_t* degrees, int64_t i) {
    if (degrees == nullptr || active < 0) return active;
    const int own = int(degrees[i]);
    return own < active ? own : active;
}

// Basis values b[k] (k < (degree+1)^2) at the unit direction (x, y, z); optionally their gradients.
template <typename T>
GEER_HD void sh_basis(int degree, T x, T y, T z, T* b, Vec3<T>* db /* may be null */) {
    b[0] = T(GEER_SH_C0);
    if (db) db[0] = Vec3<T>{0, 0, 0};
    if (degree < 1) return;
    const T c1 = T(GEER_SH_C1);
    b[1] = -c1 * y; b[2] = c1 * z; b[3] = -c1 * x;
    if (db) { db[1] = {0, -c1, 0}; db[2] = {0, 0, c1}; db[3] = {-c1, 0, 0}; }
    if (degree < 2) return;
    const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    b[4] = T(GEER_SH_C2_0) * xy;
    b[5] = T(GEER_SH_C2_1) * yz;
    b[6] = T(GEER_SH_C2_2) * (T(2) * zz - xx - yy);
    b[7] = T(GEER_SH_C2_3) * xz;
    b[8] = T(GEER_SH_C2_4) * (xx - yy);
    if (db) {
        db[4] = T(GEER_SH_C2_0) * Vec3<T>{y, x, 0};
        db[5] = T(GEER_SH_C2_1) * Vec3<T>{0, z, y};
        db[6] = T(GEER_SH_C2_2) * Vec3<T>{-T(2) * x, -T(2) * y, T(4) * z};
        db[7] = T(GEER_SH_C2_3) * Vec3<T>{z, 0, x};
        db[8] = T(GEER_SH_C2_4) * Vec3<T>{T(2) * x, -T(2) * y, 0};
    }
    if (degree < 3) return;
    b[9] = T(GEER_SH_C3_0) * y * (T(3) * xx - yy);
    b[10] = T(GEER_SH_C3_1) * xy * z;
    b[11] = T(GEER_SH_C3_2) * y * (T(4) * zz - xx - yy);
    b[12] = T(GEER_SH_C3_3) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
    b[13] = T(GEER_SH_C3_4) * x * (T(4) * zz - xx - yy);
    b[14] = T(GEER_SH_C3_5) * z * (xx - yy);
    b[15] = T(GEER_SH_C3_6) * x * (xx - T(3) * yy);
    if (db) {
        db[9] = T(GEER_SH_C3_0) * Vec3<T>{T(6) * xy, T(3) * xx - T(3) * yy, 0};
        db[10] = T(GEER_SH_C3_1) * Vec3<T>{yz, xz, xy};
        db[11] = T(GEER_SH_C3_2) * Vec3<T>{-T(2) * xy, T(4) * zz - xx - T(3) * yy, T(8) * yz};
        db[12] = T(GEER_SH_C3_3) * Vec3<T>{-T(6) * xz, -T(6) * yz, T(6) * zz - T(3) * xx - T(3) * yy};
        db[13] = T(GEER_SH_C3_4) * Vec3<T>{T(4) * zz - T(3) * xx - yy, -T(2) * xy, T(8) * xz};
        db[14] = T(GEER_SH_C3_5) * Vec3<T>{T(2) * xz, -T(2) * yz, xx - yy};
        db[15] = T(GEER_SH_C3_6) * Vec3<T>{T(3) * xx - T(3) * yy, -T(6) * xy, 0};
    }
}

// Unit view direction (sh.py normalises with the norm clamped at tiny); returns the norm.
template <typename T> GEER_HD Vec3<T> sh_direction(const Vec3<T>& dir, T* norm_out) {
    const T n = g_sqrt(dot(dir, dir));
    *norm_out = n;
    const T nc = g_max(n, Limits<T>::tiny());
    return Vec3<T>{dir.x / nc, dir.y / nc, dir.z / nc};
}

// sh_to_color for one Gaussian: coeffs [K][3] (K >= (degree+1)^2), dir = mean - camera centre (world).
// Writes the unclamped value (before the clamp at 0) to raw if given.
template <typename T>
GEER_HD Vec3<T> sh_to_color(const T* coeffs, int degree, const Vec3<T>& dir, Vec3<T>* raw = nullptr) {
    T n;
    const Vec3<T> d = sh_direction(dir, &n);
    T b[16];
    sh_basis<T>(degree, d.x, d.y, d.z, b, nullptr);
    Vec3<T> acc{0, 0, 0};
    const int nb = num_sh_bases(degree);
    for (int k = 0; k < nb; ++k) acc = acc + b[k] * load3(coeffs + 3 * k);
    acc = acc + Vec3<T>{T(0.5), T(0.5), T(0.5)};
    if (raw) *raw = acc;
    return Vec3<T>{g_max(acc.x, T(0)), g_max(acc.y, T(0)), g_max(acc.z, T(0))};
}

// ================================================================================ backward: Gaussian
// The render backward's canonical moment K = dL/dW W^T, of the total dL/dW (through W d and o_u = -W mean_c:
// geer_ray.h pair_canonical_moment, summed over the pairs) and dL/d(o_u) -> dL/d(mean_c), dL/dquat, dL/dscale
// (PreprocessCUDA, C.4-C.6). dL/dmean_c = -W^T dL/do_u (C.15). W[i][j] = R_v[j][i] / s_i with R_v = R_c R(q / |q|),
// so dL/dW = K W^-T = K S R_v^T; scaling s_i by (1 + eps) scales W's row i by 1 / (1 + eps): dL/ds_i = -K[i][i] / s_i.
// From K no term cancels for thin Gaussians (the former dL/dW - dL/do_u mean_c^T lost float32's digits there).
// mean_c: unused (kept for the callers' layout). g_rot_c (null: not wanted): this Gaussian's share of
// dL/dR_c = dL/dR_v R^T [9], row-major (camera pose gradients; the mean's share goes through dL/dmean_c, the SH
// direction's through sh_backward).
template <typename T>
GEER_HD void preprocess_backward_gaussian(const Vec3<T>& mean_c, const T* quat, const T* scales, const Mat3<T>& rot_c,
                                          const T* k_render, const Vec3<T>& g_o, Vec3<T>& g_mean_c, T* g_quat,
                                          T* g_scale, T* g_rot_c = nullptr) {
    (void)mean_c;
    const Mat3<T> rot = quat_to_rotmat(quat);
    const Mat3<T> rot_v = matmul(rot_c, rot);
    const Mat3<T> w = whitening(rot_v, scales);
    const Vec3<T> gm = matTvec(w, g_o);
    g_mean_c = Vec3<T>{-gm.x, -gm.y, -gm.z};
    // dL/dR_v[j][i] = dL/dW[i][j] / s_i = sum_k K[i][k] s_k R_v[j][k] / s_i (C.11); scales (C.10), no gradient at
    // or below MIN_SCALE.
    Mat3<T> g_rot_v;
    for (int i = 0; i < 3; ++i) {
        const T inv_s = T(1) / clamp_scale(scales[i]);
        for (int j = 0; j < 3; ++j) {
            T acc = T(0);
            for (int k = 0; k < 3; ++k) acc += k_render[3 * i + k] * clamp_scale(scales[k]) * rot_v.m[3 * j + k];
            g_rot_v.m[3 * j + i] = acc * inv_s;
        }
        g_scale[i] = scales[i] > T(kMinScale) ? -k_render[3 * i + i] * inv_s : T(0);
    }
    if (g_rot_c)
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                g_rot_c[3 * i + j] = g_rot_v.m[3 * i] * rot.m[3 * j] + g_rot_v.m[3 * i + 1] * rot.m[3 * j + 1]
                                     + g_rot_v.m[3 * i + 2] * rot.m[3 * j + 2];
    // Rotation (C.11-C.14, written for R(q) of a unit quaternion, then projected for |q| != 1).
    const Mat3<T> g = matTmul(rot_c, g_rot_v);  // dL/dR
    T q[4], qn;
    normalize_quat(quat, q, &qn);
    const T qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    const T* G = g.m;
    T gq[4];
    gq[0] = T(2) * (-qz * G[1] + qy * G[2] + qz * G[3] - qx * G[5] - qy * G[6] + qx * G[7]);
    gq[1] = T(2) * (qy * G[1] + qz * G[2] + qy * G[3] - T(2) * qx * G[4] - qw * G[5] + qz * G[6] + qw * G[7]
                    - T(2) * qx * G[8]);
    gq[2] = T(2) * (-T(2) * qy * G[0] + qx * G[1] + qw * G[2] + qx * G[3] + qz * G[5] - qw * G[6] + qz * G[7]
                    - T(2) * qy * G[8]);
    gq[3] = T(2) * (-T(2) * qz * G[0] - qw * G[1] + qx * G[2] + qw * G[3] - T(2) * qz * G[4] + qy * G[5]
                    + qx * G[6] + qy * G[7]);
    // q_hat = q / max(|q|, tiny): dq = (g - q_hat (q_hat . g)) / |q| (no norm gradient when clamped).
    if (qn >= Limits<T>::tiny()) {
        const T proj = qw * gq[0] + qx * gq[1] + qy * gq[2] + qz * gq[3];
        for (int k = 0; k < 4; ++k) g_quat[k] = (gq[k] - q[k] * proj) / qn;
    } else {
        for (int k = 0; k < 4; ++k) g_quat[k] = gq[k] / Limits<T>::tiny();
    }
}

// dL/drgb -> dL/dcoeffs [K][3] (bands <= degree written, others untouched) and dL/d(dir) (dir = mean -
// camera centre, world). The clamp at 0 passes the gradient where the value is > 0 (subgradients.floor_at).
template <typename T>
GEER_HD void sh_backward(const T* coeffs, int degree, const Vec3<T>& dir, const Vec3<T>& g_rgb, T* g_coeffs,
                         Vec3<T>& g_dir) {
    T n;
    const Vec3<T> d = sh_direction(dir, &n);
    T b[16];
    Vec3<T> db[16];
    sh_basis<T>(degree, d.x, d.y, d.z, b, db);
    const int nb = num_sh_bases(degree);
    Vec3<T> raw{T(0.5), T(0.5), T(0.5)};
    for (int k = 0; k < nb; ++k) raw = raw + b[k] * load3(coeffs + 3 * k);
    const Vec3<T> g{raw.x > T(0) ? g_rgb.x : T(0), raw.y > T(0) ? g_rgb.y : T(0), raw.z > T(0) ? g_rgb.z : T(0)};
    Vec3<T> g_d{T(0), T(0), T(0)};
    for (int k = 0; k < nb; ++k) {
        store3(g_coeffs + 3 * k, b[k] * g);
        g_d = g_d + dot(load3(coeffs + 3 * k), g) * db[k];
    }
    g_dir = Vec3<T>{T(0), T(0), T(0)};
    if (degree >= 1 && n > Limits<T>::tiny()) g_dir = (T(1) / n) * (g_d - dot(d, g_d) * d);
    else if (degree >= 1) g_dir = (T(1) / Limits<T>::tiny()) * g_d;
}

}  // namespace geer
