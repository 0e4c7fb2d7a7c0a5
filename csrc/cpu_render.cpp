// Stage 3 of the CPU build (cpu_ops.cpp has the rest and the module): render forward and backward over
// geer_ray.h's per-ray functions and geer_blocks.h's per-block orchestration, in packs of rays where the build
// has AVX2 (geer_packs.h) and one ray per thread as the kernels (the *_gpu_path operations); the warp
// reduction's lock-step and sparse forms; the single-pair probes of the tests.
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <array>
#include <type_traits>
#include <vector>

#include "cpu_common.h"
#include "geer_packs.h"  // before geer_ray.h (through geer_blocks.h): the pack overloads
#include "geer_blocks.h"

namespace {

using namespace geer_cpu;
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
// Lane<L>::width consecutive threads (a warp holds whole packs) their rays' directions and cull bounds.
template <typename T, typename L> struct Block {
    static constexpr int kWidth = geer::Lane<L>::width;
    static_assert(geer::kWarp % kWidth == 0, "a warp holds whole packs");
    int threads, packs;
    std::vector<geer::RaySlot> slot;
    std::vector<uint8_t> valid;
    std::vector<Vec3<L>> dir;
    std::vector<std::array<L, 4>> bounds;  // theta lo, hi, phi lo, hi (RayGrid.ray_cull_bounds)
    const T* warp_bounds;                  // the block's first warp's; then one row of 4 per warp

    Block(int tile, int64_t height, int64_t width, int64_t ts, const uint8_t* ray_valid, const T* dirs,
          const T* ray_bounds, const T* all_warp_bounds)
        : threads(geer::threads_per_tile(int(ts))), packs(threads / kWidth), slot(threads), valid(threads),
          dir(packs), bounds(packs), warp_bounds(geer::warp_bounds_of(all_warp_bounds, int(ts), tile, 0)) {
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
        }
    }
    typename geer::Lane<L>::Mask valid_lanes(int pk) const {
        uint32_t bits = 0;
        for (int i = 0; i < kWidth; ++i) bits |= uint32_t(valid[pk * kWidth + i]) << i;
        return geer::lanes_of_bits<L>(bits);
    }
    const T* warp_bounds_of(int tid) const { return warp_bounds + 4 * (tid / geer::kWarp); }
};

