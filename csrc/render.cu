// Stage 3, per tile (camera sub-frustum) and ray: exact ray-Gaussian response and blending.
//
// Forward: one block per tile, one thread per ray (block size rounded up to whole warps). The rays of
// a tile share its front-to-back Gaussian list; the block loads it in batches into shared memory
// (each Gaussian's ray frame is built once per tile there), every thread blends the batch into its
// ray, a warp stops once all of its rays are done and the block once all of its warps are (3DGS early
// termination). Each entry a warp blends gets the warp's largest weight, one atomicMax (max_weight).
// Backward: same layout, the list traversed back to front from the block's last blended Gaussian;
// per-pair gradients of (W, o_u, colour, opacity), 16 values, are summed over the warp by a transposing
// reduction (16 shuffles; geer_blocks.h) that leaves value k's total in lanes 2k and 2k + 1, so 16 lanes
// add them to the Gaussian's gradient row with one atomic each, in parallel. With absgrad, a separate
// build (kAbsgrad: the default build's registers stay as they are) also sums the pairs' 2 absgrad values.
// Per-pair and per-ray math: geer_ray.h (eval_pair, ray_forward_step, ray_backward_step); which ray and
// which list entry a thread touches: geer_blocks.h (shared with the CPU build, so the CPU tests run it).
#include "geer_blocks.h"
#include "geer_launchers.h"
#include "geer_math.h"
#include "geer_ray.h"
#include "geer_render_device.cuh"

