// Stage 3 in each ray's own order (geer_order.h): render.cu's layout (one block per tile, one thread per ray, the
// tile's list in shared-memory batches, the warp cull), with each thread's pending pairs in a window of
// kGpuWindow in its own (local) memory. A pending pair is blended once the entry about to be visited has a
// release bound at or above its key (a small per-tile kernel makes the bounds first). The backward replays the
// forward's walk and adds each blended pair's 16 gradient values with one atomic each: its lanes blend different
// Gaussians at a time, so render.cu's warp reduction does not apply. The CPU build runs the same per-ray code
// (cpu_render_order.cpp; its "ray:64" is this window).
#include "geer_blocks.h"
#include "geer_launchers.h"
#include "geer_order.h"
#include "geer_render_device.cuh"

namespace geer {

namespace {

// One thread per tile: the release bounds of its list entries (geer_order.h tile_release_bounds).
template <typename T> __global__ void release_bounds_kernel(const T* lower, const int32_t* ids, const int32_t* ranges,
                                                            int n_tiles, T* bound) {
    const int tile = blockIdx.x * blockDim.x + threadIdx.x;
    if (tile >= n_tiles) return;
    tile_release_bounds(lower, ids, ranges[2 * tile], ranges[2 * tile + 1], bound + ranges[2 * tile]);
}

// The walk both passes share: entries front to back in shared-memory batches; at each, release the pending pairs
// its bound allows, then (past the warp cull and the ray's own) evaluate and take a kept pair. blend(p): the pass's.
template <typename T, int kMaxThreads, bool kOrigin, typename Heap, typename Blend>
__device__ __forceinline__ void walk_tile(const RenderArgs<T>& a, GaussFrame<T>* frames, const T* wb, int tile,
                                          const Vec3<T>& d, const Vec3<T>& o, const T* rb, bool& done, Heap& heap,
                                          const T& trans, Blend&& blend) {
    Horizon<T> horizon;
    constexpr int kBatch = Batch<T>::value;
    const int start = a.ranges[2 * tile], end = a.ranges[2 * tile + 1];
    const int n_batches = batch_count(end - start, kBatch);
    for (int b = 0; b < n_batches; ++b) {
        if (__syncthreads_count(done ? 1 : 0) == int(blockDim.x)) break;
        const ListBatch bt = forward_batch(start, end, b, kBatch);
        for (int k = threadIdx.x; k < bt.size; k += blockDim.x) load_frame(a, a.ids[batch_entry(bt, k)], frames[k]);
        __syncthreads();
        for (int k = 0; k < bt.size; ++k) {
            const int j = batch_entry(bt, k);
            if (!done && release_due(a.order_bounds + start, j - start))
                done = !release_pending(heap, a.order_bounds[j], blend);
            if (__all_sync(0xffffffffu, done)) break;
            if (!ray_meets_pbf(frames[k], wb)) continue;  // the same for every lane of the warp
            if (!may_take(done, horizon, a.order_lower[a.ids[j]]) || !ray_meets_pbf(frames[k], rb)) continue;
            const PairEval<T> e = eval_pair<T, T, kOrigin>(frames[k], d, &o);
            const T next_bound = j + 1 < end ? a.order_bounds[j + 1] : Limits<T>::inf();
            if (e.keep) done = !insert_pending(heap, horizon, trans, pending_of<T, T>(e, 0, j - start), next_bound, blend);
        }
    }
    if (!done) done = !release_pending(heap, Limits<T>::inf(), blend);
}

template <typename T, int kMaxThreads, bool kOrigin>
__global__ void __launch_bounds__(kMaxThreads)
    render_forward_ordered_kernel(const RenderArgs<T> a, const RenderOutputs<T> out) {
    __shared__ GaussFrame<T> frames[Batch<T>::value];
    __shared__ T warp_b[4 * kMaxThreads / kWarp];
    const int tile = blockIdx.x, tid = threadIdx.x;
    const ThreadRay<T, kOrigin> ray(a, tile, tid, warp_b);
    RayForward<T> st;
    ray_forward_init(st, ray.valid);
    WindowHeap<T, kGpuWindow> heap;
    const int start = a.ranges[2 * tile];
    const auto blend = [&](const Pending<T>& p) {
        const int gid = a.ids[start + p.pos];
        return blend_pending(st, p, a.rgb + 3 * gid, [&](int, T w) { atomic_max_nonneg(out.max_weight + gid, w); });
    };
    bool done = st.done;
    walk_tile<T, kMaxThreads, kOrigin>(a, frames, warp_b + 4 * (tid / kWarp), tile, ray.d, ray.o,
                                       ray_bounds_of(a.ray_bounds, ray.slot.ray), done, heap, st.trans, blend);
    store_ray(out, ray.slot, st);
}

template <typename T, int kMaxThreads, bool kDirGrad, bool kOrigin>
__global__ void __launch_bounds__(kMaxThreads)
    render_backward_ordered_kernel(const RenderArgs<T> a, const RenderGradArgs<T> g) {
    __shared__ GaussFrame<T> frames[Batch<T>::value];
    __shared__ T warp_b[4 * kMaxThreads / kWarp];
    const int tile = blockIdx.x, tid = threadIdx.x;
    const ThreadRay<T, kOrigin> ray(a, tile, tid, warp_b);
    const bool valid = ray.valid;
    const int r = ray.slot.ray;
    RayOrderBackward<T> st;
    ray_forward_init(st.fwd, valid);
    st.prefix = T(0);
    st.total = valid ? g.ray_totals[r] : T(0);
    for (int c = 0; c < 3; ++c) st.g_rgb[c] = valid ? g.g_rgb[3 * r + c] : T(0);
    st.g_depth = valid ? g.g_depth[r] : T(0);
    st.g_acc = valid ? g.g_acc[r] : T(0);
    st.g_dir = st.g_origin = Vec3<T>{T(0), T(0), T(0)};
    WindowHeap<T, kGpuWindow> heap;
    const int start = a.ranges[2 * tile];
    const auto blend = [&](const Pending<T>& p) {
        const int gid = a.ids[start + p.pos];
        GaussFrame<T> f;
        load_frame(a, gid, f);
        PairGrad<T> pg;
        if (!backward_pending<T, kDirGrad, kOrigin>(st, f, ray.d, p.pos, pg, &ray.o)) return false;
        T v[kGradValues];
        lane_grad_values(pg, true, v);
        for (int i = 0; i < kGradValues; ++i) atomicAdd(g.grads + kGradValues * gid + i, v[i]);
        if (g.absgrad_rows) {
            T av[kAbsgradValues];
            lane_absgrad_values(g.absgrad_rows + kAbsgradRow * gid, pg, true, av);
            for (int i = 0; i < kAbsgradValues; ++i) atomicAdd(g.absgrad + kAbsgradValues * gid + i, av[i]);
        }
        return true;
    };
    bool done = st.fwd.done;
    walk_tile<T, kMaxThreads, kOrigin>(a, frames, warp_b + 4 * (tid / kWarp), tile, ray.d, ray.o,
                                       ray_bounds_of(a.ray_bounds, r), done, heap, st.fwd.trans, blend);
    if constexpr (kDirGrad) {
        if (valid) store3(g.g_dirs + 3 * r, st.g_dir);
        if constexpr (kOrigin) {
            if (valid) store3(g.g_origins + 3 * r, st.g_origin);
        }
    }
}

}  // namespace

template <typename T> void launch_release_bounds(const RenderArgs<T>& a, const T* lower, T* bound, cudaStream_t stream) {
    const int n_tiles = tile_count(a.height, a.width, a.tile_size);
    if (n_tiles <= 0) return;
    release_bounds_kernel<T><<<(n_tiles + 127) / 128, 128, 0, stream>>>(lower, a.ids, a.ranges, n_tiles, bound);
    GEER_KERNEL_LAUNCH_CHECK("release_bounds_kernel");
}

template <typename T>
void launch_render_forward_ordered(const RenderArgs<T>& a, const RenderOutputs<T>& out, cudaStream_t stream) {
    const int n_tiles = tile_count(a.height, a.width, a.tile_size);
    if (n_tiles <= 0) return;
    const int threads = threads_per_tile(a.tile_size);
    using Kernel = void (*)(const RenderArgs<T>, const RenderOutputs<T>);
    const Kernel builds[2][2] = {  // [small tile][per-ray origins]
        {render_forward_ordered_kernel<T, kLargeTileThreads, false>,
         render_forward_ordered_kernel<T, kLargeTileThreads, true>},
        {render_forward_ordered_kernel<T, kSmallTileThreads, false>,
         render_forward_ordered_kernel<T, kSmallTileThreads, true>}};
    builds[threads <= kSmallTileThreads][a.origins != nullptr]<<<n_tiles, threads, 0, stream>>>(a, out);
    GEER_KERNEL_LAUNCH_CHECK("render_forward_ordered_kernel");
}

template <typename T, int kMaxThreads> struct OrderedBackwardBuilds {
    using Kernel = void (*)(const RenderArgs<T>, const RenderGradArgs<T>);
    static Kernel pick(bool dir_grad, bool origin) {
        const Kernel table[2][2] = {
            {render_backward_ordered_kernel<T, kMaxThreads, false, false>,
             render_backward_ordered_kernel<T, kMaxThreads, false, true>},
            {render_backward_ordered_kernel<T, kMaxThreads, true, false>,
             render_backward_ordered_kernel<T, kMaxThreads, true, true>}};
        return table[dir_grad][origin];
    }
};

template <typename T>
void launch_render_backward_ordered(const RenderArgs<T>& a, const RenderGradArgs<T>& g, cudaStream_t stream) {
    const int n_tiles = tile_count(a.height, a.width, a.tile_size);
    if (n_tiles <= 0) return;
    const int threads = threads_per_tile(a.tile_size);
    const bool dg = g.g_dirs != nullptr, og = a.origins != nullptr;
    const auto kernel = threads <= kSmallTileThreads ? OrderedBackwardBuilds<T, kSmallTileThreads>::pick(dg, og)
                                                     : OrderedBackwardBuilds<T, kLargeTileThreads>::pick(dg, og);
    kernel<<<n_tiles, threads, 0, stream>>>(a, g);
    GEER_KERNEL_LAUNCH_CHECK("render_backward_ordered_kernel");
}

#define GEER_INSTANTIATE(T)                                                                                     \
    template void launch_release_bounds<T>(const RenderArgs<T>&, const T*, T*, cudaStream_t);                  \
    template void launch_render_forward_ordered<T>(const RenderArgs<T>&, const RenderOutputs<T>&, cudaStream_t); \
    template void launch_render_backward_ordered<T>(const RenderArgs<T>&, const RenderGradArgs<T>&, cudaStream_t);
GEER_INSTANTIATE(float)
GEER_INSTANTIATE(double)
#undef GEER_INSTANTIATE

}  // namespace geer