template <typename T, bool kPacks>
std::vector<at::Tensor> render_forward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb,
                                       at::Tensor opacities, at::Tensor pbf_pieces, at::Tensor dirs,
                                       at::Tensor ray_bounds, at::Tensor warp_bounds, at::Tensor valid,
                                       at::Tensor ids, at::Tensor ranges, int64_t height, int64_t width,
                                       int64_t tile_size, bool record) {
    using L = LaneOf<T, kPacks>;
    constexpr int kWidth = geer::Lane<L>::width;
    constexpr int kBatch = geer::Batch<T>::value;
    const int64_t r = height * width;
    auto opts = whiten.options();
    auto out_rgb = at::zeros({r, 3}, opts), depth = at::zeros({r}, opts), acc = at::zeros({r}, opts);
    auto t_final = at::ones({r}, opts);
    auto n_contrib = at::zeros({r}, at::kInt);
    // Which lanes blended each list entry, per warp: what the CPU backward visits (render_backward). Only
    // when a backward will run (record): 32 bytes per list entry with 16-pixel tiles.
    const int warps = geer::warps_per_tile(int(tile_size));
    auto blended_lanes = record ? at::zeros({ids.numel(), warps}, at::kInt) : at::empty({0}, at::kInt);
    uint32_t* blended = record ? reinterpret_cast<uint32_t*>(blended_lanes.data_ptr<int32_t>()) : nullptr;
    const auto f = frames<T>(whiten, o_u, rgb, opacities, pbf_pieces);
    const int32_t* id = ids.data_ptr<int32_t>();
    const int32_t* rg = ranges.data_ptr<int32_t>();
    parallel_dynamic(geer::tile_count(int(height), int(width), int(tile_size)), [&](int64_t tile) {
        const Block<T, L> blk(int(tile), height, width, tile_size, bptr(valid), ptr<T>(dirs), ptr<T>(ray_bounds),
                              ptr<T>(warp_bounds));
        std::vector<geer::RayForward<L>> st(blk.packs);
        for (int pk = 0; pk < blk.packs; ++pk) geer::ray_forward_init(st[pk], blk.valid_lanes(pk));
        const int start = rg[2 * tile], end = rg[2 * tile + 1];
        for (int b = 0; b < geer::batch_count(end - start, kBatch); ++b) {
            bool all_done = true;  // __syncthreads_count(done) == blockDim.x
            for (int pk = 0; pk < blk.packs; ++pk)
                all_done = all_done && geer::lane_bits(st[pk].done) == geer::all_lane_bits<L>();
            if (all_done) break;
            const geer::ListBatch bt = geer::forward_batch(start, end, b, kBatch);
            for (int k = 0; k < bt.size; ++k) {
                const int j = geer::batch_entry(bt, k);
                const GaussFrame<T>& frame = f[id[j]];
                for (int w0 = 0; w0 < blk.threads; w0 += geer::kWarp) {
                    if (!geer::ray_meets_pbf(frame, blk.warp_bounds_of(w0))) continue;
                    uint32_t lanes = 0;
                    for (int pk = w0 / kWidth; pk < (w0 + geer::kWarp) / kWidth; ++pk) {
                        const auto before = st[pk].n_contrib;
                        geer::ray_forward_step(st[pk], frame, blk.dir[pk], blk.bounds[pk].data(), j - start);
                        // blended: n_contrib moved to j
                        lanes |= geer::lane_bits(st[pk].n_contrib != before) << (pk * kWidth - w0);
                    }
                    if (blended) blended[size_t(j) * warps + w0 / geer::kWarp] = lanes;
                }
            }
        }
        for (int tid = 0; tid < blk.threads; ++tid) {
            if (!blk.slot[tid].in_image) continue;
            const int ray = blk.slot[tid].ray, pk = tid / kWidth, i = tid % kWidth;
            for (int c = 0; c < 3; ++c) mptr<T>(out_rgb)[3 * ray + c] = geer::lane_get(st[pk].rgb[c], i);
            mptr<T>(depth)[ray] = geer::lane_get(st[pk].depth, i);
            mptr<T>(acc)[ray] = geer::lane_get(st[pk].acc, i);
            mptr<T>(t_final)[ray] = geer::lane_get(st[pk].trans, i);
            n_contrib.data_ptr<int32_t>()[ray] = geer::lane_get(st[pk].n_contrib, i);
        }
    });
    return {out_rgb, depth, acc, t_final, n_contrib, blended_lanes};
}

// The render stage's per-ray and per-warp cull bounds fit the grid (both passes).
void check_cull_bounds(const at::Tensor& ray_bounds, const at::Tensor& warp_bounds, int64_t height, int64_t width,
                       int64_t tile_size) {
    TORCH_CHECK(ray_bounds.numel() == 4 * height * width, "geer: ray_bounds must be [R,4]");
    TORCH_CHECK(warp_bounds.numel() == 4 * geer::tile_count(int(height), int(width), int(tile_size)) *
                                           geer::warps_per_tile(int(tile_size)),
                "geer: warp_bounds must be [tiles * warps per tile, 4]");
}

// render_forward for either dtype: kPacks, the CPU's path; otherwise one ray per thread, the kernels' path.
template <bool kPacks>
std::vector<at::Tensor> render_forward_op(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                                          at::Tensor pbf_pieces, at::Tensor dirs, at::Tensor ray_bounds,
                                          at::Tensor warp_bounds, at::Tensor valid, at::Tensor ids, at::Tensor ranges,
                                          int64_t height, int64_t width, int64_t tile_size, bool record) {
    whiten = cpu(whiten); o_u = cpu(o_u); rgb = cpu(rgb); opacities = cpu(opacities); pbf_pieces = cpu(pbf_pieces);
    dirs = cpu(dirs); ray_bounds = cpu(ray_bounds); warp_bounds = cpu(warp_bounds);
    valid = cpu(valid); ids = cpu(ids); ranges = cpu(ranges);
    check_cull_bounds(ray_bounds, warp_bounds, height, width, tile_size);
    return dispatch<int>(whiten, [&](auto tag) {
        return render_forward<decltype(tag), kPacks>(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds,
                                                     warp_bounds, valid, ids, ranges, height, width, tile_size,
                                                     record);
    });
}

constexpr int kGradValues = geer::kGradValues;

