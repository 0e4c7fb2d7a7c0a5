// Stage 2, PBF x CSF association (paper Sec. 3.2, App. D.2, Alg. 1 DuplicateWithKeys / SortByKeys /
// IdentifyFrustumRanges):
//   count   each Gaussian counts the active tiles its PBF overlaps (rectangles found by binary search
//           on separable BEAP grids, every tile tested on arbitrary per-pixel grids: O(N T));
//   emit    after an exclusive scan of the counts, each Gaussian writes one (key, id) per tile with
//           key = tile << 32 | front-to-back rank;
//   sort    one radix sort by key gives every tile's list, front to back (ranks are the twin's
//           stable depth order, so the lists are exactly associate.py's);
//   ranges  each tile's [start, end) in the sorted pairs.
#include <cub/cub.cuh>

#include "geer_launchers.h"
#include "geer_math.h"

namespace geer {

template <typename T> __device__ __forceinline__ TileGrid<T> tile_grid(const AssociateArgs<T>& a) {
    TileGrid<T> g;
    g.tile_bounds = a.tile_bounds;
    g.active = a.active;
    g.n_tiles = a.n_tiles;
    g.tiles_x = a.tiles_x;
    g.tiles_y = a.tiles_y;
    g.separable = a.separable != 0;
    g.col_bounds = a.col_bounds;
    g.row_bounds = a.row_bounds;
    return g;
}

template <typename T> __global__ void __launch_bounds__(kThreads) count_tiles_kernel(const AssociateArgs<T> a, int32_t* counts) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.n) return;
    counts[i] = for_each_overlapping_tile(a.bounds + 4 * i, a.alive[i] != 0, tile_grid(a), [](int) {});
}

template <typename T>
__global__ void __launch_bounds__(kThreads) emit_pairs_kernel(const AssociateArgs<T> a, const int64_t* offsets, uint64_t* keys, int32_t* ids) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.n) return;
    int64_t out = offsets[i];
    const int rank = a.rank[i];
    for_each_overlapping_tile(a.bounds + 4 * i, a.alive[i] != 0, tile_grid(a), [&](int tile) {
        keys[out] = pair_key(tile, rank);
        ids[out] = i;
        ++out;
    });
}

// A tile's list starts where the tile id changes and ends where the next one starts.
__global__ void __launch_bounds__(kThreads) tile_ranges_kernel(const uint64_t* keys, int64_t m, int32_t* ranges) {
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= m) return;
    const uint32_t tile = uint32_t(keys[i] >> 32);
    if (i == 0 || uint32_t(keys[i - 1] >> 32) != tile) ranges[2 * tile] = int32_t(i);
    if (i == m - 1 || uint32_t(keys[i + 1] >> 32) != tile) ranges[2 * tile + 1] = int32_t(i + 1);
}

static int blocks_for(int64_t n, int threads) { return int((n + threads - 1) / threads); }

template <typename T> void launch_count_tiles(const AssociateArgs<T>& a, int32_t* counts, cudaStream_t stream) {
    if (a.n <= 0) return;
    count_tiles_kernel<T><<<blocks_for(a.n, kThreads), kThreads, 0, stream>>>(a, counts);
    GEER_KERNEL_LAUNCH_CHECK("count_tiles_kernel");
}

template <typename T>
void launch_emit_pairs(const AssociateArgs<T>& a, const int64_t* offsets, uint64_t* keys, int32_t* ids,
                       cudaStream_t stream) {
    if (a.n <= 0) return;
    emit_pairs_kernel<T><<<blocks_for(a.n, kThreads), kThreads, 0, stream>>>(a, offsets, keys, ids);
    GEER_KERNEL_LAUNCH_CHECK("emit_pairs_kernel");
}

size_t sort_pairs_temp_bytes(int64_t m, int end_bit) {
    size_t bytes = 0;
    GEER_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, bytes, static_cast<const uint64_t*>(nullptr),
                                                    static_cast<uint64_t*>(nullptr),
                                                    static_cast<const int32_t*>(nullptr),
                                                    static_cast<int32_t*>(nullptr), m, 0, end_bit),
                    "cub::DeviceRadixSort::SortPairs (temp size)");
    return bytes;
}

void sort_pairs(void* temp, size_t temp_bytes, const uint64_t* keys_in, uint64_t* keys_out, const int32_t* ids_in,
                int32_t* ids_out, int64_t m, int end_bit, cudaStream_t stream) {
    if (m <= 0) return;
    GEER_CUDA_CHECK(
        cub::DeviceRadixSort::SortPairs(temp, temp_bytes, keys_in, keys_out, ids_in, ids_out, m, 0, end_bit, stream),
        "cub::DeviceRadixSort::SortPairs");
}

void launch_tile_ranges(const uint64_t* sorted_keys, int64_t m, int32_t* ranges, cudaStream_t stream) {
    if (m <= 0) return;
    tile_ranges_kernel<<<blocks_for(m, kThreads), kThreads, 0, stream>>>(sorted_keys, m, ranges);
    GEER_KERNEL_LAUNCH_CHECK("tile_ranges_kernel");
}

template void launch_count_tiles<float>(const AssociateArgs<float>&, int32_t*, cudaStream_t);
template void launch_count_tiles<double>(const AssociateArgs<double>&, int32_t*, cudaStream_t);
template void launch_emit_pairs<float>(const AssociateArgs<float>&, const int64_t*, uint64_t*, int32_t*, cudaStream_t);
template void launch_emit_pairs<double>(const AssociateArgs<double>&, const int64_t*, uint64_t*, int32_t*,
                                        cudaStream_t);

}  // namespace geer
