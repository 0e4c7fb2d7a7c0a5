// Stage 3's per-pair and per-ray math: the Gaussian's ray frame, the exact ray response (eval_pair), front-
// to-back blending (ray_forward_step) and the back-to-front gradient (ray_backward_step), shared by the CUDA
// kernels (render.cu) and the CPU build (cpu_render*.cpp).
//
// Every function takes its ray quantities as a lane type L (geer_math.h Lane): L = T is one ray, what a GPU
// thread runs; the CPU build also runs them on packs of rays (geer_packs.h), which must be included first so
// that the pack overloads of the lane_* helpers are visible here. Per-lane control flow is written as "skip
// when no lane needs it (lane_any), then merge per lane (lane_select)": for L = T that is the plain branch,
// and a pack computes each lane with the same operations in the same order, so the same bits.
#pragma once
#define GEER_RAY_H

#include "geer_math.h"

namespace geer {

template <typename L> GEER_HD Vec3<L> lane_select3(typename Lane<L>::Mask m, const Vec3<L>& a, const Vec3<L>& b) {
    return Vec3<L>{lane_select(m, a.x, b.x), lane_select(m, a.y, b.y), lane_select(m, a.z, b.z)};
}

// ================================================================================ forward: pair
// One Gaussian as the render stage sees it (transmittance.ray_frame, plus what blending needs): 32 values,
// 16-byte aligned (128 bytes in float32), so that the kernels' shared-memory reads vectorise.
template <typename T> struct alignas(16) GaussFrame {
    T w[9];       // rows 0-2: d_u = W d
    T mom[9];     // rows 3-5: m_u = ([o_u]_x W) d (columns o_u x W e_j)
    T along[3];   // row 6: o_u . d_u = (W^T o_u) . d
    T o[3];       // o_u (for the backward)
    T o_sq;       // |o_u|^2: q of every ray whose line peaks behind the camera (t* <= 0)
    T q_max;      // 2 ln(255 sigma): alpha >= 1/255 exactly when q <= q_max (-inf for sigma = 0)
    T rgb[3];
    T opacity;
    PbfPieces<T> pbf;  // the per-ray cull (ray_meets_pbf)
    T pad[2];
};
static_assert(sizeof(GaussFrame<float>) == 160 && alignof(GaussFrame<float>) == 16, "GaussFrame<float>: 10 x 16 B");
static_assert(sizeof(GaussFrame<double>) == 320, "GaussFrame<double>: 20 x 16 B");

// pieces: the Gaussian's PBF as the association tests it, [8] = theta (a_lo, a_hi, b_lo, b_hi), phi (same)
// in the mirror domain (cuda_backend.pbf_cull_pieces; made once per Gaussian and view, not per tile: the
// tangents would cost the render kernels registers).
template <typename T>
GEER_HD void make_frame(const T* w, const T* o_u, const T* rgb, T opacity, const T* pieces, GaussFrame<T>& f) {
    const Vec3<T> o = load3(o_u);
    for (int i = 0; i < 9; ++i) f.w[i] = w[i];
    for (int j = 0; j < 3; ++j) {
        const Vec3<T> col{w[j], w[3 + j], w[6 + j]};
        const Vec3<T> c = x_cross(o, col);
        f.mom[j] = c.x; f.mom[3 + j] = c.y; f.mom[6 + j] = c.z;
        f.along[j] = x_dot(o, col);
    }
    for (int i = 0; i < 3; ++i) { f.o[i] = o_u[i]; f.rgb[i] = rgb[i]; }
    f.o_sq = x_dot(o, o);
    f.q_max = T(2.0) * g_log(T(255.0) * opacity);  // transmittance.alpha_level_sq
    f.opacity = opacity;
    f.pbf.theta = MirrorPieces<T>{pieces[0], pieces[1], pieces[2], pieces[3]};
    f.pbf.phi = MirrorPieces<T>{pieces[4], pieces[5], pieces[6], pieces[7]};
    f.pad[0] = f.pad[1] = T(0);
}

// Per-ray cull before any per-pair arithmetic: a ray whose own mirror-domain bounds (RayGrid.ray_cull_bounds:
// its BEAP angles, widened by a slack far above the PBF's rounding) miss the Gaussian's PBF has alpha < 1/255,
// so eval_pair would not keep it either (the association's tile test, one ray at a time). On a tile's list
// most rays lie outside most PBFs (65-71 % of the pairs on the views of docs/renderer.md).
// ray_bounds: the lane's 4 bounds (theta lo, hi, phi lo, hi), each an L.
template <typename T, typename L>
GEER_HD typename Lane<L>::Mask ray_meets_pbf(const GaussFrame<T>& g, const L* ray_bounds) {
    return pbf_overlaps(g.pbf, ray_bounds);
}

template <typename L> struct PairEval {
    using Mask = typename Lane<L>::Mask;
    Vec3<L> d_u;   // W d
    Vec3<L> m_hat; // m_u / |d_u|
    L inv_norm;    // 1 / |d_u| (|d_u|^2 clamped at tiny)
    Mask clamped;  // |d_u|^2 <= tiny: inv_norm does not depend on d_u
    L dist_sq;     // D^2: q on the whole line, at t*
    L t_star;      // distance along the unit ray to the line's maximum response
    Mask front;    // t* > 0: the line's maximum lies on the half-line t >= 0, q = D^2; else q = |o_u|^2
    L q;           // q(max(t*, 0)): squared canonical distance of the half-line's closest point
    Mask keep;     // q <= q_max (alpha >= 1/255): decided before the exponential
    L gauss;       // exp(-q / 2)        (0 where not kept)
    L raw;         // sigma exp(-q / 2)  (0 where not kept)
    L alpha;       // min(0.99, raw)     (0 where not kept)
    Vec3<L> o_u;   // the ray's origin in the canonical frame (set by eval_pair<kOrigin> only; else g.o)
};

// transmittance.canonical_ray_response + half_line_sq + pair_alpha for one (ray, Gaussian) pair: the
// half-line rule, the peak response on the ray as travelled (t >= 0), sigma exp(-q(max(t*, 0)) / 2).
// The forward and the backward kernel both decide `front` and `keep` here, on values computed with
// x_* arithmetic (never contracted into FMAs), so the two decisions are the same bits.
// kOrigin: the ray starts at its own point `origin` of the camera frame (rolling shutter: the camera centre at
// the ray's time), so its canonical origin is o_u + W origin and the moment, o_u . d_u and |o_u|^2 are the
// pair's own (three more dot products and a cross product); otherwise every ray starts at the camera centre
// and reads them from the frame.
template <typename T, typename L, bool kOrigin = false>
GEER_HD PairEval<L> eval_pair(const GaussFrame<T>& g, const Vec3<L>& d, const Vec3<L>* origin = nullptr) {
    PairEval<L> e;
    e.d_u = Vec3<L>{x_dot(splat3<L>(g.w), d), x_dot(splat3<L>(g.w + 3), d), x_dot(splat3<L>(g.w + 6), d)};
    Vec3<L> m;
    L a, o_sq;
    if constexpr (kOrigin) {
        const Vec3<L> wo{x_dot(splat3<L>(g.w), *origin), x_dot(splat3<L>(g.w + 3), *origin),
                         x_dot(splat3<L>(g.w + 6), *origin)};
        e.o_u = Vec3<L>{x_add(splat<L>(g.o[0]), wo.x), x_add(splat<L>(g.o[1]), wo.y), x_add(splat<L>(g.o[2]), wo.z)};
        m = x_cross(e.o_u, e.d_u);
        a = x_dot(e.o_u, e.d_u);
        o_sq = x_dot(e.o_u, e.o_u);
    } else {
        m = Vec3<L>{x_dot(splat3<L>(g.mom), d), x_dot(splat3<L>(g.mom + 3), d), x_dot(splat3<L>(g.mom + 6), d)};
        a = x_dot(splat3<L>(g.along), d);
        o_sq = splat<L>(g.o_sq);
    }
    const L nsq = x_dot(e.d_u, e.d_u);
    const L tiny = splat<L>(Limits<T>::tiny());
    e.clamped = nsq <= tiny;
    e.inv_norm = g_rsqrt(g_max(nsq, tiny));
    e.m_hat = Vec3<L>{x_mul(e.inv_norm, m.x), x_mul(e.inv_norm, m.y), x_mul(e.inv_norm, m.z)};  // no overflow
    e.dist_sq = x_dot(e.m_hat, e.m_hat);
    e.t_star = x_mul(x_mul(-a, e.inv_norm), e.inv_norm);
    e.front = e.t_star > splat<L>(T(0));
    e.q = lane_select(e.front, e.dist_sq, o_sq);
    e.keep = e.q <= splat<L>(g.q_max);
    e.gauss = exp_where(e.keep, T(-0.5) * e.q);
    e.raw = g.opacity * e.gauss;
    e.alpha = g_min(e.raw, splat<L>(T(kAlphaMax)));
    return e;
}

// A pair's position on the ray as blended and reported: max(t*, 0) (the depth; the per-ray order's key).
template <typename T, typename L> GEER_HD L pair_depth(const PairEval<L>& e) {
    return lane_select(e.front, e.t_star, splat<L>(T(0)));
}

// v = gC . c + gZ z + gA of one pair (colour c, depth z): what its blend weight is worth to the loss.
template <typename T, typename L>
GEER_HD L blend_value(const L* g_rgb, const T* rgb, L g_depth, L z, L g_acc) {
    return g_rgb[0] * rgb[0] + g_rgb[1] * rgb[1] + g_rgb[2] * rgb[2] + g_depth * z + g_acc;
}

// ================================================================================ forward: ray
template <typename L> struct RayForward;
template <typename T, typename L>
GEER_HD L ray_blend(RayForward<L>& s, typename Lane<L>::Mask kept, L alpha, L t_hit, const T* rgb, int pos);

template <typename L> struct RayForward {
    L rgb[3];
    L depth;      // sum of w_i max(t*_i, 0)
    L acc;        // sum of w_i
    L trans;      // transmittance after the last blended Gaussian
    L median;     // max(t*, 0) of the Gaussian whose blend takes the transmittance below 0.5 (0: never)
    typename Lane<L>::Int n_contrib;  // 1 + list position of the last blended Gaussian (0: none)
    typename Lane<L>::Mask done;      // stopped (T would fall below T_MIN) or the ray is invalid
};

template <typename L> GEER_HD void ray_forward_init(RayForward<L>& s, typename Lane<L>::Mask valid) {
    using T = typename Lane<L>::Scalar;
    s.rgb[0] = s.rgb[1] = s.rgb[2] = splat<L>(T(0));
    s.depth = s.acc = splat<L>(T(0));
    s.trans = splat<L>(T(1));
    s.median = splat<L>(T(0));
    s.n_contrib = Lane<L>::splat_int(0);
    s.done = lane_not(valid);
}

// Blend the Gaussian at list position `pos` (composite.composite: stop before T < T_MIN). Returns each lane's
// blend weight T_before alpha, 0 where the lane does not blend the Gaussian (RenderOutput.max_weight).
// kOrigin, origin: the ray's own origin (eval_pair).
template <typename T, typename L, bool kOrigin = false>
GEER_HD L ray_forward_step(RayForward<L>& s, const GaussFrame<T>& g, const Vec3<L>& d, const L* ray_bounds,
                           int pos, const Vec3<L>* origin = nullptr) {
    using Mask = typename Lane<L>::Mask;
    const L zero = splat<L>(T(0));
    const Mask open = lane_not(s.done) & ray_meets_pbf(g, ray_bounds);
    if (!lane_any(open)) return zero;
    const PairEval<L> e = eval_pair<T, L, kOrigin>(g, d, origin);
    const Mask kept = open & e.keep;
    if (!lane_any(kept)) return zero;
    return ray_blend<T, L>(s, kept, e.alpha, pair_depth<T, L>(e), g.rgb, pos);
}

// Blend one Gaussian (colour rgb, alpha, at t_hit = max(t*, 0) on the ray, list position pos) into the lanes of
// `kept` (composite.composite: stop before T < T_MIN). Returns each lane's blend weight T_before alpha, 0 where
// the lane does not blend it. The blend of ray_forward_step (list order) and of blend_pending (geer_order.h).
template <typename T, typename L>
GEER_HD L ray_blend(RayForward<L>& s, typename Lane<L>::Mask kept, L alpha, L t_hit, const T* rgb, int pos) {
    using Mask = typename Lane<L>::Mask;
    const L zero = splat<L>(T(0));
    const L t_after = s.trans * (splat<L>(T(1)) - alpha);
    const Mask stop = kept & (t_after < splat<L>(T(kTMin)));
    s.done = s.done | stop;
    const Mask blend = kept & lane_not(stop);
    if (!lane_any(blend)) return zero;
    const L w = alpha * s.trans;
    for (int c = 0; c < 3; ++c) s.rgb[c] = lane_select(blend, s.rgb[c] + w * rgb[c], s.rgb[c]);
    s.depth = lane_select(blend, s.depth + w * t_hit, s.depth);
    s.acc = lane_select(blend, s.acc + w, s.acc);
    const L half = splat<L>(T(0.5));
    s.median = lane_select(blend & lane_not(s.trans < half) & (t_after < half), t_hit, s.median);
    s.trans = lane_select(blend, t_after, s.trans);
    s.n_contrib = lane_select(blend, Lane<L>::splat_int(pos + 1), s.n_contrib);
    return lane_select(blend, w, zero);
}

// ================================================================================ backward: pair
// dL/dD^2, dL/dt* of one pair -> dL/d(o_u), dL/dW (paper C.3-C.4, RenderCUDA part).
// With m = o_u x d_u, n = 1 / |d_u|, m_hat = m n, d_hat = d_u n:
//   D^2 = |m|^2 n^2        dD^2/dm = 2 n m_hat      dD^2/dd_u (via n) = -2 D^2 n d_hat
//   t*  = -(o_u . d_u) n^2 dt*/do_u = -n d_hat      dt*/dd_u = -n^2 o_u - 2 t* n d_hat
//   d(m . g)/do_u = d_u x g,  d(m . g)/dd_u = g x o_u
// so dL/do_u = 2 gD (d_hat x m_hat) - gt n d_hat and dL/dd_u = n [2 gD (m_hat x o_u) - gt n o_u
// - 2 (gD D^2 + gt t*) d_hat], dL/dW = dL/dd_u d^T (C.9). Everything stays O(|o_u|), never |m|^2.
template <typename T, typename L>
GEER_HD void pair_response_grads(const PairEval<L>& e, const Vec3<L>& o_u, L g_dist_sq, L g_t_star, Vec3<L>& g_o,
                                 Vec3<L>& g_du) {
    const L n = e.inv_norm;
    const Vec3<L> d_hat = n * e.d_u;
    g_o = (T(2) * g_dist_sq) * cross(d_hat, e.m_hat) - (g_t_star * n) * d_hat;
    g_du = (T(2) * g_dist_sq) * cross(e.m_hat, o_u) - (g_t_star * n) * o_u;
    const typename Lane<L>::Mask unclamped = lane_not(e.clamped);
    if (lane_any(unclamped))
        g_du = lane_select3<L>(unclamped, g_du - (T(2) * (g_dist_sq * e.dist_sq + g_t_star * e.t_star)) * d_hat, g_du);
    g_du = n * g_du;
}

// The same, with dL/dW = dL/dd_u d^T accumulated into g_w (the per-pair test op, cpu_render.cpp pair_backward).
template <typename T, typename L>
GEER_HD void pair_response_backward(const PairEval<L>& e, const Vec3<L>& o_u, const Vec3<L>& d, L g_dist_sq,
                                    L g_t_star, Vec3<L>& g_o, L* g_w /* 9, accumulated */) {
    Vec3<L> g_du;
    pair_response_grads<T>(e, o_u, g_dist_sq, g_t_star, g_o, g_du);
    const L gd[3] = {g_du.x, g_du.y, g_du.z};
    const L dv[3] = {d.x, d.y, d.z};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) g_w[3 * i + j] += gd[i] * dv[j];
}