// One warp's reduction as render.cu runs it (geer_blocks.h): the 32 lanes in lock-step through the stages,
// each shuffle reading what the partner lane sent at the same stage; the writer lanes then add their totals
// to row (the kernel's atomicAdds). v: the lanes' values, left holding each lane's v[0] total. The reference
// for warp_grad_sum_sparse (what the CPU backward runs), through the warp_grad_sum op of the tests.
// GCC 12.2 at -O3 -mavx512f (-march=native here) miscompiles the scatter_send lane loop (some lanes send the
// wrong half; a standalone loop of copies does the same); the extension builds at -O3 for the generic x86-64
// target, where it does not, and tests/test_blocks_warp_reduction.py fails on a build that does.
template <typename T> void warp_grad_sum(T (*v)[kGradValues] /* [kWarp] */, T* row /* kGradValues */) {
    constexpr int kWarp = geer::kWarp;
    T sent[kWarp][kGradValues / 2];
    geer::for_each_scatter_stage([&](auto stage) {
        for (int lane = 0; lane < kWarp; ++lane) geer::scatter_send(stage, v[lane], lane, sent[lane]);
        for (int lane = 0; lane < kWarp; ++lane) geer::scatter_keep(stage, v[lane], lane, sent[lane ^ stage.mask]);
    });
    for (int lane = 0; lane < kWarp; ++lane)
        if (geer::scatter_writer(lane)) row[geer::scatter_value(lane)] += v[lane][0];
}

// The same sums as warp_grad_sum, bit for bit, without visiting the lanes that add zeros. For every value the
// butterfly adds the partial sums of lanes differing in bit 4 first (mask 16), bit 0 last (mask 1): a fixed
// binary tree over the lanes. Float addition is commutative and x + 0 == x exactly, so combining only the
// partials that hold a contributing lane (moving a lone one up unchanged) gives the same bits; on the CPU most
// lanes of most warps contribute nothing. tests/test_blocks_warp_reduction.py compares the two on random warps.
template <typename T> void warp_grad_sum_sparse(uint32_t contrib, const geer::PairGrad<T>* p, T* row) {
    if (!contrib) return;
    T vals[geer::kWarp][kGradValues];
    T* part[geer::kWarp];  // part[l]: the partial sum of lane l's subtree at the current stage
    for (uint32_t m = contrib; m; m &= m - 1) {
        const int l = __builtin_ctz(m);
        geer::lane_grad_values(p[l], true, vals[l]);
        part[l] = vals[l];
    }
    uint32_t present = contrib;
    for (int mask = geer::kWarp / 2; mask >= 1; mask >>= 1) {
        for (uint32_t upper = (present >> mask) & ((1u << mask) - 1); upper; upper &= upper - 1) {
            const int l = __builtin_ctz(upper);
            if ((present >> l) & 1u) {
                for (int i = 0; i < kGradValues; ++i) part[l][i] += part[l + mask][i];
            } else {
                part[l] = part[l + mask];
            }
        }
        present = (present | (present >> mask)) & ((1u << mask) - 1);
    }
    for (int i = 0; i < kGradValues; ++i) row[i] += part[0][i];  // the writer lanes' atomicAdds
}

// One lane of a pack's pair gradient.
template <typename T, typename L> void pair_grad_lane(const geer::PairGrad<L>& pg, int i, geer::PairGrad<T>& out) {
    for (int v = 0; v < 9; ++v) out.w[v] = geer::lane_get(pg.w[v], i);
    for (int v = 0; v < 3; ++v) {
        out.o[v] = geer::lane_get(pg.o[v], i);
        out.rgb[v] = geer::lane_get(pg.rgb[v], i);
    }
    out.opacity = geer::lane_get(pg.opacity, i);
}

