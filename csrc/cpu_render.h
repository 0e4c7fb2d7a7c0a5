// Stage 3 of the CPU build, shared by its forward (cpu_render.cpp) and backward (cpu_render_backward.cpp): the
// Gaussians' frames, the lane type a loop runs, one tile's block as render.cu launches it, and how per-entry
// slots become per-Gaussian values.
#pragma once
#include <array>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "cpu_common.h"
#include "geer_packs.h"  // before geer_ray.h (through geer_blocks.h): the pack overloads
#include "geer_blocks.h"

namespace geer_cpu {

using geer::GaussFrame;
using geer::Vec3;

template <typename T>
std::vector<GaussFrame<T>> frames(const at::Tensor& whiten, const at::Tensor& o_u, const at::Tensor& rgb,
                                  const at::Tensor& opac, const at::Tensor& pbf_pieces) {
    const int64_t n = whiten.size(0);
    TORCH_CHECK(pbf_pieces.numel() == 8 * n, "geer: pbf_pieces must be [N,8]");
    std::vector<GaussFrame<T>> f(n);
    parallel(n, kGaussGrain, [&](int64_t i) {
        geer::make_frame(ptr<T>(whiten) + 9 * i, ptr<T>(o_u) + 3 * i, ptr<T>(rgb) + 3 * i, ptr<T>(opac)[i],
                         ptr<T>(pbf_pieces) + 8 * i, f[i]);
    });
    return f;
}

// The lane type a CPU loop runs the per-ray functions on: a pack of rays (geer_packs.h), or one ray as a GPU
// thread does (kPacks false: the kernels' path, which the tests compare bit for bit). The CPU's own path uses
// packs where the build has AVX2 (cuda_backend.cpu_cflags passes -mavx2 where the CPU has it): without it
// GCC splits the 256-bit vectors into slower scalar code than one ray at a time.
template <typename T, bool kPacks> using LaneOf = std::conditional_t<kPacks, typename geer::PackOf<T>::type, T>;
#if defined(__AVX2__)
constexpr bool kCpuPacks = true;
#else
constexpr bool kCpuPacks = false;
#endif

// One tile's block as render.cu launches it: its threads' ray slots and validity, and per pack of
// Lane<L>::width consecutive threads (a warp holds whole packs) their rays' directions, origins (rolling shutter;
// empty when every ray starts at the camera centre) and cull bounds.
template <typename T, typename L> struct Block {
    static constexpr int kWidth = geer::Lane<L>::width;
    static_assert(geer::kWarp % kWidth == 0, "a warp holds whole packs");
    int threads, packs;
    std::vector<geer::RaySlot> slot;
    std::vector<uint8_t> valid;
    std::vector<Vec3<L>> dir;
    std::vector<Vec3<L>> origin;           // empty without per-ray origins
    std::vector<std::array<L, 4>> bounds;  // theta lo, hi, phi lo, hi (RayGrid.ray_cull_bounds)
    const T* warp_bounds;                  // the block's first warp's; then one row of 4 per warp

    Block(int tile, int64_t height, int64_t width, int64_t ts, const uint8_t* ray_valid, const T* dirs,
          const T* ray_bounds, const T* all_warp_bounds, const T* origins = nullptr)
        : threads(geer::threads_per_tile(int(ts))), packs(threads / kWidth), slot(threads), valid(threads),
          dir(packs), origin(origins ? packs : 0), bounds(packs),
          warp_bounds(geer::warp_bounds_of(all_warp_bounds, int(ts), tile, 0)) {
        for (int tid = 0; tid < threads; ++tid) {
            slot[tid] = geer::ray_slot(int(height), int(width), int(ts), tile, tid);
            valid[tid] = slot[tid].in_image && ray_valid[slot[tid].ray] != 0;
            const Vec3<T> d = valid[tid] ? geer::load3(dirs + 3 * slot[tid].ray) : Vec3<T>{T(0), T(0), T(0)};
            const T* rb = geer::ray_bounds_of(ray_bounds, slot[tid].ray);
            const int pk = tid / kWidth, i = tid % kWidth;
            geer::lane_set(dir[pk].x, i, d.x);
            geer::lane_set(dir[pk].y, i, d.y);
            geer::lane_set(dir[pk].z, i, d.z);
            for (int c = 0; c < 4; ++c) geer::lane_set(bounds[pk][c], i, rb[c]);
            if (!origins) continue;
            const Vec3<T> o = valid[tid] ? geer::load3(origins + 3 * slot[tid].ray) : Vec3<T>{T(0), T(0), T(0)};
            geer::lane_set(origin[pk].x, i, o.x);
            geer::lane_set(origin[pk].y, i, o.y);
            geer::lane_set(origin[pk].z, i, o.z);
        }
    }
    typename geer::Lane<L>::Mask valid_lanes(int pk) const {
        uint32_t bits = 0;
        for (int i = 0; i < kWidth; ++i) bits |= uint32_t(valid[pk * kWidth + i]) << i;
        return geer::lanes_of_bits<L>(bits);
    }
    const T* warp_bounds_of(int tid) const { return warp_bounds + 4 * (tid / geer::kWarp); }
    const Vec3<L>* origin_of(int pk) const { return origin.empty() ? nullptr : &origin[pk]; }
};

// The render stage's inputs (both passes), on the CPU and checked.
struct RenderInputs {
    at::Tensor whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges;
    int64_t height, width, tile_size;
    at::Tensor origins;  // [R,3] or empty
};
// The backward's per-ray inputs: the forward's record, dL/d(rgb, depth, acc sums), absgrad's rows (or empty),
// and for the per-ray order each ray's total V = gC . rgb + gZ depth + gA acc (geer_order.h).
struct RayGrads {
    at::Tensor blended_lanes, g_rgb, g_depth, g_acc, absgrad_rows, ray_totals;
};

// Stage 3 in each ray's own order (cpu_render_order.cpp): packs, the CPU's path (else the kernels'); recorded, the
// backward visits the forward's recorded lanes (else the kernels' path); lower [N] the Gaussians' key bounds,
// window the pending pairs a ray holds (0: as many as it needs, the exact order).
std::vector<at::Tensor> render_forward_ordered_op(bool packs, const RenderInputs& in, bool record,
                                                  const at::Tensor& lower, int64_t window);
std::vector<at::Tensor> render_backward_ordered_op(bool recorded, bool dir_grad, const RenderInputs& in,
                                                   const RayGrads& g, const at::Tensor& lower, int64_t window);

// Per-ray origins [R,3] of the Gaussians' dtype, or empty (every ray from the camera centre).
inline bool check_origins(const at::Tensor& origins, const at::Tensor& like, int64_t rays) {
    if (origins.numel() == 0) return false;
    TORCH_CHECK(origins.scalar_type() == like.scalar_type() && origins.numel() == 3 * rays,
                "geer: origins must be [R,3] of the Gaussians' dtype, or empty");
    return true;
}

// The render stage's per-ray and per-warp cull bounds fit the grid (both passes).
inline void check_cull_bounds(const at::Tensor& ray_bounds, const at::Tensor& warp_bounds, int64_t height,
                              int64_t width, int64_t tile_size) {
    TORCH_CHECK(ray_bounds.numel() == 4 * height * width, "geer: ray_bounds must be [R,4]");
    TORCH_CHECK(warp_bounds.numel() == 4 * geer::tile_count(int(height), int(width), int(tile_size)) *
                                           geer::warps_per_tile(int(tile_size)),
                "geer: warp_bounds must be [tiles * warps per tile, 4]");
}

// Per-Gaussian values from per-entry slots. The tiles run on any thread, so each pass writes one slot per list
// entry (a tile's entries are its own); then each Gaussian folds its entries' slots in list order: the same
// order, so the same bits, whatever the threads did (the kernels' atomics instead).
struct EntriesOfGaussians {
    std::vector<int64_t> start;    // [N + 1]: Gaussian g's entries are entries[start[g] .. start[g + 1])
    std::vector<int64_t> entries;  // [M] list entries grouped by Gaussian, each group in list order
};

inline EntriesOfGaussians entries_of_gaussians(const int32_t* id, int64_t m, int64_t n) {
    EntriesOfGaussians e{std::vector<int64_t>(n + 1, 0), std::vector<int64_t>(m)};
    for (int64_t j = 0; j < m; ++j) ++e.start[id[j] + 1];
    for (int64_t i = 0; i < n; ++i) e.start[i + 1] += e.start[i];
    std::vector<int64_t> fill(e.start.begin(), e.start.end() - 1);
    for (int64_t j = 0; j < m; ++j) e.entries[fill[id[j]]++] = j;
    return e;
}

// out [N, width] = op-fold, from out's values, of each Gaussian's slots [M, width] in list order.
template <typename T, typename Op>
void fold_entries(const EntriesOfGaussians& e, int width, const T* slots, T* out, Op&& op) {
    parallel(int64_t(e.start.size()) - 1, kGaussGrain, [&](int64_t g) {
        T* row = out + int64_t(width) * g;
        for (int64_t q = e.start[g]; q < e.start[g + 1]; ++q) {
            const T* slot = slots + int64_t(width) * e.entries[q];
            for (int v = 0; v < width; ++v) row[v] = op(row[v], slot[v]);
        }
    });
}

}  // namespace geer_cpu
