// Stage 3 of the CPU build, backward (the forward: cpu_render.cpp): the back-to-front gradient over geer_ray.h's
// per-ray functions and geer_blocks.h's per-block orchestration, in packs of rays where the build has AVX2
// (render_backward), one ray per thread as the kernels (render_backward_gpu_path) and the CPU's path one ray at
// a time (render_backward_one_ray); the warp reductions' lock-step and sparse forms, and their test ops.
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <vector>

#include "cpu_render.h"

namespace {

using namespace geer_cpu;

constexpr int kGradValues = geer::kGradValues;
constexpr int kAbsgradValues = geer::kAbsgradValues;
constexpr int kWarp = geer::kWarp;

// One warp's reduction as render.cu runs it (geer_blocks.h): the 32 lanes in lock-step through the stages,
// each shuffle reading what the partner lane sent at the same stage; the writer lanes then add their totals
// to row (the kernel's atomicAdds). v: the lanes' values, left holding each lane's v[0] total. The reference
// for warp_sum_sparse (what the CPU backward runs), through the warp_grad_sum op of the tests.
// GCC 12.2 at -O3 -mavx512f (-march=native here) miscompiles the scatter_send lane loop (some lanes send the
// wrong half; a standalone loop of copies does the same); the extension builds at -O3 for the generic x86-64
// target, where it does not, and tests/test_blocks_warp_reduction.py fails on a build that does.
template <typename T> void warp_grad_sum(T (*v)[kGradValues] /* [kWarp] */, T* row /* kGradValues */) {
    T sent[kWarp][kGradValues / 2];
    geer::for_each_scatter_stage([&](auto stage) {
        for (int lane = 0; lane < kWarp; ++lane) geer::scatter_send(stage, v[lane], lane, sent[lane]);
        for (int lane = 0; lane < kWarp; ++lane) geer::scatter_keep(stage, v[lane], lane, sent[lane ^ stage.mask]);
    });
    for (int lane = 0; lane < kWarp; ++lane)
        if (geer::scatter_writer(lane)) row[geer::scatter_value(lane)] += v[lane][0];
}

// render.cu's warp_tree_sum (the absgrad values' butterfly) in lock-step: at every mask each lane adds what lane
// ^ mask holds; lane 0's totals go to row (its atomicAdds). The reference for warp_sum_sparse's 2 values.
template <int kValues, typename T> void warp_tree_sum(T (*v)[kValues] /* [kWarp] */, T* row /* kValues */) {
    geer::for_each_tree_mask([&](int mask) {
        T received[kWarp][kValues];
        for (int lane = 0; lane < kWarp; ++lane)
            for (int i = 0; i < kValues; ++i) received[lane][i] = v[lane ^ mask][i];
        for (int lane = 0; lane < kWarp; ++lane)
            for (int i = 0; i < kValues; ++i) v[lane][i] += received[lane][i];
    });
    for (int i = 0; i < kValues; ++i) row[i] += v[0][i];
}

// The warp's sums of kValues values per lane, bit for bit those of warp_grad_sum (each of the reduce-scatter's
// values) and warp_tree_sum, without visiting the lanes that add zeros. Both add, for every value, the partial
// sums of lanes differing in bit 4 first (mask 16), bit 0 last (mask 1): geer_blocks.h's tree. Float addition
// is commutative and x + 0 == x exactly, so combining only the partials that hold a contributing lane (moving a
// lone one up unchanged) gives the same bits; on the CPU most lanes of most warps contribute nothing.
// values(l, v) fills lane l's kValues values; row gets the totals added. tests/test_blocks_warp_reduction.py
// compares it with both lock-step forms on random warps.
template <int kValues, typename T, typename F> void warp_sum_sparse(uint32_t contrib, F&& values, T* row) {
    if (!contrib) return;
    T vals[kWarp][kValues];
    T* part[kWarp];  // part[l]: the partial sum of lane l's subtree at the current stage
    for (uint32_t m = contrib; m; m &= m - 1) {
        const int l = __builtin_ctz(m);
        values(l, vals[l]);
        part[l] = vals[l];
    }
    uint32_t present = contrib;
    geer::for_each_tree_mask([&](int mask) {
        for (uint32_t upper = (present >> mask) & ((1u << mask) - 1); upper; upper &= upper - 1) {
            const int l = __builtin_ctz(upper);
            if ((present >> l) & 1u) {
                for (int i = 0; i < kValues; ++i) part[l][i] += part[l + mask][i];
            } else {
                part[l] = part[l + mask];
            }
        }
        present = (present | (present >> mask)) & ((1u << mask) - 1);
    });
    for (int i = 0; i < kValues; ++i) row[i] += part[0][i];  // the writer lanes' atomicAdds
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

// -> ([N,16] gradient rows (geer_launchers.h RenderGradArgs::grads), absgrad [N,2] or empty). kRecorded: the
// CPU's path (render_backward), which visits only the lanes the forward recorded as blending each entry
// (blended_lanes), in packs where kPacks; otherwise the GPU's path (render_backward_gpu_path: one ray per thread,
// the warp cull, then every lane of the blended prefix evaluates the pair, as render.cu), which the tests check
// gives the same bits. absgrad_rows [N,6] (empty: off): also each pair's absgrad values (geer_blocks.h
// lane_absgrad_values), summed as the gradients are.
// kDirGrad: also each ray's dL/d(direction) [R,3] (geer_ray.h ray_backward_step), the third output.
// kOrigin: every ray from its own origin (origins [R,3], rolling shutter); with kDirGrad also each ray's
// dL/d(origin) [R,3], the fourth output.
template <bool kPacks, bool kRecorded, bool kDirGrad, bool kOrigin>
std::vector<at::Tensor> render_backward_impl(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                                             at::Tensor pbf_pieces, at::Tensor dirs, at::Tensor ray_bounds,
                                             at::Tensor warp_bounds, at::Tensor valid, at::Tensor ids,
                                             at::Tensor ranges, int64_t height, int64_t width, int64_t tile_size,
                                             at::Tensor t_final, at::Tensor n_contrib, at::Tensor blended_lanes,
                                             at::Tensor g_rgb, at::Tensor g_depth, at::Tensor g_acc,
                                             at::Tensor absgrad_rows, at::Tensor origins) {
    whiten = cpu(whiten); o_u = cpu(o_u); rgb = cpu(rgb); opacities = cpu(opacities); pbf_pieces = cpu(pbf_pieces);
    dirs = cpu(dirs); ray_bounds = cpu(ray_bounds); warp_bounds = cpu(warp_bounds);
    valid = cpu(valid); ids = cpu(ids); ranges = cpu(ranges);
    t_final = cpu(t_final); blended_lanes = cpu(blended_lanes); absgrad_rows = cpu(absgrad_rows);
    origins = cpu(origins);
    check_cull_bounds(ray_bounds, warp_bounds, height, width, tile_size);
    const int warps = geer::warps_per_tile(int(tile_size));
    TORCH_CHECK(!kRecorded || (blended_lanes.scalar_type() == at::kInt && blended_lanes.numel() == ids.numel() * warps),
                "geer: blended_lanes must be render_forward's [M, warps per tile] int32 record");
    n_contrib = cpu(n_contrib); g_rgb = cpu(g_rgb); g_depth = cpu(g_depth); g_acc = cpu(g_acc);
    const int64_t n = whiten.size(0), m = ids.numel();
    const bool with_absgrad = absgrad_rows.numel() > 0;
    TORCH_CHECK(!with_absgrad || (absgrad_rows.scalar_type() == whiten.scalar_type() &&
                                  absgrad_rows.numel() == geer::kAbsgradRow * n),
                "geer: absgrad_rows must be [N,6] of the Gaussians' dtype");
    auto opts = whiten.options();
    auto grads = at::zeros({n, kGradValues}, opts);
    auto absgrad = with_absgrad ? at::zeros({n, kAbsgradValues}, opts) : at::empty({0}, opts);
    auto g_dirs = kDirGrad ? at::zeros({height * width, 3}, opts) : at::empty({0}, opts);
    auto g_origins = kDirGrad && kOrigin ? at::zeros({height * width, 3}, opts) : at::empty({0}, opts);
    dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        using L = LaneOf<T, kPacks>;
        constexpr int kWidth = geer::Lane<L>::width;
        constexpr int kBatch = geer::Batch<T>::value;
        const auto f = frames<T>(whiten, o_u, rgb, opacities, pbf_pieces);
        const int32_t* id = ids.data_ptr<int32_t>();
        const int32_t* rg = ranges.data_ptr<int32_t>();
        const int32_t* nc = n_contrib.data_ptr<int32_t>();
        const uint32_t* blended = reinterpret_cast<const uint32_t*>(blended_lanes.data_ptr<int32_t>());
        const T* rows = with_absgrad ? ptr<T>(absgrad_rows) : nullptr;
        std::vector<T> pair_grad(size_t(m) * kGradValues, T(0));  // one slot per (tile, Gaussian) pair
        std::vector<T> pair_absgrad(with_absgrad ? size_t(m) * kAbsgradValues : 0, T(0));
        parallel_dynamic(geer::tile_count(int(height), int(width), int(tile_size)), [&](int64_t tile) {
            const Block<T, L> blk(int(tile), height, width, tile_size, bptr(valid), ptr<T>(dirs), ptr<T>(ray_bounds),
                                  ptr<T>(warp_bounds), kOrigin ? ptr<T>(origins) : nullptr);
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
                if (kDirGrad)
                    for (L* c : {&s.g_dir.x, &s.g_dir.y, &s.g_dir.z, &s.g_origin.x, &s.g_origin.y, &s.g_origin.z})
                        geer::lane_set(*c, i, T(0));
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
                            const uint32_t done = geer::lane_bits(geer::ray_backward_step<T, L, kDirGrad, kOrigin>(
                                st[pk], frame, blk.dir[pk], active, pg, blk.origin_of(pk)));
                            contrib |= done << first;
                            for (uint32_t d = done; d; d &= d - 1) {
                                const int i = __builtin_ctz(d);
                                pair_grad_lane(pg, i, p[first + i]);
                            }
                        }
                        warp_sum_sparse<kGradValues>(
                            contrib, [&](int l, T* v) { geer::lane_grad_values(p[l], true, v); },
                            pair_grad.data() + size_t(j) * kGradValues);
                        if (!rows) continue;
                        const T* row = rows + geer::kAbsgradRow * id[j];
                        warp_sum_sparse<kAbsgradValues>(
                            contrib, [&](int l, T* v) { geer::lane_absgrad_values(row, p[l], true, v); },
                            pair_absgrad.data() + size_t(j) * kAbsgradValues);
                    }
                }
            }
            if (!kDirGrad) return;
            for (int tid = 0; tid < blk.threads; ++tid) {
                if (!blk.valid[tid]) continue;
                const geer::RayBackward<L>& sr = st[tid / kWidth];
                for (auto [g, out] : {std::pair{&sr.g_dir, &g_dirs}, std::pair{&sr.g_origin, &g_origins}}) {
                    if (out == &g_origins && !kOrigin) continue;
                    T* row = mptr<T>(*out) + 3 * blk.slot[tid].ray;
                    row[0] = geer::lane_get(g->x, tid % kWidth);
                    row[1] = geer::lane_get(g->y, tid % kWidth);
                    row[2] = geer::lane_get(g->z, tid % kWidth);
                }
            }
        });
        const auto plus = [](T a, T b) { return a + b; };
        const EntriesOfGaussians entries = entries_of_gaussians(id, m, n);
        fold_entries(entries, kGradValues, pair_grad.data(), mptr<T>(grads), plus);
        if (rows) fold_entries(entries, kAbsgradValues, pair_absgrad.data(), mptr<T>(absgrad), plus);
        return 0;
    });
    return {grads, absgrad, g_dirs, g_origins};
}