// -> [N,16] gradient rows (geer_launchers.h RenderGradArgs::grads). kRecorded: the CPU's path (render_backward),
// which visits only the lanes the forward recorded as blending each entry (blended_lanes), in packs where
// kPacks; otherwise the GPU's path (render_backward_gpu_path: one ray per thread, the warp cull, then every lane
// of the blended prefix evaluates the pair, as render.cu), which the tests check gives the same bits.
template <bool kPacks, bool kRecorded>
at::Tensor render_backward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                           at::Tensor pbf_pieces,
                           at::Tensor dirs, at::Tensor ray_bounds, at::Tensor warp_bounds, at::Tensor valid,
                           at::Tensor ids, at::Tensor ranges,
                           int64_t height, int64_t width, int64_t tile_size, at::Tensor t_final,
                           at::Tensor n_contrib, at::Tensor blended_lanes, at::Tensor g_rgb, at::Tensor g_depth,
                           at::Tensor g_acc) {
    whiten = cpu(whiten); o_u = cpu(o_u); rgb = cpu(rgb); opacities = cpu(opacities); pbf_pieces = cpu(pbf_pieces);
    dirs = cpu(dirs); ray_bounds = cpu(ray_bounds); warp_bounds = cpu(warp_bounds);
    valid = cpu(valid); ids = cpu(ids); ranges = cpu(ranges);
    t_final = cpu(t_final); blended_lanes = cpu(blended_lanes);
    check_cull_bounds(ray_bounds, warp_bounds, height, width, tile_size);
    const int warps = geer::warps_per_tile(int(tile_size));
    TORCH_CHECK(!kRecorded || (blended_lanes.scalar_type() == at::kInt && blended_lanes.numel() == ids.numel() * warps),
                "geer: blended_lanes must be render_forward's [M, warps per tile] int32 record");
    n_contrib = cpu(n_contrib); g_rgb = cpu(g_rgb); g_depth = cpu(g_depth); g_acc = cpu(g_acc);
    const int64_t n = whiten.size(0), m = ids.numel();
    auto opts = whiten.options();
    auto grads = at::zeros({n, kGradValues}, opts);
    dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        using L = LaneOf<T, kPacks>;
        constexpr int kWidth = geer::Lane<L>::width;
        constexpr int kBatch = geer::Batch<T>::value;
        constexpr int kWarp = geer::kWarp;
        const auto f = frames<T>(whiten, o_u, rgb, opacities, pbf_pieces);
        const int32_t* id = ids.data_ptr<int32_t>();
        const int32_t* rg = ranges.data_ptr<int32_t>();
        const int32_t* nc = n_contrib.data_ptr<int32_t>();
        const uint32_t* blended = reinterpret_cast<const uint32_t*>(blended_lanes.data_ptr<int32_t>());
        std::vector<T> pair_grad(size_t(m) * kGradValues, T(0));  // one slot per (tile, Gaussian) pair
        parallel_dynamic(geer::tile_count(int(height), int(width), int(tile_size)), [&](int64_t tile) {
            const Block<T, L> blk(int(tile), height, width, tile_size, bptr(valid), ptr<T>(dirs), ptr<T>(ray_bounds),
                                  ptr<T>(warp_bounds));
            std::vector<geer::RayBackward<L>> st(blk.packs);
            std::vector<typename geer::Lane<L>::Int> my_n(blk.packs);
            int block_n = 0;
            for (int tid = 0; tid < blk.threads; ++tid) {
                const bool ok = blk.valid[tid] != 0;
                const int ray = blk.slot[tid].ray, pk = tid / kWidth, i = tid % kWidth;
                const int n_mine = ok ? nc[ray] : 0;
                geer::lane_set(my_n[pk], i, n_mine);
                block_n = std::max(block_n, n_mine);  // atomicMax
                geer::RayBackward<L>& s = st[pk];
                geer::lane_set(s.trans, i, ok ? ptr<T>(t_final)[ray] : T(1));
                geer::lane_set(s.rec, i, T(0));
                for (int c = 0; c < 3; ++c) geer::lane_set(s.g_rgb[c], i, ok ? ptr<T>(g_rgb)[3 * ray + c] : T(0));
                geer::lane_set(s.g_depth, i, ok ? ptr<T>(g_depth)[ray] : T(0));
                geer::lane_set(s.g_acc, i, ok ? ptr<T>(g_acc)[ray] : T(0));
            }
            const int start = rg[2 * tile];
            geer::PairGrad<T> p[kWarp];
            geer::PairGrad<L> pg{};  // only the lanes ray_backward_step returns are read
            for (int b = 0; b < geer::batch_count(block_n, kBatch); ++b) {
                const geer::ListBatch bt = geer::backward_batch(start, block_n, b, kBatch);
                for (int k = 0; k < bt.size; ++k) {
                    const int j = geer::batch_entry(bt, k);
                    const int pos = j - start;
                    const GaussFrame<T>& frame = f[id[j]];
                    T* slot = pair_grad.data() + size_t(j) * kGradValues;
                    for (int w0 = 0; w0 < blk.threads; w0 += kWarp) {
                        // The lanes to visit: the CPU's path, those that blended the entry (every other lane's
                        // step finds nothing: outside the PBF, q > q_max, or past its blended prefix); the
                        // kernels' path, every lane of a warp the cull keeps.
                        uint32_t lanes = ~0u;
                        if (kRecorded) lanes = blended[size_t(j) * warps + w0 / kWarp];
                        else if (!geer::ray_meets_pbf(frame, blk.warp_bounds_of(w0))) lanes = 0;
                        if (!lanes) continue;
                        uint32_t contrib = 0;  // __ballot_sync
                        for (int pk = w0 / kWidth; pk < (w0 + kWarp) / kWidth; ++pk) {
                            const int first = pk * kWidth - w0;  // the pack's first lane in the warp
                            const uint32_t mine = (lanes >> first) & geer::all_lane_bits<L>();
                            if (!mine) continue;
                            const auto active =
                                geer::lanes_of_bits<L>(mine) & (geer::Lane<L>::splat_int(pos) < my_n[pk]);
                            const uint32_t done = geer::lane_bits(geer::ray_backward_step(st[pk], frame, blk.dir[pk],
                                                                                          active, pg));
                            contrib |= done << first;
                            for (uint32_t d = done; d; d &= d - 1) {
                                const int i = __builtin_ctz(d);
                                pair_grad_lane(pg, i, p[first + i]);
                            }
                        }
                        warp_grad_sum_sparse(contrib, p, slot);
                    }
                }
            }
        });
        // Each Gaussian sums its pairs in list order.
        std::vector<int64_t> start(n + 1, 0);
        for (int64_t j = 0; j < m; ++j) ++start[id[j] + 1];
        for (int64_t i = 0; i < n; ++i) start[i + 1] += start[i];
        std::vector<int64_t> pairs(m), fill(start.begin(), start.end() - 1);
        for (int64_t j = 0; j < m; ++j) pairs[fill[id[j]]++] = j;
        parallel(n, kGaussGrain, [&](int64_t g) {
            T* row = mptr<T>(grads) + kGradValues * g;
            for (int64_t q = start[g]; q < start[g + 1]; ++q) {
                const T* slot = pair_grad.data() + size_t(pairs[q]) * kGradValues;
                for (int v = 0; v < kGradValues; ++v) row[v] += slot[v];
            }
        });
        return 0;
    });
    return grads;
}

