// Stage 3 of the CPU build, forward (cpu_ops.cpp has the rest and the module; the backward and the warp
// reductions are in cpu_render_backward.cpp): render forward over geer_ray.h's per-ray functions and
// geer_blocks.h's per-block orchestration, in packs of rays where the build has AVX2 (geer_packs.h) and one ray
// per thread as the kernels (render_forward_gpu_path); the single-pair probes of the tests.
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <array>
#include <vector>

#include "cpu_render.h"

namespace {

using namespace geer_cpu;

// kOrigin: every ray from its own origin (origins [R,3]: rolling shutter), else from the camera centre.
template <typename T, bool kPacks, bool kOrigin>
std::vector<at::Tensor> render_forward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb,
                                       at::Tensor opacities, at::Tensor pbf_pieces, at::Tensor dirs,
                                       at::Tensor ray_bounds, at::Tensor warp_bounds, at::Tensor valid,
                                       at::Tensor ids, at::Tensor ranges, int64_t height, int64_t width,
                                       int64_t tile_size, bool record, at::Tensor origins) {
    using L = LaneOf<T, kPacks>;
    constexpr int kWidth = geer::Lane<L>::width;
    constexpr int kBatch = geer::Batch<T>::value;
    const int64_t r = height * width;
    auto opts = whiten.options();
    auto out_rgb = at::zeros({r, 3}, opts), depth = at::zeros({r}, opts), acc = at::zeros({r}, opts);
    auto t_final = at::ones({r}, opts), median = at::zeros({r}, opts);
    auto n_contrib = at::zeros({r}, at::kInt);
    // Which lanes blended each list entry, per warp: what the CPU backward visits (render_backward). Only
    // when a backward will run (record): 32 bytes per list entry with 16-pixel tiles.
    const int warps = geer::warps_per_tile(int(tile_size));
    auto blended_lanes = record ? at::zeros({ids.numel(), warps}, at::kInt) : at::empty({0}, at::kInt);
    uint32_t* blended = record ? reinterpret_cast<uint32_t*>(blended_lanes.data_ptr<int32_t>()) : nullptr;
    const auto f = frames<T>(whiten, o_u, rgb, opacities, pbf_pieces);
    const int32_t* id = ids.data_ptr<int32_t>();
    const int32_t* rg = ranges.data_ptr<int32_t>();
    const int64_t m = ids.numel();
    std::vector<T> entry_weight(size_t(m), T(0));  // per list entry: its rays' largest blend weight
    parallel_dynamic(geer::tile_count(int(height), int(width), int(tile_size)), [&](int64_t tile) {
        const Block<T, L> blk(int(tile), height, width, tile_size, bptr(valid), ptr<T>(dirs), ptr<T>(ray_bounds),
                              ptr<T>(warp_bounds), kOrigin ? ptr<T>(origins) : nullptr);
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
                T top = T(0);  // the entry's largest weight (a max: exact in any order)
                for (int w0 = 0; w0 < blk.threads; w0 += geer::kWarp) {
                    if (!geer::ray_meets_pbf(frame, blk.warp_bounds_of(w0))) continue;
                    uint32_t lanes = 0;
                    for (int pk = w0 / kWidth; pk < (w0 + geer::kWarp) / kWidth; ++pk) {
                        const auto before = st[pk].n_contrib;
                        const L w = geer::ray_forward_step<T, L, kOrigin>(st[pk], frame, blk.dir[pk],
                                                                          blk.bounds[pk].data(), j - start,
                                                                          blk.origin_of(pk));
                        // blended: n_contrib moved to j
                        lanes |= geer::lane_bits(st[pk].n_contrib != before) << (pk * kWidth - w0);
                        for (int i = 0; i < kWidth; ++i) top = geer::g_max(top, geer::lane_get(w, i));
                    }
                    if (blended) blended[size_t(j) * warps + w0 / geer::kWarp] = lanes;
                }
                entry_weight[j] = top;
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
            mptr<T>(median)[ray] = geer::lane_get(st[pk].median, i);
        }
    });
    auto max_weight = at::zeros({whiten.size(0)}, opts);
    fold_entries(entries_of_gaussians(id, m, whiten.size(0)), 1, entry_weight.data(), mptr<T>(max_weight),
                 [](T a, T b) { return geer::g_max(a, b); });
    return {out_rgb, depth, acc, t_final, n_contrib, blended_lanes, max_weight, median};
}

// render_forward for either dtype: kPacks, the CPU's path; otherwise one ray per thread, the kernels' path.
template <bool kPacks>
std::vector<at::Tensor> render_forward_op(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                                          at::Tensor pbf_pieces, at::Tensor dirs, at::Tensor ray_bounds,
                                          at::Tensor warp_bounds, at::Tensor valid, at::Tensor ids, at::Tensor ranges,
                                          int64_t height, int64_t width, int64_t tile_size, bool record,
                                          at::Tensor origins, at::Tensor order_lower, int64_t order_window) {
    whiten = cpu(whiten); o_u = cpu(o_u); rgb = cpu(rgb); opacities = cpu(opacities); pbf_pieces = cpu(pbf_pieces);
    dirs = cpu(dirs); ray_bounds = cpu(ray_bounds); warp_bounds = cpu(warp_bounds);
    valid = cpu(valid); ids = cpu(ids); ranges = cpu(ranges); origins = cpu(origins);
    check_cull_bounds(ray_bounds, warp_bounds, height, width, tile_size);
    const bool with_origins = check_origins(origins, whiten, height * width);
    if (order_lower.numel() > 0) {  // each ray's own order
        const RenderInputs in{whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid,
                              ids, ranges, height, width, tile_size, origins};
        return render_forward_ordered_op(kPacks, in, record, cpu(order_lower), order_window);
    }
    return dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        const auto run = with_origins ? &render_forward<T, kPacks, true> : &render_forward<T, kPacks, false>;
        return run(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges, height,
                   width, tile_size, record, origins);
    });
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

}  // namespace

namespace geer_cpu {

void register_render_backward_ops(pybind11::module_& m);  // cpu_render_backward.cpp

void register_render_ops(pybind11::module_& m) {
    m.def("render_forward", &render_forward_op<kCpuPacks>);
    m.def("render_forward_gpu_path", &render_forward_op<false>);
    register_render_backward_ops(m);  // render_backward (+ _gpu_path, _one_ray), warp_grad_sum, warp_tree_sum
    m.def("render_lanes", [](bool float64) -> int64_t {
        if (!kCpuPacks) return 1;
        return float64 ? geer::Lane<geer::DoublePack>::width : geer::Lane<geer::FloatPack>::width;
    }, "rays per pack in render_forward / render_backward (1: one ray at a time, as a GPU thread)");
    m.def("pair_eval", &pair_eval);
    m.def("pair_backward", &pair_backward);
}

}  // namespace geer_cpu