// The pair's canonical moment K = dL/dA at A = I, A a linear map of the Gaussian's canonical frame (W -> A W):
// K = dL/dW W^T = dL/dd_u d_u^T + dL/do_u o_u^T, what the preprocess backward turns into the scale and
// rotation gradients (geer_math.h preprocess_backward_gaussian; docs/cuda.md, "the float32 gap"). Written as
// the sum above it cancels catastrophically for thin Gaussians (1e-8 scales: both terms ~1e8 |g|, K ~ |g|),
// so it is evaluated in closed form from the closest point p = d_hat x m_hat of the line (= o_u + t* d_u,
// no cancellation): q = |p|^2 is a minimum over t, so dq/dA = 2 p p^T (envelope theorem), and
// dt*/dA = -n (d_hat p^T + p d_hat^T). The camera-centre branch (q = |o_u|^2): 2 o_u o_u^T, no depth term.
// Lanes with |d_u|^2 clamped at tiny (scales > 1e19) keep the plain sum (no W dependence through n there).
template <typename T, typename L>
GEER_HD void pair_canonical_moment(const PairEval<L>& e, const Vec3<L>& o_u, L g_q, L g_depth_t, const Vec3<L>& g_o,
                                   L* k /* 9, row-major, overwritten */) {
    const Vec3<L> d_hat = e.inv_norm * e.d_u;
    const Vec3<L> p = cross(d_hat, e.m_hat);
    const L two_g = T(2) * g_q, g_t = g_depth_t * e.inv_norm;
    const L pv[3] = {p.x, p.y, p.z}, dv[3] = {d_hat.x, d_hat.y, d_hat.z}, ov[3] = {o_u.x, o_u.y, o_u.z};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            const L front = two_g * pv[i] * pv[j] - g_t * (dv[i] * pv[j] + pv[i] * dv[j]);
            k[3 * i + j] = lane_select(e.front, front, two_g * ov[i] * ov[j]);
        }
    if (lane_any(e.clamped & e.front)) {
        Vec3<L> g_o_line, g_du;
        pair_response_grads<T>(e, o_u, g_q, g_depth_t, g_o_line, g_du);
        const L gd[3] = {g_du.x, g_du.y, g_du.z}, du[3] = {e.d_u.x, e.d_u.y, e.d_u.z};
        const L go[3] = {g_o.x, g_o.y, g_o.z};
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                k[3 * i + j] = lane_select(e.clamped & e.front, gd[i] * du[j] + go[i] * ov[j], k[3 * i + j]);
    }
}