// ------------------------------------------------------------------------------------ primitives
// A PBF that every ray meets, for the single-pair probes (they test the pair math, not the cull).
template <typename T> std::array<T, 8> full_range_pieces() {
    const T inf = geer::Limits<T>::inf();
    return {-inf, inf, inf, -inf, -inf, inf, inf, -inf};
}

// Per-pair response of K pairs (Gaussian k with ray k): D^2, t*, q (half-line), alpha (0 where not kept).
std::vector<at::Tensor> pair_eval(at::Tensor whiten, at::Tensor o_u, at::Tensor opac, at::Tensor dirs) {
    whiten = cpu(whiten); o_u = cpu(o_u); opac = cpu(opac); dirs = cpu(dirs);
    const int64_t k = whiten.size(0);
    auto d2 = at::empty({k}, whiten.options()), ts = at::empty({k}, whiten.options());
    auto q = at::empty({k}, whiten.options()), al = at::empty({k}, whiten.options());
    dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        const T zero[3] = {T(0), T(0), T(0)};
        for (int64_t i = 0; i < k; ++i) {
            GaussFrame<T> f;
            geer::make_frame(ptr<T>(whiten) + 9 * i, ptr<T>(o_u) + 3 * i, zero, ptr<T>(opac)[i],
                             full_range_pieces<T>().data(), f);
            auto e = geer::eval_pair(f, geer::load3(ptr<T>(dirs) + 3 * i));
            mptr<T>(d2)[i] = e.dist_sq;
            mptr<T>(ts)[i] = e.t_star;
            mptr<T>(q)[i] = e.q;
            mptr<T>(al)[i] = e.alpha;
        }
        return 0;
    });
    return {d2, ts, q, al};
}

