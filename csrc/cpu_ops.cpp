// The 3DGEER pipeline on the CPU: geer_math.h (per-Gaussian math), geer_ray.h (per-pair and per-ray math),
// geer_associate.h (tile search, sort keys, ranges) and geer_blocks.h (which ray and which list entry each GPU
// thread touches, batches, the warp reduction's order) run behind the same operation names and signatures as
// the CUDA extension (bindings.cpp), so geer_ns/render/cuda_backend.py drives either: backend="cpu", and
// the twin checks of tests/test_csrc_math.py. What the GPU adds on top (shared memory, atomics, the
// radix sort) is not exercised here.
//
// The render stage's own path evaluates a warp's rays in packs (geer_packs.h, where the build has AVX2), and
// its forward records which lanes blended each list entry so that the backward visits only those. The
// kernels' path, one ray per thread with the warp cull, runs here too (render_forward_gpu_path,
// render_backward_gpu_path); tests/test_cpu_backend.py checks that both give the same bits.
//
// Multi-threaded with at::parallel_for over tiles (render) and Gaussians (preprocess, association), with
// every float sum in a fixed order: results do not depend on the thread count or scheduling. The render
// backward sums each (tile, Gaussian) pair's gradient over the tile's rays in the kernel's order (the warp
// reduction's order over the contributing lanes, warp_sum_sparse, then warps in order) into that pair's
// own slot, then each Gaussian sums its pairs in list order (absgrad's sums and max_weight's maxima too).
// Stage 3 lives in cpu_render.cpp (forward) and cpu_render_backward.cpp.
// ATen + pybind only (not torch/extension.h): half the compile time.
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <optional>
#include <vector>

#include "cpu_common.h"
#include "geer_associate.h"
#include "geer_math.h"

namespace geer_cpu {
void register_render_ops(pybind11::module_& m);  // cpu_render.cpp
}

