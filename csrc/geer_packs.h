// Packs of rays for the CPU build: the per-ray functions of geer_ray.h evaluated for several rays at once
// with GCC vector types (256 bits: 8 float32 or 4 float64 lanes; AVX2 where the build enables it, two SSE
// halves or NEON otherwise). Every lane goes through the same IEEE operations in the same order as the scalar
// code (no FMA contraction, -ffp-contract=off; sqrt and division correctly rounded; exp lane by lane with the
// scalar function), so a pack gives the scalar code's bits: tests/test_cpu_backend.py compares the CPU
// build's pack path with the GPU's one-ray-per-thread path bit for bit.
//
// Include before geer_ray.h: its templates find these overloads by ordinary lookup (vector types have no
// namespace for argument-dependent lookup to search).
#pragma once
#if defined(__CUDACC__)
#error "geer_packs.h is for the CPU build"
#endif
#if defined(GEER_RAY_H)
#error "include geer_packs.h before geer_ray.h"
#endif

#include <stdint.h>

#include "geer_math.h"

namespace geer {

typedef float FloatPack __attribute__((vector_size(32)));
typedef int32_t FloatPackMask __attribute__((vector_size(32)));  // a lane comparison: -1 true, 0 false
typedef double DoublePack __attribute__((vector_size(32)));
typedef int64_t DoublePackMask __attribute__((vector_size(32)));

template <typename P, typename M, typename S, int W> struct PackLane {
    using Scalar = S;
    using Mask = M;
    using Int = M;  // per-lane integers (n_contrib) in the mask's lane width
    static constexpr int width = W;
    // x - 0 is x exactly (also -0), unlike 0 + x: the broadcast keeps every bit.
    static P splat(S x) { return x - P{}; }
    static M splat_int(int x) { return x - M{}; }
};
template <> struct Lane<FloatPack> : PackLane<FloatPack, FloatPackMask, float, 8> {};
template <> struct Lane<DoublePack> : PackLane<DoublePack, DoublePackMask, double, 4> {};

// The pack of a scalar type, and the pack's lane i.
template <typename T> struct PackOf;
template <> struct PackOf<float> { using type = FloatPack; };
template <> struct PackOf<double> { using type = DoublePack; };

inline FloatPackMask lane_not(FloatPackMask m) { return ~m; }
inline DoublePackMask lane_not(DoublePackMask m) { return ~m; }
inline FloatPack lane_select(FloatPackMask m, FloatPack a, FloatPack b) { return m ? a : b; }
inline FloatPackMask lane_select(FloatPackMask m, FloatPackMask a, FloatPackMask b) { return m ? a : b; }
inline DoublePack lane_select(DoublePackMask m, DoublePack a, DoublePack b) { return m ? a : b; }
inline DoublePackMask lane_select(DoublePackMask m, DoublePackMask a, DoublePackMask b) { return m ? a : b; }

// Bit i set where lane i is set.
template <typename M> inline uint32_t lane_bits(M m) {
    constexpr int w = sizeof(M) / sizeof(m[0]);
    uint32_t bits = 0;
    for (int i = 0; i < w; ++i) bits |= uint32_t(m[i] != 0) << i;
    return bits;
}
inline bool lane_any(FloatPackMask m) { return lane_bits(m) != 0; }
inline bool lane_any(DoublePackMask m) { return lane_bits(m) != 0; }
// The mask whose lane i is set where bit i of bits is.
template <typename M> inline M mask_of_bits(uint32_t bits) {
    constexpr int w = sizeof(M) / sizeof(M{}[0]);
    M m;
    for (int i = 0; i < w; ++i) m[i] = ((bits >> i) & 1u) ? -1 : 0;
    return m;
}

// g_rsqrt's CPU form lane by lane (1 / sqrt, both correctly rounded: the vector instructions' results).
template <typename P> inline P pack_rsqrt(P x) {
    constexpr int w = sizeof(P) / sizeof(x[0]);
    P r;
    for (int i = 0; i < w; ++i) r[i] = g_sqrt(x[i]);
    return Lane<P>::splat(1) / r;
}
inline FloatPack g_rsqrt(FloatPack x) { return pack_rsqrt(x); }
inline DoublePack g_rsqrt(DoublePack x) { return pack_rsqrt(x); }

// exp where kept, 0 elsewhere, with the scalar function (its bits), only where kept.
template <typename P, typename M> inline P pack_exp_where(M keep, P x) {
    constexpr int w = sizeof(P) / sizeof(x[0]);
    P r = P{};
    for (int i = 0; i < w; ++i)
        if (keep[i]) r[i] = g_exp_pair(x[i]);
    return r;
}
inline FloatPack exp_where(FloatPackMask keep, FloatPack x) { return pack_exp_where(keep, x); }
inline DoublePack exp_where(DoublePackMask keep, DoublePack x) { return pack_exp_where(keep, x); }

// ------------------------------------------------------------------ lane access (a scalar is a one-lane pack)
inline float lane_get(const FloatPack& v, int i) { return v[i]; }
inline double lane_get(const DoublePack& v, int i) { return v[i]; }
inline int lane_get(const FloatPackMask& v, int i) { return int(v[i]); }
inline int lane_get(const DoublePackMask& v, int i) { return int(v[i]); }
inline void lane_set(FloatPack& v, int i, float x) { v[i] = x; }
inline void lane_set(DoublePack& v, int i, double x) { v[i] = x; }
inline void lane_set(FloatPackMask& v, int i, int x) { v[i] = x; }
inline void lane_set(DoublePackMask& v, int i, int x) { v[i] = x; }
inline uint32_t lane_bits(bool m) { return m ? 1u : 0u; }
// Every lane of L as bits (bit i: lane i).
template <typename L> constexpr uint32_t all_lane_bits() {
    return Lane<L>::width == 32 ? ~0u : (uint32_t(1) << Lane<L>::width) - 1;
}
// The lanes of L whose bit is set in bits (bit i: lane i).
template <typename L> inline typename Lane<L>::Mask lanes_of_bits(uint32_t bits) {
    if constexpr (Lane<L>::width == 1) {
        return (bits & 1u) != 0;
    } else {
        return mask_of_bits<typename Lane<L>::Mask>(bits);
    }
}

}  // namespace geer