// dL/dD^2, dL/dt* of K pairs -> dL/do_u [K,3], dL/dW [K,3,3].
std::vector<at::Tensor> pair_backward(at::Tensor whiten, at::Tensor o_u, at::Tensor dirs,
                                         at::Tensor g_d2, at::Tensor g_t) {
    whiten = cpu(whiten); o_u = cpu(o_u); dirs = cpu(dirs); g_d2 = cpu(g_d2); g_t = cpu(g_t);
    const int64_t k = whiten.size(0);
    auto go = at::zeros({k, 3}, whiten.options()), gw = at::zeros({k, 3, 3}, whiten.options());
    dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        const T zero[3] = {T(0), T(0), T(0)};
        for (int64_t i = 0; i < k; ++i) {
            GaussFrame<T> f;
            geer::make_frame(ptr<T>(whiten) + 9 * i, ptr<T>(o_u) + 3 * i, zero, T(1), full_range_pieces<T>().data(),
                             f);
            const Vec3<T> d = geer::load3(ptr<T>(dirs) + 3 * i);
            auto e = geer::eval_pair(f, d);
            Vec3<T> g;
            geer::pair_response_backward<T>(e, geer::load3(ptr<T>(o_u) + 3 * i), d, ptr<T>(g_d2)[i], ptr<T>(g_t)[i], g,
                                         mptr<T>(gw) + 9 * i);
            geer::store3(mptr<T>(go) + 3 * i, g);
        }
        return 0;
    });
    return {go, gw};
}

// One warp through the backward's reduction: values [32,16] (lane, gradient-row order: W, o_u, colour,
// opacity, as each lane's PairGrad), contrib [32] -> (the row its writer lanes add to zeros [16], every
// lane's total afterwards [32], the row of warp_grad_sum_sparse, which the CPU backward runs).
std::vector<at::Tensor> warp_grad_sum_op(at::Tensor values, at::Tensor contrib) {
    values = cpu(values); contrib = cpu(contrib);
    constexpr int kWarp = geer::kWarp;
    TORCH_CHECK(values.dim() == 2 && values.size(0) == kWarp && values.size(1) == kGradValues,
                "geer cpu_ops: warp_grad_sum: values must be [32, 16], got ", values.sizes());
    TORCH_CHECK(contrib.scalar_type() == at::kBool && contrib.numel() == kWarp,
                "geer cpu_ops: warp_grad_sum: contrib must be 32 bools");
    auto row = at::zeros({kGradValues}, values.options()), totals = at::empty({kWarp}, values.options());
    auto row_sparse = at::zeros({kGradValues}, values.options());
    dispatch<int>(values, [&](auto tag) {
        using T = decltype(tag);
        T v[kWarp][kGradValues];
        geer::PairGrad<T> p[kWarp];
        uint32_t mask = 0;
        for (int lane = 0; lane < kWarp; ++lane) {
            const T* in = ptr<T>(values) + kGradValues * lane;
            for (int i = 0; i < 9; ++i) p[lane].w[i] = in[i];
            for (int i = 0; i < 3; ++i) {
                p[lane].o[i] = in[9 + i];
                p[lane].rgb[i] = in[12 + i];
            }
            p[lane].opacity = in[15];
            geer::lane_grad_values(p[lane], bptr(contrib)[lane] != 0, v[lane]);
            if (bptr(contrib)[lane]) mask |= 1u << lane;
        }
        warp_grad_sum(v, mptr<T>(row));
        for (int lane = 0; lane < kWarp; ++lane) mptr<T>(totals)[lane] = v[lane][0];
        warp_grad_sum_sparse(mask, p, mptr<T>(row_sparse));
        return 0;
    });
    return {row, totals, row_sparse};
}

}  // namespace

namespace geer_cpu {

void register_render_ops(pybind11::module_& m) {
    m.def("render_forward", &render_forward_op<kCpuPacks>);
    m.def("render_forward_gpu_path", &render_forward_op<false>);
    m.def("render_backward", &render_backward<kCpuPacks, true>);
    m.def("render_backward_gpu_path", &render_backward<false, false>);
    // The CPU's path one ray at a time: what render_backward is on a build without AVX2.
    m.def("render_backward_one_ray", &render_backward<false, true>);
    m.def("render_lanes", [](bool float64) -> int64_t {
        if (!kCpuPacks) return 1;
        return float64 ? geer::Lane<geer::DoublePack>::width : geer::Lane<geer::FloatPack>::width;
    }, "rays per pack in render_forward / render_backward (1: one ray at a time, as a GPU thread)");
    m.def("pair_eval", &pair_eval);
    m.def("pair_backward", &pair_backward);
    m.def("warp_grad_sum", &warp_grad_sum_op);
}

}  // namespace geer_cpu