// dL/dq, dL/d(depth position) of one kept pair -> dL/d(o_u) and the canonical moment K through the half-line
// rule. One gradient at every clamp, the rule of subgradients.py (a tie takes the clamped side), as the twin's
// masks (transmittance.py):
//   max(t*, 0)   the t* branch where t* > 0, the camera-centre branch q = |o_u|^2 (no W, no depth
//                gradient) where t* <= 0. q is C^1 across t* = 0 (both branches: value |o_u|^2,
//                gradient 2 o_u), so only depth has a kink there, and at the tie it takes the derivative 0.
//   min(raw, 0.99), the 1/255 skip, the 1e-4 stop: see ray_backward_step.
// g_du_out (null: not wanted): dL/dd_u (0 on the camera-centre branch, which does not depend on the ray).
template <typename T, typename L>
GEER_HD void half_line_backward(const PairEval<L>& e, const Vec3<L>& o_u, L g_q, L g_depth_t, Vec3<L>& g_o,
                                L* k /* 9 */, Vec3<L>* g_du_out = nullptr) {
    const Vec3<L> g_o_centre = (T(2) * g_q) * o_u;
    const Vec3<L> zero3{splat<L>(T(0)), splat<L>(T(0)), splat<L>(T(0))};
    if (lane_any(e.front)) {
        Vec3<L> g_du;
        pair_response_grads<T>(e, o_u, g_q, g_depth_t, g_o, g_du);
        g_o = lane_select3<L>(e.front, g_o, g_o_centre);
        if (g_du_out) *g_du_out = lane_select3<L>(e.front, g_du, zero3);
    } else {
        g_o = g_o_centre;
        if (g_du_out) *g_du_out = zero3;
    }
    pair_canonical_moment<T>(e, o_u, g_q, g_depth_t, g_o, k);
}