// -> (gradient rows, absgrad or empty, dL/d(ray directions) [R,3] where dir_grad, else empty, dL/d(ray origins)
// [R,3] where dir_grad and origins are given, else empty).
template <bool kPacks, bool kRecorded>
std::vector<at::Tensor> render_backward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                                        at::Tensor pbf_pieces, at::Tensor dirs, at::Tensor ray_bounds,
                                        at::Tensor warp_bounds, at::Tensor valid, at::Tensor ids, at::Tensor ranges,
                                        int64_t height, int64_t width, int64_t tile_size, at::Tensor t_final,
                                        at::Tensor n_contrib, at::Tensor blended_lanes, at::Tensor g_rgb,
                                        at::Tensor g_depth, at::Tensor g_acc, at::Tensor absgrad_rows, bool dir_grad,
                                        at::Tensor origins, at::Tensor order_lower, int64_t order_window,
                                        at::Tensor ray_totals) {
    const bool with_origins = check_origins(origins, whiten, height * width);
    if (order_lower.numel() > 0) {  // each ray's own order
        check_cull_bounds(ray_bounds, warp_bounds, height, width, tile_size);
        TORCH_CHECK(blended_lanes.scalar_type() == at::kInt, "geer: blended_lanes must be render_forward's record");
        TORCH_CHECK(absgrad_rows.numel() == 0 || (absgrad_rows.scalar_type() == whiten.scalar_type() &&
                                                  absgrad_rows.numel() == geer::kAbsgradRow * whiten.size(0)),
                    "geer: absgrad_rows must be [N,6] of the Gaussians' dtype");
        const RenderInputs in{cpu(whiten), cpu(o_u), cpu(rgb), cpu(opacities), cpu(pbf_pieces), cpu(dirs),
                              cpu(ray_bounds), cpu(warp_bounds), cpu(valid), cpu(ids), cpu(ranges), height, width,
                              tile_size, cpu(origins)};
        const RayGrads g{cpu(blended_lanes), cpu(g_rgb), cpu(g_depth), cpu(g_acc), cpu(absgrad_rows), cpu(ray_totals)};
        return render_backward_ordered_op(kRecorded, dir_grad, in, g, cpu(order_lower), order_window);
    }
    const auto run = dir_grad ? (with_origins ? &render_backward_impl<kPacks, kRecorded, true, true>
                                              : &render_backward_impl<kPacks, kRecorded, true, false>)
                              : (with_origins ? &render_backward_impl<kPacks, kRecorded, false, true>
                                              : &render_backward_impl<kPacks, kRecorded, false, false>);
    return run(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids, ranges, height,
               width, tile_size, t_final, n_contrib, blended_lanes, g_rgb, g_depth, g_acc, absgrad_rows, origins);
}