namespace {

using namespace geer_cpu;
using geer::Mat3;
using geer::Vec3;

// ------------------------------------------------------------------------------------ stage 1
// Each Gaussian's own SH degree (uint8 [n]), or an empty tensor where none is given (every Gaussian at sh_degree).
at::Tensor own_degrees(const std::optional<at::Tensor>& degrees, int64_t n) {
    if (!degrees.has_value() || degrees->numel() == 0) return at::empty({0}, at::kByte);
    TORCH_CHECK(degrees->scalar_type() == at::kByte && degrees->numel() == n,
                "geer cpu_ops: sh_degrees must be uint8, one degree per Gaussian");
    return cpu(*degrees);
}

const uint8_t* degrees_ptr(const at::Tensor& own) { return own.numel() ? own.data_ptr<uint8_t>() : nullptr; }

std::vector<at::Tensor> preprocess_forward(at::Tensor means_c, at::Tensor quats, at::Tensor scales,
                                              at::Tensor opacities, at::Tensor sh, at::Tensor sh_dirs,
                                              at::Tensor rot_c, int64_t sh_degree, bool paper_lambda,
                                              std::optional<at::Tensor> sh_degrees) {
    means_c = cpu(means_c); quats = cpu(quats); scales = cpu(scales); opacities = cpu(opacities);
    sh = cpu(sh); sh_dirs = cpu(sh_dirs); rot_c = cpu(rot_c);
    const at::Tensor own = own_degrees(sh_degrees, means_c.size(0));
    const int64_t n = means_c.size(0);
    auto opts = means_c.options();
    auto whiten = at::zeros({n, 3, 3}, opts), o_u = at::zeros({n, 3}, opts), rgb = at::zeros({n, 3}, opts);
    auto bounds = at::zeros({n, 4}, opts);
    auto alive = at::zeros({n}, opts.dtype(at::kBool)), inside = at::zeros({n}, opts.dtype(at::kBool));
    dispatch<int>(means_c, [&](auto tag) {
        using T = decltype(tag);
        const Mat3<T> rc = geer::load_mat3(ptr<T>(rot_c));
        const int64_t k = sh_degree >= 0 ? sh.size(1) : 0;
        parallel(n, kGaussGrain, [&](int64_t i) {
            auto g = geer::preprocess_gaussian(geer::load3(ptr<T>(means_c) + 3 * i), ptr<T>(quats) + 4 * i,
                                               ptr<T>(scales) + 3 * i, ptr<T>(opacities)[i], rc, paper_lambda);
            geer::store_mat3(mptr<T>(whiten) + 9 * i, g.w);
            geer::store3(mptr<T>(o_u) + 3 * i, g.o_u);
            for (int j = 0; j < 4; ++j) mptr<T>(bounds)[4 * i + j] = g.bounds[j];
            mbptr(alive)[i] = g.alive;
            mbptr(inside)[i] = g.camera_inside;
            if (sh_degree >= 0) {
                const Vec3<T> dir = geer::load3(ptr<T>(sh_dirs) + 3 * i);
                const int degree = geer::gaussian_sh_degree(int(sh_degree), degrees_ptr(own), i);
                geer::store3(mptr<T>(rgb) + 3 * i, geer::sh_to_color(ptr<T>(sh) + 3 * k * i, degree, dir));
            }
        });
        return 0;
    });
    return {whiten, o_u, rgb, bounds, alive, inside};
}

// ------------------------------------------------------------------------------------ stage 2
// associate.cu's passes: count (pyramid search), exclusive scan, emit (each Gaussian's tile box only),
// then the pairs in key order (the radix sort's result, reached by bucketing: see below) and the ranges.
// -> (ids, ranges [T,2], counts [N] tiles per Gaussian, tests [N] tile tests of both passes).
std::vector<at::Tensor> associate(at::Tensor bounds, at::Tensor alive, at::Tensor order, at::Tensor node_bounds,
                                  at::Tensor node_active, int64_t tiles_x, int64_t tiles_y, at::Tensor gauss_cones,
                                  at::Tensor tile_cones) {
    bounds = cpu(bounds); alive = cpu(alive); order = cpu(order).to(at::kInt); node_bounds = cpu(node_bounds);
    node_active = cpu(node_active); gauss_cones = cpu(gauss_cones); tile_cones = cpu(tile_cones);
    // Empty cones: the box test alone (the association before the cone test).
    const bool cones = gauss_cones.numel() > 0 && tile_cones.numel() > 0;
    TORCH_CHECK(!cones || (gauss_cones.numel() == geer::kGaussConeValues * bounds.size(0) &&
                           tile_cones.numel() == geer::kTileConeValues * tiles_x * tiles_y &&
                           gauss_cones.scalar_type() == bounds.scalar_type() &&
                           tile_cones.scalar_type() == bounds.scalar_type()),
                "geer cpu_ops: gauss_cones must be [N,9] and tile_cones [tiles,10], in the bounds' dtype");
    TORCH_CHECK(tiles_x < (1 << 16) && tiles_y < (1 << 16), "geer cpu_ops: at most 65535 tiles along an axis");
    const geer::TilePyramid pyr = geer::make_tile_pyramid(int(tiles_x), int(tiles_y));
    TORCH_CHECK(node_bounds.size(0) == pyr.n_nodes && node_active.size(0) == pyr.n_nodes,
                "geer cpu_ops: node_bounds / node_active must hold the tile pyramid of a ", tiles_x, " x ", tiles_y,
                " grid (", pyr.n_nodes, " nodes)");
    const int64_t n = bounds.size(0), n_tiles = tiles_x * tiles_y;
    auto counts = at::zeros({n}, at::kInt), tests = at::zeros({n}, at::kInt);
    int32_t* cnt = counts.data_ptr<int32_t>();
    int32_t* tst = tests.data_ptr<int32_t>();
    std::vector<uint64_t> boxes(n);
    std::vector<int64_t> offsets(n + 1, 0);
    std::vector<int32_t> pair_tile, pair_gid;
    dispatch<int>(bounds, [&](auto tag) {
        using T = decltype(tag);
        const geer::PyramidNodes<T> nodes{ptr<T>(node_bounds), bptr(node_active), cones ? ptr<T>(tile_cones) : nullptr};
        auto gauss_cone = [&](int64_t i) { return cones ? ptr<T>(gauss_cones) + geer::kGaussConeValues * i : nullptr; };
        parallel(n, kGaussGrain, [&](int64_t i) {
            geer::TileBox box;
            int t;
            cnt[i] = geer::count_overlapping_tiles(ptr<T>(bounds) + 4 * i, gauss_cone(i), bptr(alive)[i] != 0, pyr, nodes, &t, &box);
            boxes[i] = geer::pack_box(box);
            tst[i] = t;
        });
        for (int64_t i = 0; i < n; ++i) offsets[i + 1] = offsets[i] + cnt[i];
        TORCH_CHECK(offsets[n] < (int64_t(1) << 31), "geer cpu_ops: more than 2^31 (tile, Gaussian) pairs");
        pair_tile.resize(offsets[n]);
        pair_gid.resize(offsets[n]);
        parallel(n, kGaussGrain, [&](int64_t i) {
            int64_t out = offsets[i];
            tst[i] += geer::emit_overlapping_tiles(ptr<T>(bounds) + 4 * i, gauss_cone(i), geer::unpack_box(boxes[i]), int(tiles_x),
                                                   nodes, [&](int tile) {
                                                       pair_tile[out] = tile;
                                                       pair_gid[out] = int32_t(i);
                                                       ++out;
                                                   });
        });
        return 0;
    });
    // Bucket the pairs by tile, visiting the Gaussians front to back (stable sort of their depth order, ties
    // by index): every tile's list comes out sorted by key, as the radix sort of all pairs leaves it.
    const int64_t m = offsets[n];
    const int32_t* ord = order.data_ptr<int32_t>();
    std::vector<int32_t> front_to_back(n);
    for (int64_t i = 0; i < n; ++i) front_to_back[i] = int32_t(i);
    std::stable_sort(front_to_back.begin(), front_to_back.end(),
                     [&](int32_t a, int32_t b) { return uint32_t(ord[a]) < uint32_t(ord[b]); });
    std::vector<int64_t> fill(n_tiles + 1, 0);
    for (int64_t e = 0; e < m; ++e) ++fill[pair_tile[e] + 1];
    for (int64_t t = 0; t < n_tiles; ++t) fill[t + 1] += fill[t];
    std::vector<uint64_t> keys(m);
    std::vector<int32_t> gids(m);
    for (const int32_t i : front_to_back)
        for (int64_t e = offsets[i]; e < offsets[i + 1]; ++e) {
            const int64_t j = fill[pair_tile[e]]++;
            keys[j] = geer::pair_key(pair_tile[e], uint32_t(ord[i]));
            gids[j] = i;
        }
    auto ids = at::empty({m}, at::kInt);
    std::copy(gids.begin(), gids.end(), ids.data_ptr<int32_t>());
    auto ranges = at::zeros({n_tiles, 2}, at::kInt);
    int32_t* rg = ranges.data_ptr<int32_t>();
    parallel(m, 4096, [&](int64_t j) { geer::mark_tile_range(keys.data(), m, j, rg); });
    return {ids, ranges, counts, tests};
}

// ------------------------------------------------------------------------------------ stage 4
std::vector<at::Tensor> preprocess_backward(at::Tensor means_c, at::Tensor quats, at::Tensor scales,
                                               at::Tensor sh, at::Tensor sh_dirs, at::Tensor rot_c,
                                               int64_t sh_degree, at::Tensor g_whiten, at::Tensor g_o_u,
                                               at::Tensor g_rgb, bool pose_grad, std::optional<at::Tensor> sh_degrees) {
    means_c = cpu(means_c); quats = cpu(quats); scales = cpu(scales); sh = cpu(sh); sh_dirs = cpu(sh_dirs);
    rot_c = cpu(rot_c); g_whiten = cpu(g_whiten); g_o_u = cpu(g_o_u); g_rgb = cpu(g_rgb);
    const at::Tensor own = own_degrees(sh_degrees, means_c.size(0));
    const int64_t n = means_c.size(0);
    auto opts = means_c.options();
    auto g_mc = at::zeros({n, 3}, opts), g_q = at::zeros({n, 4}, opts), g_s = at::zeros({n, 3}, opts);
    auto g_sh = at::zeros_like(sh), g_dirs = at::zeros({n, 3}, opts);
    auto g_rot_c = pose_grad ? at::empty({n, 3, 3}, opts) : at::empty({0}, opts);
    dispatch<int>(means_c, [&](auto tag) {
        using T = decltype(tag);
        const Mat3<T> rc = geer::load_mat3(ptr<T>(rot_c));
        const int64_t k = sh_degree >= 0 ? sh.size(1) : 0;
        parallel(n, kGaussGrain, [&](int64_t i) {
            Vec3<T> gm;
            geer::preprocess_backward_gaussian(geer::load3(ptr<T>(means_c) + 3 * i), ptr<T>(quats) + 4 * i,
                                               ptr<T>(scales) + 3 * i, rc, ptr<T>(g_whiten) + 9 * i,
                                               geer::load3(ptr<T>(g_o_u) + 3 * i), gm, mptr<T>(g_q) + 4 * i,
                                               mptr<T>(g_s) + 3 * i, pose_grad ? mptr<T>(g_rot_c) + 9 * i : nullptr);
            geer::store3(mptr<T>(g_mc) + 3 * i, gm);
            if (sh_degree < 0) return;
            Vec3<T> gd;
            const Vec3<T> dir = geer::load3(ptr<T>(sh_dirs) + 3 * i);
            // g_sh starts at zero: the bands above the Gaussian's degree stay 0.
            const int degree = geer::gaussian_sh_degree(int(sh_degree), degrees_ptr(own), i);
            geer::sh_backward(ptr<T>(sh) + 3 * k * i, degree, dir, geer::load3(ptr<T>(g_rgb) + 3 * i),
                              mptr<T>(g_sh) + 3 * k * i, gd);
            geer::store3(mptr<T>(g_dirs) + 3 * i, gd);
        });
        return 0;
    });
    return {g_mc, g_q, g_s, g_sh, g_dirs, g_rot_c};
}

at::Tensor mirror_tangent(at::Tensor theta) {
    theta = cpu(theta);
    auto out = at::empty_like(theta);
    dispatch<int>(theta, [&](auto tag) {
        using T = decltype(tag);
        for (int64_t i = 0; i < theta.numel(); ++i) mptr<T>(out)[i] = geer::mirror_tangent(ptr<T>(theta)[i]);
        return 0;
    });
    return out;
}

// associate._interval_pieces: [N,4] (a_lo, a_hi, b_lo, b_hi) in the mirror domain.
at::Tensor interval_pieces(at::Tensor lo, at::Tensor hi) {
    lo = cpu(lo); hi = cpu(hi);
    auto out = at::empty({lo.numel(), 4}, lo.options());
    dispatch<int>(lo, [&](auto tag) {
        using T = decltype(tag);
        for (int64_t i = 0; i < lo.numel(); ++i) {
            auto p = geer::interval_pieces(ptr<T>(lo)[i], ptr<T>(hi)[i]);
            T* o = mptr<T>(out) + 4 * i;
            o[0] = p.a_lo; o[1] = p.a_hi; o[2] = p.b_lo; o[3] = p.b_hi;
        }
        return 0;
    });
    return out;
}
}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "the geer kernels' code on the CPU (backend='cpu' and the tests)";
    namespace py = pybind11;
    // sh_degrees (each Gaussian's own SH degree, uint8 [N]) last and optional: callers without it are unchanged.
    m.def("preprocess_forward", &preprocess_forward, py::arg("means_c"), py::arg("quats"), py::arg("scales"),
          py::arg("opacities"), py::arg("sh"), py::arg("sh_dirs"), py::arg("rot_c"), py::arg("sh_degree"),
          py::arg("paper_lambda"), py::arg("sh_degrees") = py::none());
    m.def("associate", &associate);
    geer_cpu::register_render_ops(m);  // render_forward / _backward (+ _gpu_path), render_lanes, pair probes
    m.def("preprocess_backward", &preprocess_backward, py::arg("means_c"), py::arg("quats"), py::arg("scales"),
          py::arg("sh"), py::arg("sh_dirs"), py::arg("rot_c"), py::arg("sh_degree"), py::arg("g_whiten"),
          py::arg("g_o_u"), py::arg("g_rgb"), py::arg("pose_grad"), py::arg("sh_degrees") = py::none());
    m.def("mirror_tangent", &mirror_tangent);
    m.def("interval_pieces", &interval_pieces);
}
