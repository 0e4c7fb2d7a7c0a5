// Stage 2, PBF x CSF association (paper Sec. 3.2, App. D.2, Alg. 1 DuplicateWithKeys / SortByKeys /
// IdentifyFrustumRanges), O(N log T + pairs) on every ray grid (geer_associate.h):
//   count   each Gaussian searches the tile pyramid for the active tiles its PBF overlaps, counting them
//           and recording their tile box;
//   emit    after an exclusive scan of the counts, each Gaussian writes one (key, id) per tile of its box
//           that is hit, with key = tile << 32 | depth order;
//   sort    one stable radix sort by key gives every tile's list, front to back (ties by index: exactly
//           associate.py's lists);
//   ranges  each tile's [start, end) in the sorted pairs.
#include <cub/cub.cuh>

#include "geer_associate.h"
#include "geer_launchers.h"

namespace geer {

template <typename T> __device__ __forceinline__ PyramidNodes<T> pyramid_nodes(const AssociateArgs<T>& a) {
    return PyramidNodes<T>{a.node_bounds, a.node_active, a.tile_cones};
}

template <typename T> __device__ __forceinline__ const T* gauss_cone(const AssociateArgs<T>& a, int i) {
    return a.gauss_cones ? a.gauss_cones + kGaussConeValues * i : nullptr;
}

template <typename T>
__global__ void __launch_bounds__(kThreads) count_tiles_kernel(const AssociateArgs<T> a, int32_t* counts, uint64_t* boxes, int32_t* tests) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.n) return;
    const TilePyramid pyr = make_tile_pyramid(a.tiles_x, a.tiles_y);
    TileBox box;
    int n_tests;
    counts[i] = count_overlapping_tiles(a.bounds + 4 * i, gauss_cone(a, i), a.alive[i] != 0, pyr, pyramid_nodes(a), &n_tests, &box);
    boxes[i] = pack_box(box);
    tests[i] = n_tests;
}

template <typename T>
__global__ void __launch_bounds__(kThreads) emit_pairs_kernel(const AssociateArgs<T> a, const uint64_t* boxes, const int64_t* offsets,
                                                                uint64_t* keys, int32_t* ids, int32_t* tests) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.n) return;
    int64_t out = offsets[i];
    const uint32_t order = uint32_t(a.order[i]);
    tests[i] += emit_overlapping_tiles(a.bounds + 4 * i, gauss_cone(a, i), unpack_box(boxes[i]), a.tiles_x, pyramid_nodes(a),
                                       [&](int tile) {
                                           keys[out] = pair_key(tile, order);
                                           ids[out] = i;
                                           ++out;
                                       });
}

// A tile's list starts where the tile id changes and ends where the next one starts.
__global__ void __launch_bounds__(kThreads) tile_ranges_kernel(const uint64_t* keys, int64_t m, int32_t* ranges) {
    const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
    if (i >= m) return;
    mark_tile_range(keys, m, i, ranges);
}

static int blocks_for(int64_t n, int threads) { return int((n + threads - 1) / threads); }

template <typename T>
void launch_count_tiles(const AssociateArgs<T>& a, int32_t* counts, uint64_t* boxes, int32_t* tests,
                        cudaStream_t stream) {
    if (a.n <= 0) return;
    count_tiles_kernel<T><<<blocks_for(a.n, kThreads), kThreads, 0, stream>>>(a, counts, boxes, tests);
    GEER_KERNEL_LAUNCH_CHECK("count_tiles_kernel");
}

template <typename T>
void launch_emit_pairs(const AssociateArgs<T>& a, const uint64_t* boxes, const int64_t* offsets, uint64_t* keys,
                       int32_t* ids, int32_t* tests, cudaStream_t stream) {
    if (a.n <= 0) return;
    emit_pairs_kernel<T><<<blocks_for(a.n, kThreads), kThreads, 0, stream>>>(a, boxes, offsets, keys, ids, tests);
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

template void launch_count_tiles<float>(const AssociateArgs<float>&, int32_t*, uint64_t*, int32_t*, cudaStream_t);
template void launch_count_tiles<double>(const AssociateArgs<double>&, int32_t*, uint64_t*, int32_t*, cudaStream_t);
template void launch_emit_pairs<float>(const AssociateArgs<float>&, const uint64_t*, const int64_t*, uint64_t*,
                                       int32_t*, int32_t*, cudaStream_t);
template void launch_emit_pairs<double>(const AssociateArgs<double>&, const uint64_t*, const int64_t*, uint64_t*,
                                        int32_t*, int32_t*, cudaStream_t);

}  // namespace geer