// A test op's warp: values [32, width] (a row per lane), contrib [32] bools -> the contributing lanes' bits.
uint32_t warp_inputs(const at::Tensor& values, const at::Tensor& contrib, int width, const char* op) {
    TORCH_CHECK(values.dim() == 2 && values.size(0) == kWarp && values.size(1) == width, "geer cpu_ops: ", op,
                ": values must be [32, ", width, "], got ", values.sizes());
    TORCH_CHECK(contrib.scalar_type() == at::kBool && contrib.numel() == kWarp, "geer cpu_ops: ", op,
                ": contrib must be 32 bools");
    uint32_t mask = 0;
    for (int lane = 0; lane < kWarp; ++lane) mask |= uint32_t(bptr(contrib)[lane] != 0) << lane;
    return mask;
}

// One warp through the backward's reductions. values [32,16] (lane, gradient-row order: W, o_u, colour, opacity,
// as each lane's PairGrad), contrib [32] -> (the row its writer lanes add to zeros [16], every lane's total
// afterwards [32], the row of warp_sum_sparse, which the CPU backward runs).
std::vector<at::Tensor> warp_grad_sum_op(at::Tensor values, at::Tensor contrib) {
    values = cpu(values); contrib = cpu(contrib);
    const uint32_t mask = warp_inputs(values, contrib, kGradValues, "warp_grad_sum");
    auto row = at::zeros({kGradValues}, values.options()), totals = at::empty({kWarp}, values.options());
    auto row_sparse = at::zeros({kGradValues}, values.options());
    dispatch<int>(values, [&](auto tag) {
        using T = decltype(tag);
        T v[kWarp][kGradValues];
        geer::PairGrad<T> p[kWarp];
        for (int lane = 0; lane < kWarp; ++lane) {
            const T* in = ptr<T>(values) + kGradValues * lane;
            for (int i = 0; i < 9; ++i) p[lane].w[i] = in[i];
            for (int i = 0; i < 3; ++i) {
                p[lane].o[i] = in[9 + i];
                p[lane].rgb[i] = in[12 + i];
            }
            p[lane].opacity = in[15];
            geer::lane_grad_values(p[lane], (mask >> lane) & 1u, v[lane]);
        }
        warp_grad_sum(v, mptr<T>(row));
        for (int lane = 0; lane < kWarp; ++lane) mptr<T>(totals)[lane] = v[lane][0];
        warp_sum_sparse<kGradValues>(mask, [&](int l, T* out) { geer::lane_grad_values(p[l], true, out); },
                                     mptr<T>(row_sparse));
        return 0;
    });
    return {row, totals, row_sparse};
}