// ================================================================================ backward: ray
// Back-to-front state of one ray (3DGS-style): transmittance before the current Gaussian is
// recovered as T_after / (1 - alpha); `rec` is sum_{j > i} alpha_j prod_{i<k<j} (1 - alpha_k) v_j with
// v = gC . c + gZ z + gA, so that dL/dalpha_i = T_i (v_i - rec).
template <typename L> struct RayBackward {
    L trans;      // transmittance after the Gaussian about to be processed
    L rec;
    L g_rgb[3];   // dL/d(rgb sum), dL/d(depth sum), dL/d(accumulation) of this ray
    L g_depth;
    L g_acc;
    Vec3<L> g_dir;     // dL/d(this ray's direction), summed over its blended pairs (ray_backward_step's kDirGrad)
    Vec3<L> g_origin;  // dL/d(this ray's origin), the same (kDirGrad with kOrigin)
};

// Per-pair gradient contributions, to be summed into the Gaussian's buffers.
template <typename L> struct PairGrad {
    L w[9];  // the canonical moment K = dL/dW W^T (pair_canonical_moment), row-major
    L o[3];
    L rgb[3];
    L opacity;
};

template <typename L> GEER_HD void pair_grad_zero(PairGrad<L>& p) {
    const L zero = splat<L>(typename Lane<L>::Scalar(0));
    for (int i = 0; i < 9; ++i) p.w[i] = zero;
    for (int i = 0; i < 3; ++i) p.o[i] = p.rgb[i] = zero;
    p.opacity = zero;
}

