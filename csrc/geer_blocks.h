// Per-block orchestration of the render kernels (csrc/render.cu), shared with the CPU build
// (csrc/cpu_ops.cpp) so that the code deciding which ray and which Gaussian a thread touches is the code
// the CPU tests run: the ray a thread owns, the batches a tile's list is walked in (front to back in the
// forward, back to front from the block's last blended Gaussian in the backward), the list position of
// each batch item, and the warp reduction's summation order.
#pragma once

#include "geer_math.h"

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

// The warp's sum as lane 0 sees it after a shuffle-down tree (offsets 16, 8, 4, 2, 1): the GPU passes
// a shuffle, the CPU build runs warp_tree_sum_lanes over the 32 lanes' values, in the same order.
template <typename T, typename Shfl> GEER_HD T warp_tree_sum(T v, Shfl&& shfl_down) {
    for (int off = kWarp / 2; off > 0; off >>= 1) v += shfl_down(v, off);
    return v;
}
template <typename T> GEER_HD T warp_tree_sum_lanes(T* v /* kWarp values, overwritten */) {
    for (int off = kWarp / 2; off > 0; off >>= 1)
        for (int lane = 0; lane < off; ++lane) v[lane] += v[lane + off];  // lanes >= off: not read by lane 0
    return v[0];
}

}  // namespace geer