namespace geer {

// kMaxThreads: the largest block this build is launched with (kSmallTileThreads or kLargeTileThreads).
// The warp's largest x (geer_blocks.h's tree; a max is exact, so any order gives its bits).
template <typename T> __device__ __forceinline__ T warp_max(T x) {
    for_each_tree_mask([&](int mask) { x = g_max(x, __shfl_xor_sync(0xffffffffu, x, mask)); });
    return x;
}

// kOrigin: every ray from its own origin (a.origins: rolling shutter), a build of its own (registers).
template <typename T, int kMaxThreads, bool kOrigin>
__global__ void __launch_bounds__(kMaxThreads) render_forward_kernel(const RenderArgs<T> a, const RenderOutputs<T> out) {
    constexpr int kBatch = Batch<T>::value;
    __shared__ GaussFrame<T> frames[kBatch];
    __shared__ T warp_b[4 * kMaxThreads / kWarp];
    const int tile = blockIdx.x;
    const int tid = threadIdx.x;
    const RaySlot slot = ray_slot(a.height, a.width, a.tile_size, tile, tid);
    const bool valid = slot.in_image && a.valid[slot.ray] != 0;
    const Vec3<T> d = valid ? load3(a.dirs + 3 * slot.ray) : Vec3<T>{T(0), T(0), T(0)};
    Vec3<T> o{T(0), T(0), T(0)};
    if constexpr (kOrigin) o = valid ? load3(a.origins + 3 * slot.ray) : o;
    const T* rb = ray_bounds_of(a.ray_bounds, slot.ray);
    const int lane = tid % kWarp;
    if (lane < 4) warp_b[4 * (tid / kWarp) + lane] = warp_bounds_of(a.warp_bounds, a.tile_size, tile, tid)[lane];
    const T* wb = warp_b + 4 * (tid / kWarp);  // read after the loop's first barrier
    RayForward<T> st;
    ray_forward_init(st, valid);

    const int start = a.ranges[2 * tile], end = a.ranges[2 * tile + 1];
    const int n_batches = batch_count(end - start, kBatch);
    for (int b = 0; b < n_batches; ++b) {
        // Also the barrier that keeps the previous batch alive until every thread has used it.
        if (__syncthreads_count(st.done ? 1 : 0) == int(blockDim.x)) break;
        const ListBatch bt = forward_batch(start, end, b, kBatch);
        for (int k = tid; k < bt.size; k += blockDim.x) load_frame(a, a.ids[batch_entry(bt, k)], frames[k]);
        __syncthreads();
        // Warp-uniform: the warp's maximum below needs all 32 lanes (a done lane's step blends nothing).
        for (int k = 0; k < bt.size; ++k) {
            if (__all_sync(0xffffffffu, st.done)) break;
            if (!ray_meets_pbf(frames[k], wb)) continue;  // the same for every lane of the warp
            const T w = ray_forward_step<T, T, kOrigin>(st, frames[k], d, rb, batch_entry(bt, k) - start, &o);
            if (!__any_sync(0xffffffffu, w > T(0))) continue;
            const T top = warp_max(w);
            // The id from global memory, by lane 0 only: a shared copy of the batch's ids costs registers.
            if (lane == 0) atomic_max_nonneg(out.max_weight + a.ids[batch_entry(bt, k)], top);
        }
    }
    store_ray(out, slot, st);
}

// The warp's totals of the lanes' values (geer_blocks.h): lane ends with value scatter_value(lane)'s in v[0].
template <typename T> __device__ __forceinline__ void warp_reduce_scatter(T* v, int lane) {
    for_each_scatter_stage([&](auto stage) {
        T sent[stage.count];
        scatter_send(stage, v, lane, sent);
        for (int i = 0; i < stage.count; ++i) sent[i] = __shfl_xor_sync(0xffffffffu, sent[i], stage.mask);
        scatter_keep(stage, v, lane, sent);
    });
}

// The warp's totals of kCount values along geer_blocks.h's tree (a butterfly: lane 0 ends with them).
template <int kCount, typename T> __device__ __forceinline__ void warp_tree_sum(T* v) {
    for_each_tree_mask([&](int mask) {
        for (int i = 0; i < kCount; ++i) v[i] += __shfl_xor_sync(0xffffffffu, v[i], mask);
    });
}

// kAbsgrad: also sum each pair's absgrad values (g.absgrad_rows, g.absgrad); kDirGrad: also each ray's
// dL/d(direction) (g.g_dirs, one thread per ray: no atomics); kOrigin: every ray from its own origin
// (a.origins), with kDirGrad also its dL/d(origin) (g.g_origins); builds of their own, so that the default one
// keeps its registers.
template <typename T, int kMaxThreads, bool kAbsgrad, bool kDirGrad, bool kOrigin>
__global__ void __launch_bounds__(kMaxThreads) render_backward_kernel(const RenderArgs<T> a, const RenderGradArgs<T> g) {
    constexpr int kBatch = Batch<T>::value;
    __shared__ GaussFrame<T> frames[kBatch];
    __shared__ int frame_ids[kBatch];
    __shared__ T warp_b[4 * kMaxThreads / kWarp];
    __shared__ int block_n;
    const int tile = blockIdx.x;
    const int tid = threadIdx.x;
    const int lane = tid & 31;
    const RaySlot slot = ray_slot(a.height, a.width, a.tile_size, tile, tid);
    const bool valid = slot.in_image && a.valid[slot.ray] != 0;
    const int r = slot.ray;
    const Vec3<T> d = valid ? load3(a.dirs + 3 * r) : Vec3<T>{T(0), T(0), T(0)};
    Vec3<T> o{T(0), T(0), T(0)};
    if constexpr (kOrigin) o = valid ? load3(a.origins + 3 * r) : o;
    if (lane < 4) warp_b[4 * (tid / kWarp) + lane] = warp_bounds_of(a.warp_bounds, a.tile_size, tile, tid)[lane];
    const T* wb = warp_b + 4 * (tid / kWarp);  // read after the barriers below
    const int my_n = valid ? g.n_contrib[r] : 0;
    RayBackward<T> st;
    st.trans = valid ? g.t_final[r] : T(1);
    st.rec = T(0);
    for (int c = 0; c < 3; ++c) st.g_rgb[c] = valid ? g.g_rgb[3 * r + c] : T(0);
    st.g_depth = valid ? g.g_depth[r] : T(0);
    st.g_acc = valid ? g.g_acc[r] : T(0);
    if constexpr (kDirGrad) st.g_dir = st.g_origin = Vec3<T>{T(0), T(0), T(0)};

    // Nothing after the block's last blended Gaussian needs a visit.
    if (tid == 0) block_n = 0;
    __syncthreads();
    if (my_n > 0) atomicMax(&block_n, my_n);
    __syncthreads();
    const int start = a.ranges[2 * tile];
    const int n_batches = batch_count(block_n, kBatch);

    for (int b = 0; b < n_batches; ++b) {
        const ListBatch bt = backward_batch(start, block_n, b, kBatch);
        __syncthreads();  // the previous batch is no longer read
        for (int k = tid; k < bt.size; k += blockDim.x) {
            const int gid = a.ids[batch_entry(bt, k)];
            frame_ids[k] = gid;
            load_frame(a, gid, frames[k]);
        }
        __syncthreads();
        for (int k = 0; k < bt.size; ++k) {
            if (!ray_meets_pbf(frames[k], wb)) continue;  // the same for every lane of the warp
            const int pos = batch_entry(bt, k) - start;  // list position within the tile
            PairGrad<T> p;
            const bool contrib = ray_backward_step<T, T, kDirGrad, kOrigin>(st, frames[k], d, pos < my_n, p, &o);
            if (!__any_sync(0xffffffffu, contrib)) continue;
            if constexpr (kAbsgrad) {  // before the 16 values are reduced, while they are still p
                T av[kAbsgradValues];
                lane_absgrad_values(g.absgrad_rows + kAbsgradRow * frame_ids[k], p, contrib, av);
                warp_tree_sum<kAbsgradValues>(av);
                T* out = g.absgrad + kAbsgradValues * frame_ids[k];
                if (lane == 0)
                    for (int j = 0; j < kAbsgradValues; ++j) atomicAdd(out + j, av[j]);
            }
            T v[kGradValues];
            lane_grad_values(p, contrib, v);
            warp_reduce_scatter(v, lane);
            if (scatter_writer(lane)) atomicAdd(g.grads + kGradValues * frame_ids[k] + scatter_value(lane), v[0]);
        }
    }
    if constexpr (kDirGrad) {
        if (valid) store3(g.g_dirs + 3 * r, st.g_dir);
        if constexpr (kOrigin) {
            if (valid) store3(g.g_origins + 3 * r, st.g_origin);
        }
    }
}

template <typename T>
void launch_render_forward(const RenderArgs<T>& a, const RenderOutputs<T>& out, cudaStream_t stream) {
    const int n_tiles = tile_count(a.height, a.width, a.tile_size);
    if (n_tiles <= 0) return;
    const int threads = threads_per_tile(a.tile_size);
    using Kernel = void (*)(const RenderArgs<T>, const RenderOutputs<T>);
    const Kernel builds[2][2] = {  // [small tile][per-ray origins]
        {render_forward_kernel<T, kLargeTileThreads, false>, render_forward_kernel<T, kLargeTileThreads, true>},
        {render_forward_kernel<T, kSmallTileThreads, false>, render_forward_kernel<T, kSmallTileThreads, true>}};
    builds[threads <= kSmallTileThreads][a.origins != nullptr]<<<n_tiles, threads, 0, stream>>>(a, out);
    GEER_KERNEL_LAUNCH_CHECK("render_forward_kernel");
}

// The backward's builds of one block size, indexed [absgrad][direction gradients][per-ray origins].
template <typename T, int kMaxThreads> struct BackwardBuilds {
    using Kernel = void (*)(const RenderArgs<T>, const RenderGradArgs<T>);
    template <bool kAbsgrad, bool kDirGrad, bool kOrigin>
    static constexpr Kernel k = render_backward_kernel<T, kMaxThreads, kAbsgrad, kDirGrad, kOrigin>;
    static Kernel pick(bool absgrad, bool dir_grad, bool origin) {
        const Kernel table[2][2][2] = {{{k<false, false, false>, k<false, false, true>},
                                        {k<false, true, false>, k<false, true, true>}},
                                       {{k<true, false, false>, k<true, false, true>},
                                        {k<true, true, false>, k<true, true, true>}}};
        return table[absgrad][dir_grad][origin];
    }
};

template <typename T>
void launch_render_backward(const RenderArgs<T>& a, const RenderGradArgs<T>& g, cudaStream_t stream) {
    const int n_tiles = tile_count(a.height, a.width, a.tile_size);
    if (n_tiles <= 0) return;
    const int threads = threads_per_tile(a.tile_size);
    const bool ag = g.absgrad != nullptr, dg = g.g_dirs != nullptr, og = a.origins != nullptr;
    const auto kernel = threads <= kSmallTileThreads ? BackwardBuilds<T, kSmallTileThreads>::pick(ag, dg, og)
                                                     : BackwardBuilds<T, kLargeTileThreads>::pick(ag, dg, og);
    kernel<<<n_tiles, threads, 0, stream>>>(a, g);
    GEER_KERNEL_LAUNCH_CHECK("render_backward_kernel");
}

template void launch_render_forward<float>(const RenderArgs<float>&, const RenderOutputs<float>&, cudaStream_t);
template void launch_render_forward<double>(const RenderArgs<double>&, const RenderOutputs<double>&, cudaStream_t);
template void launch_render_backward<float>(const RenderArgs<float>&, const RenderGradArgs<float>&, cudaStream_t);
template void launch_render_backward<double>(const RenderArgs<double>&, const RenderGradArgs<double>&, cudaStream_t);

}  // namespace geer