template <typename T, typename L, bool kDirGrad, bool kOrigin>
GEER_HD void pair_backward_from_alpha(const PairEval<L>& e, const GaussFrame<T>& g, L w, L g_alpha, const L* g_rgb,
                                      L g_depth, typename Lane<L>::Mask live, PairGrad<L>& p, Vec3<L>& g_dir,
                                      Vec3<L>& g_origin);

// One Gaussian of the ray's blended prefix, back to front, for the lanes in `active`. Returns the lanes
// that blended it (q <= q_max: what the forward blended too), whose p it sets; the state of the others is
// untouched. No per-ray cull here: the GPU, whose 1024-thread float32 build has no registers to spare for
// it, skips whole warps (render.cu); the CPU build visits only the lanes its forward recorded as blending
// the pair (cpu_render_backward.cpp); tests/test_cpu_backend.py checks that the two give the same bits.
// Subgradients at the clamps:
//   alpha = min(raw, 0.99)  the derivative of raw where raw < 0.99, none where raw >= 0.99 (subgradients.py);
//   skip (q <= q_max) and stop (T_after >= 1e-4)  piecewise constant: a blended pair gets its ordinary
//                           derivative (also exactly on a threshold, where it is blended), others none;
//   max(t*, 0)              half_line_backward.
// kDirGrad: also add the pair's dL/d(ray direction) = W^T dL/dd_u to s.g_dir (lens refinement; a build of its
// own, so that the default one keeps its registers). kOrigin: the ray starts at `origin` (eval_pair); the pair's
// canonical origin o_u + W origin then takes o_u's place below (p.o is dL/d of it, which is dL/do_u, and the
// canonical moment K is in its terms: o_u + W origin = W (origin - mean) scales with W as o_u does), and with
// kDirGrad s.g_origin gets dL/d(origin) = W^T p.o.
template <typename T, typename L, bool kDirGrad = false, bool kOrigin = false>
GEER_HD typename Lane<L>::Mask ray_backward_step(RayBackward<L>& s, const GaussFrame<T>& g, const Vec3<L>& d,
                                                 typename Lane<L>::Mask active, PairGrad<L>& p,
                                                 const Vec3<L>* origin = nullptr) {
    using Mask = typename Lane<L>::Mask;
    if (!lane_any(active)) return active;
    const PairEval<L> e = eval_pair<T, L, kOrigin>(g, d, origin);
    const Mask live = active & e.keep;
    if (!lane_any(live)) return live;
    const L zero = splat<L>(T(0));
    const L one_minus = splat<L>(T(1)) - e.alpha;
    const L t_before = s.trans / one_minus;
    const L w = e.alpha * t_before;
    const L v = blend_value<T, L>(s.g_rgb, g.rgb, s.g_depth, pair_depth<T, L>(e), s.g_acc);
    const L g_alpha = t_before * (v - s.rec);
    s.rec = lane_select(live, e.alpha * v + one_minus * s.rec, s.rec);
    s.trans = lane_select(live, t_before, s.trans);
    pair_backward_from_alpha<T, L, kDirGrad, kOrigin>(e, g, w, g_alpha, s.g_rgb, s.g_depth, live, p, s.g_dir,
                                                      s.g_origin);
    return live;
}

