// Device helpers both render stages' kernels use (render.cu: the per-view order, render_order.cu: each ray's own):
// a Gaussian's frame from the preprocess outputs, the max_weight atomic, a thread's ray and its outputs.
#pragma once

#include "geer_blocks.h"
#include "geer_launchers.h"

namespace geer {

template <typename T> __device__ __forceinline__ void load_frame(const RenderArgs<T>& a, int g, GaussFrame<T>& f) {
    make_frame(a.whiten + 9 * g, a.o_u + 3 * g, a.rgb + 3 * g, a.opacities[g], a.pbf_pieces + 8 * g, f);
}

// *a = max(*a, x) for x >= 0: non-negative floats order like their bits (NaN above every number).
__device__ __forceinline__ void atomic_max_nonneg(float* a, float x) {
    atomicMax(reinterpret_cast<unsigned int*>(a), __float_as_uint(x));
}
__device__ __forceinline__ void atomic_max_nonneg(double* a, double x) {
    atomicMax(reinterpret_cast<unsigned long long*>(a), static_cast<unsigned long long>(__double_as_longlong(x)));
}

// A thread's ray: its slot, whether it is valid, its direction and (kOrigin) origin; lanes 0-3 of each warp copy
// the warp's cull bounds into warp_b (read after the caller's next barrier).
template <typename T, bool kOrigin> struct ThreadRay {
    RaySlot slot;
    bool valid;
    Vec3<T> d;
    Vec3<T> o{T(0), T(0), T(0)};
    __device__ ThreadRay(const RenderArgs<T>& a, int tile, int tid, T* warp_b) {
        slot = ray_slot(a.height, a.width, a.tile_size, tile, tid);
        valid = slot.in_image && a.valid[slot.ray] != 0;
        d = valid ? load3(a.dirs + 3 * slot.ray) : Vec3<T>{T(0), T(0), T(0)};
        if constexpr (kOrigin) o = valid ? load3(a.origins + 3 * slot.ray) : o;
        const int lane = tid % kWarp;
        if (lane < 4) warp_b[4 * (tid / kWarp) + lane] = warp_bounds_of(a.warp_bounds, a.tile_size, tile, tid)[lane];
    }
};

// A ray's forward outputs (nothing for a thread off the image).
template <typename T> __device__ __forceinline__ void store_ray(const RenderOutputs<T>& out, const RaySlot& slot,
                                                               const RayForward<T>& st) {
    if (!slot.in_image) return;
    const int r = slot.ray;
    for (int c = 0; c < 3; ++c) out.rgb[3 * r + c] = st.rgb[c];
    out.depth[r] = st.depth;
    out.acc[r] = st.acc;
    out.t_final[r] = st.trans;
    out.n_contrib[r] = st.n_contrib;
    out.median[r] = st.median;
}

}  // namespace geer