// The absgrad values' reduction: values [32,2] (zeros where contrib is false, as lane_absgrad_values gives
// them), contrib [32] -> (the kernel's butterfly in lock-step, warp_sum_sparse), each a row [2] added to zeros.
std::vector<at::Tensor> warp_tree_sum_op(at::Tensor values, at::Tensor contrib) {
    values = cpu(values); contrib = cpu(contrib);
    const uint32_t mask = warp_inputs(values, contrib, kAbsgradValues, "warp_tree_sum");
    auto row = at::zeros({kAbsgradValues}, values.options());
    auto row_sparse = at::zeros({kAbsgradValues}, values.options());
    dispatch<int>(values, [&](auto tag) {
        using T = decltype(tag);
        const T* in = ptr<T>(values);
        const auto lane_values = [&](int lane, T* out) {  // zeros off contrib, as lane_absgrad_values
            const bool on = (mask >> lane) & 1u;
            for (int i = 0; i < kAbsgradValues; ++i) out[i] = on ? in[kAbsgradValues * lane + i] : T(0);
        };
        T v[kWarp][kAbsgradValues];
        for (int lane = 0; lane < kWarp; ++lane) lane_values(lane, v[lane]);
        warp_sum_sparse<kAbsgradValues>(mask, lane_values, mptr<T>(row_sparse));
        warp_tree_sum<kAbsgradValues>(v, mptr<T>(row));
        return 0;
    });
    return {row, row_sparse};
}

}  // namespace

namespace geer_cpu {

void register_render_backward_ops(pybind11::module_& m) {
    m.def("render_backward", &render_backward<kCpuPacks, true>);
    m.def("render_backward_gpu_path", &render_backward<false, false>);
    // The CPU's path one ray at a time: what render_backward is on a build without AVX2.
    m.def("render_backward_one_ray", &render_backward<false, true>);
    m.def("warp_grad_sum", &warp_grad_sum_op);
    m.def("warp_tree_sum", &warp_tree_sum_op);
}

}  // namespace geer_cpu