// One blended pair's gradients from its blend weight w and dL/dalpha (the order's part, which ray_backward_step
// and geer_order.h's backward_pending each take their own way): p for the Gaussian, and with kDirGrad the ray's
// direction (and with kOrigin its origin) gradients added to g_dir (g_origin) in the lanes of `live`.
template <typename T, typename L, bool kDirGrad, bool kOrigin>
GEER_HD void pair_backward_from_alpha(const PairEval<L>& e, const GaussFrame<T>& g, L w, L g_alpha, const L* g_rgb,
                                      L g_depth, typename Lane<L>::Mask live, PairGrad<L>& p, Vec3<L>& g_dir,
                                      Vec3<L>& g_origin) {
    using Mask = typename Lane<L>::Mask;
    const L zero = splat<L>(T(0));
    pair_grad_zero(p);
    for (int c = 0; c < 3; ++c) p.rgb[c] = w * g_rgb[c];
    const Mask unclamped = e.raw < splat<L>(T(kAlphaMax));
    p.opacity = lane_select(unclamped, g_alpha * e.gauss, zero);
    const L g_q = lane_select(unclamped, T(-0.5) * g_alpha * e.raw, zero);
    Vec3<L> g_o;
    Vec3<L> o_u;
    if constexpr (kOrigin) o_u = e.o_u;
    else o_u = splat3<L>(g.o);
    if constexpr (kDirGrad) {
        Vec3<L> g_du;
        half_line_backward<T>(e, o_u, g_q, lane_select(e.front, w * g_depth, zero), g_o, p.w, &g_du);
        const Vec3<L> g_d = g_du.x * splat3<L>(g.w) + g_du.y * splat3<L>(g.w + 3) + g_du.z * splat3<L>(g.w + 6);
        g_dir = lane_select3<L>(live, g_dir + g_d, g_dir);
        if constexpr (kOrigin) {
            const Vec3<L> g_org = g_o.x * splat3<L>(g.w) + g_o.y * splat3<L>(g.w + 3) + g_o.z * splat3<L>(g.w + 6);
            g_origin = lane_select3<L>(live, g_origin + g_org, g_origin);
        }
    } else {
        half_line_backward<T>(e, o_u, g_q, lane_select(e.front, w * g_depth, zero), g_o, p.w);
    }
    p.o[0] = g_o.x; p.o[1] = g_o.y; p.o[2] = g_o.z;
}

}  // namespace geer
