// Per-block orchestration of the render kernels (csrc/render.cu), shared with the CPU build
// (csrc/cpu_render*.cpp) so that the code deciding which ray and which Gaussian a thread touches is the code
// the CPU tests run: the ray a thread owns, the batches a tile's list is walked in (front to back in the
// forward, back to front from the block's last blended Gaussian in the backward), the list position of
// each batch item, and the warp reductions (the backward's reduce-scatter: its stages, summation order and
// output slots; the one tree of absgrad's sums and max_weight's maxima; absgrad's per-lane values).
#pragma once

#include "geer_ray.h"

namespace geer {

constexpr int kWarp = 32;

// Gaussians per shared-memory batch: ~30 KB of frames for either precision.
template <typename T> struct Batch { static constexpr int value = sizeof(T) == 4 ? 256 : 128; };

GEER_HD int tiles_along(int pixels, int tile_size) { return (pixels + tile_size - 1) / tile_size; }
GEER_HD int tile_count(int height, int width, int tile_size) {
    return tiles_along(height, tile_size) * tiles_along(width, tile_size);
}
// One thread per ray of the tile, rounded up to whole warps.
GEER_HD int threads_per_tile(int tile_size) { return ((tile_size * tile_size + kWarp - 1) / kWarp) * kWarp; }

// The ray a thread owns: the tile's pixel (row-major within the tile, as raygrid._tile_ray_indices).
struct RaySlot {
    int ray;        // index into the R rays, valid when in_image
    bool in_image;  // the tile does not overhang the image here (and the thread is not warp padding)
};

GEER_HD RaySlot ray_slot(int height, int width, int tile_size, int tile, int tid) {
    const int tx = tiles_along(width, tile_size);
    const int row = (tile / tx) * tile_size + tid / tile_size;
    const int col = (tile % tx) * tile_size + tid % tile_size;
    RaySlot s;
    s.in_image = tid < tile_size * tile_size && row < height && col < width;
    s.ray = s.in_image ? row * width + col : 0;
    return s;
}

GEER_HD int warps_per_tile(int tile_size) { return threads_per_tile(tile_size) / kWarp; }
// The cull bounds of a warp (RayGrid.warp_cull_bounds [tiles * warps_per_tile, 4]): the union of its rays'.
// A list entry whose PBF they miss is skipped by the whole warp at once (warp-uniform, no divergence).
template <typename T> GEER_HD const T* warp_bounds_of(const T* warp_bounds, int tile_size, int tile, int tid) {
    return warp_bounds + 4 * (tile * warps_per_tile(tile_size) + tid / kWarp);
}

// The cull bounds of a ray (RayGrid.ray_cull_bounds [R,4]; empty for an invalid ray, which never reaches
// the cull: done in the forward, no blended prefix in the backward). Read where used, not held in registers.
template <typename T> GEER_HD const T* ray_bounds_of(const T* ray_bounds, int ray) { return ray_bounds + 4 * ray; }

// A batch of a tile's list: item k (0 <= k < size) is list entry first + step * k, at list position
// (within the tile) first + step * k - start.
struct ListBatch {
    int first, size, step;
};
GEER_HD int batch_count(int n, int batch) { return (n + batch - 1) / batch; }

// Forward: entries [start, end) front to back.
GEER_HD ListBatch forward_batch(int start, int end, int b, int batch) {
    const int first = start + b * batch;
    return ListBatch{first, g_min(batch, end - first), 1};
}
// Backward: the block's blended prefix [start, start + block_n) back to front.
GEER_HD ListBatch backward_batch(int start, int block_n, int b, int batch) {
    const int top = start + block_n - b * batch;
    return ListBatch{top - 1, g_min(batch, top - start), -1};
}
GEER_HD int batch_entry(const ListBatch& bt, int k) { return bt.first + bt.step * k; }

// ------------------------------------------------------------ the backward's warp reduction
// Per (warp, Gaussian) the backward sums 16 values over the 32 lanes (the pairs' PairGrad, zeros where a
// ray does not blend the Gaussian) into the Gaussian's row of the [N, kGradValues] gradient. Separate
// shuffle trees would take 16 x 5 shuffles and leave every total in lane 0, which then issues 16 serial
// atomics. This reduction is transposing (reduce-scatter): butterfly stages with xor masks 16, 8, 4, 2,
// 1. At mask m >= 2 a lane holds m partial sums, keeps one half (the upper one where lane & m), adds the
// partner lane ^ m's copy of that half, and sends the partner the other half; at mask 1 the two exchange
// their one value. 8 + 4 + 2 + 1 + 1 = 16 shuffles; lanes 2k and 2k + 1 end with the warp's total of value
// k (both add the same two numbers), and the even lanes issue one atomic each, in parallel, to 16
// adjacent words. The GPU exchanges with __shfl_xor_sync (render.cu); the CPU build runs all 32 lanes in
// lock-step and reads the partner's sent values (cpu_render_backward.cpp): both sum in this order.
constexpr int kGradValues = 16;  // one gradient row: K = dL/dW W^T row-major (9), o_u (3), colour (3), opacity

// A lane's values: its pair gradient, or zeros where its ray does not blend the pair (p is then not read).
template <typename T> GEER_HD void lane_grad_values(const PairGrad<T>& p, bool contrib, T* v /* kGradValues */) {
    for (int i = 0; i < 9; ++i) v[i] = contrib ? p.w[i] : T(0);
    for (int i = 0; i < 3; ++i) {
        v[9 + i] = contrib ? p.o[i] : T(0);
        v[12 + i] = contrib ? p.rgb[i] : T(0);
    }
    v[15] = contrib ? p.opacity : T(0);
}

// A stage: its xor mask, and how many values a lane sends (and keeps) there. Compile-time, so that every
// index below is a constant and the GPU keeps the values in registers.
template <int kMask> struct ScatterStage {
    static constexpr int mask = kMask;
    static constexpr int count = kMask > 1 ? kMask / 2 : 1;
    static constexpr int half = kMask / 2;  // 0 at mask 1: the one value is both kept and sent
};
static_assert(kWarp == 32, "the stages below are those of a 32-lane warp");
// The stages in order: xor masks 16, 8, 4, 2, 1.
template <typename F> GEER_HD void for_each_scatter_stage(F&& f) {
    f(ScatterStage<16>{});
    f(ScatterStage<8>{});
    f(ScatterStage<4>{});
    f(ScatterStage<2>{});
    f(ScatterStage<1>{});
}
// sent[i], i < count: the half of v the lane gives to lane ^ mask (at mask 1: its value). Both halves are
// constant indices (a pointer to either would put the GPU's values in local memory).
template <int kMask, typename T> GEER_HD void scatter_send(ScatterStage<kMask> s, const T* v, int lane, T* sent) {
    const bool upper = (lane & s.mask) != 0;
    if (upper) {
        for (int i = 0; i < s.count; ++i) sent[i] = v[i];
    } else {
        for (int i = 0; i < s.count; ++i) sent[i] = v[i + s.half];
    }
}
// v[i] = the kept half's value + what lane ^ mask sent (in place: each v[i] is read before it is written).
template <int kMask, typename T> GEER_HD void scatter_keep(ScatterStage<kMask> s, T* v, int lane, const T* received) {
    const bool upper = (lane & s.mask) != 0;
    if (upper) {
        for (int i = 0; i < s.count; ++i) v[i] = v[i + s.half] + received[i];
    } else {
        for (int i = 0; i < s.count; ++i) v[i] = v[i] + received[i];
    }
}
// After the stages the lane's v[0] is the warp's total of value scatter_value(lane); one of its two
// holders (scatter_writer) adds it to the gradient row.
GEER_HD int scatter_value(int lane) { return lane >> 1; }
GEER_HD bool scatter_writer(int lane) { return (lane & 1) == 0; }

// The tree each value of the reduce-scatter is summed along, and absgrad's 2 sums and max_weight's maxima too:
// xor masks 16, 8, 4, 2, 1, lane l < m taking lane l + m's partial at mask m. The GPU runs the latter two as a
// butterfly (render.cu warp_tree_sum, warp_max: every lane combines its value with lane ^ m's, the same two
// numbers in lanes l and l ^ m, lane 0 ends with the total); the CPU build's sparse sums combine only the
// contributing lanes' partials along it (cpu_render_backward.cpp warp_sum_sparse): both iterate these masks, so
// both give its bits (a max is exact: its order only has to be one).
template <typename F> GEER_HD void for_each_tree_mask(F&& f) {
    for (int mask = kWarp / 2; mask >= 1; mask >>= 1) f(mask);
}

// absgrad (rasterize.render's absgrad): per pair |A_n[j] . dL_p/do_u|, j = 0, 1, with A_n = -lateral_n^T W_n^T
// the Gaussian's offset rows ([6], row-major 2x3: absgrad.offset_rows), so that A_n dL_p/do_u is the pair's
// gradient w.r.t. the Gaussian's two lateral offsets. Zeros where the lane's ray does not blend the pair (p is
// then not read).
constexpr int kAbsgradValues = 2;
constexpr int kAbsgradRow = 6;  // A_n's values per Gaussian
template <typename T>
GEER_HD void lane_absgrad_values(const T* rows /* kAbsgradRow */, const PairGrad<T>& p, bool contrib,
                                 T* v /* kAbsgradValues */) {
    for (int j = 0; j < kAbsgradValues; ++j) {
        const T* a = rows + 3 * j;
        v[j] = contrib ? g_fabs(a[0] * p.o[0] + a[1] * p.o[1] + a[2] * p.o[2]) : T(0);
    }
}

}  // namespace geer
