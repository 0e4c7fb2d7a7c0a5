// Host-side entry points of the 3DGEER CUDA stages: plain structs of raw device pointers, one
// launcher per stage, explicitly instantiated for float and double in the .cu files. No torch here:
// bindings.cpp allocates the tensors and fills these structs; the .cu files build with plain nvcc.
//
// Layouts (all contiguous, row-major): N Gaussians, T tiles, R = height * width rays, M pairs.
//
// Every kernel declares its largest block with __launch_bounds__ (so ptxas fits its registers to that
// block, and tests/test_csrc_compile.py can check registers x block <= 65,536 from the build), and every
// launch and CUB call is checked where it happens: a failure throws std::runtime_error (a RuntimeError in
// Python) naming the kernel, instead of leaving uninitialised outputs for a later, unrelated op to trip on.
#pragma once

#include <cuda_runtime_api.h>
#include <stddef.h>
#include <stdint.h>

#include <stdexcept>
#include <string>

namespace geer {

// Threads per block of the per-Gaussian / per-pair kernels.
constexpr int kThreads = 256;
// Render kernels, one thread per ray of a tile: tiles up to 16 x 16 (the default) launch a build bounded at
// 256 threads, with all the registers it wants; larger tiles (up to 32 x 32, the bindings' limit) a build
// bounded at 1024 threads, which ptxas fits into 64 registers (float64 spills a little there).
constexpr int kSmallTileThreads = 256;
constexpr int kLargeTileThreads = 1024;

inline void check_cuda(cudaError_t err, const char* what, const char* file, int line) {
    if (err == cudaSuccess) return;
    throw std::runtime_error(std::string("geer: ") + what + " failed: " + cudaGetErrorName(err) + ": " +
                             cudaGetErrorString(err) + " (" + file + ":" + std::to_string(line) + ")");
}
// After every <<<...>>>: launch errors (bad configuration, too many resources) raise at their own call.
// cudaGetLastError also clears them, so the next operation does not inherit this one's error.
#define GEER_KERNEL_LAUNCH_CHECK(kernel) ::geer::check_cuda(cudaGetLastError(), "launch of " kernel, __FILE__, __LINE__)
// Around every call that returns a cudaError_t (CUB).
#define GEER_CUDA_CHECK(call, what) ::geer::check_cuda((call), what, __FILE__, __LINE__)

// A trivial kernel launched with `threads` per block (tests: a block over 1024 threads must raise at this call).
void launch_probe(int threads, int32_t* out, cudaStream_t stream);

// ------------------------------------------------------------------ stage 1: preprocess (per Gaussian)
template <typename T> struct PreprocessArgs {
    int n;
    const T* means_c;    // [N,3] view-space means
    const T* quats;      // [N,4] wxyz, any norm
    const T* scales;     // [N,3]
    const T* opacities;  // [N]
    const T* sh;         // [N,K,3] SH coefficients (null when sh_degree < 0: colours are given as RGB)
    int sh_k;            // K
    int sh_degree;       // active degree, -1 for RGB colours
    const uint8_t* sh_degrees;  // [N] each Gaussian's own degree, capping sh_degree (null: none)
    const T* sh_dirs;    // [N,3] SH view directions: mean - camera centre in world axes, unnormalised, rounded
                         // from float64 by the caller (transforms.camera_offsets: exact far from the origin)
    // Per-view constant, read in place on the device (every thread reads the same 9 values, a broadcast):
    // copying it to the host first would be a device-to-host sync in every forward and backward.
    const T* rot_c;      // [9] world-to-camera rotation (viewmat[:3,:3]), row-major
    int paper_lambda;    // 1: lambda = 3 (paper); 0: opacity-aware lambda^2 = 2 ln(255 sigma)
    // outputs
    T* whiten;           // [N,9]
    T* o_u;              // [N,3]
    T* rgb;              // [N,3] (untouched when sh_degree < 0)
    T* bounds;           // [N,4] theta_lo, theta_hi, phi_lo, phi_hi
    uint8_t* alive;      // [N]
    uint8_t* inside;     // [N]
};
template <typename T> void launch_preprocess_forward(const PreprocessArgs<T>& a, cudaStream_t stream);

// ------------------------------------------------------------------ stage 2: association (per tile)
template <typename T> struct AssociateArgs {
    int n;
    const T* bounds;          // [N,4] PBF bounds (unwrapped angles)
    const uint8_t* alive;     // [N]
    const int32_t* order;     // [N] depth order key: float32 depth bits, or rank for float64 (geer_associate.h)
    const T* node_bounds;     // [nodes,4] tile pyramid (raygrid.RayGrid.tile_pyramid), level 0 = the tiles
    const uint8_t* node_active;  // [nodes]
    const T* gauss_cones;     // [N,9] cones.gaussian_cone_form, or null: the box test alone
    const T* tile_cones;      // [tiles,10] cones.tile_cones, or null
    int tiles_x, tiles_y;
};
// Pass 1: tiles each Gaussian overlaps -> counts [N], their tile box boxes [N] (packed), tile tests [N].
template <typename T>
void launch_count_tiles(const AssociateArgs<T>& a, int32_t* counts, uint64_t* boxes, int32_t* tests,
                        cudaStream_t stream);
// Pass 2: with offsets [N] (exclusive scan of counts), write keys (tile << 32 | order) and Gaussian ids,
// visiting each Gaussian's box only; adds the emit pass's tile tests to tests [N].
template <typename T>
void launch_emit_pairs(const AssociateArgs<T>& a, const uint64_t* boxes, const int64_t* offsets, uint64_t* keys,
                       int32_t* ids, int32_t* tests, cudaStream_t stream);
// Radix sort of M pairs by key (bits [0, end_bit)); temp storage size first, then the sort.
size_t sort_pairs_temp_bytes(int64_t m, int end_bit);
void sort_pairs(void* temp, size_t temp_bytes, const uint64_t* keys_in, uint64_t* keys_out, const int32_t* ids_in,
                int32_t* ids_out, int64_t m, int end_bit, cudaStream_t stream);
// Per-tile [start, end) into the sorted pairs; ranges [T,2] must be zeroed by the caller.
void launch_tile_ranges(const uint64_t* sorted_keys, int64_t m, int32_t* ranges, cudaStream_t stream);

// ------------------------------------------------------------------ stage 3: render (per tile / ray)
template <typename T> struct RenderArgs {
    int n;
    const T* whiten;         // [N,9]
    const T* o_u;            // [N,3]
    const T* rgb;            // [N,3]
    const T* opacities;      // [N]
    const T* pbf_pieces;     // [N,8] PBF pieces, mirror domain (cuda_backend.pbf_cull_pieces)
    const T* dirs;           // [R,3] unit ray directions (camera frame)
    const T* origins;        // [R,3] each ray's origin (camera frame; rolling shutter), null: the camera centre
    const T* ray_bounds;     // [R,4] each ray's cull bounds, mirror domain (RayGrid.ray_cull_bounds)
    const T* warp_bounds;    // [T * warps per tile, 4] each warp's (RayGrid.warp_cull_bounds)
    const uint8_t* valid;    // [R]
    const int32_t* ids;      // [M] Gaussian ids sorted by (tile, rank)
    const int32_t* ranges;   // [T,2]
    int height, width, tile_size;
    // [M] each list entry's release bound (geer_order.h; render_order.cu makes them), null: the per-view order
    const T* order_bounds;
    const T* order_lower;  // [N] each Gaussian's key bound (render/order.py key_lower_bounds), with order_bounds
};
template <typename T> struct RenderOutputs {
    T* rgb;           // [R,3] blended colour, no background
    T* depth;         // [R] sum of w max(t*, 0)
    T* acc;           // [R] sum of w
    T* t_final;       // [R] transmittance after the last blended Gaussian
    int32_t* n_contrib;  // [R] 1 + list position (within the tile) of the last blended Gaussian
    T* max_weight;       // [N] largest blend weight T_before alpha over the rays, zeroed by the caller: the
                         // weights are >= 0, so a max of their bits (one atomicMax per warp and entry) is theirs
    T* median;           // [R] max(t*, 0) where the transmittance crosses 0.5 (0: it never does)
};
template <typename T> void launch_render_forward(const RenderArgs<T>& a, const RenderOutputs<T>& out, cudaStream_t stream);

template <typename T> struct RenderGradArgs {
    const T* t_final;           // [R] from the forward
    const int32_t* n_contrib;   // [R]
    const T* g_rgb;             // [R,3] dL/d(rgb), dL/d(depth sum), dL/d(accumulation)
    const T* g_depth;           // [R]
    const T* g_acc;             // [R]
    // output, zeroed by the caller, accumulated with atomics: one row per Gaussian, dL/d of W row-major (9),
    // o_u (3), colour (3), opacity (geer_blocks.h kGradValues), so a warp's 16 totals go to adjacent words
    T* grads;                   // [N,16]
    // absgrad (null when off: the kernel built without it runs): A_n per Gaussian (geer_blocks.h
    // lane_absgrad_values) and the output sum_p |A_n dL_p/do_u| [N,2], zeroed by the caller, atomics
    const T* absgrad_rows;      // [N,6]
    T* absgrad;                 // [N,2]
    // dL/d(ray direction) [R,3] of every valid ray (null when off: the kernel built without it runs), written
    T* g_dirs;
    // dL/d(ray origin) [R,3] (null unless g_dirs and a.origins), written
    T* g_origins;
    // [R] each ray's gC . rgb + gZ depth + gA acc of the forward's sums (the per-ray order's backward only)
    const T* ray_totals;
};
template <typename T>
void launch_render_backward(const RenderArgs<T>& a, const RenderGradArgs<T>& g, cudaStream_t stream);

// Each ray in its own order (render_order.cu): the entries' release bounds from the Gaussians' key bounds
// lower [N] into bound [M] (then a.order_bounds), and the two passes.
template <typename T> void launch_release_bounds(const RenderArgs<T>& a, const T* lower, T* bound, cudaStream_t stream);
template <typename T>
void launch_render_forward_ordered(const RenderArgs<T>& a, const RenderOutputs<T>& out, cudaStream_t stream);
template <typename T>
void launch_render_backward_ordered(const RenderArgs<T>& a, const RenderGradArgs<T>& g, cudaStream_t stream);

// ------------------------------------------------------------------ stage 4: preprocess backward
template <typename T> struct PreprocessGradArgs {
    const T* g_whiten;   // [N,9] from the render backward
    const T* g_o_u;      // [N,3]
    const T* g_rgb;      // [N,3] (ignored when sh_degree < 0)
    // outputs (fully written)
    T* g_means_c;        // [N,3]
    T* g_quats;          // [N,4]
    T* g_scales;         // [N,3]
    T* g_sh;             // [N,K,3] (bands above the Gaussian's degree written as 0; null when sh_degree < 0)
    T* g_sh_dirs;        // [N,3] w.r.t. the SH view directions (0 when sh_degree < 1)
    T* g_rot_c;          // [N,9] each Gaussian's share of dL/d(camera rotation R_c) (null: not wanted)
};
template <typename T>
void launch_preprocess_backward(const PreprocessArgs<T>& a, const PreprocessGradArgs<T>& g, cudaStream_t stream);

}  // namespace geer
