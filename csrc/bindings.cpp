// Torch glue for the 3DGEER CUDA stages: checks tensors, allocates outputs, fills the launcher
// structs of geer_launchers.h and runs them on the current stream. The same operation names and
// signatures are implemented on the CPU by cpu_ops.cpp; geer_ns/render/cuda_backend.py drives
// either one.
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <ATen/ATen.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <optional>
#include <vector>

#include "geer_associate.h"
#include "geer_blocks.h"
#include "geer_launchers.h"
#include "geer_order.h"

namespace {

void check_input(const at::Tensor& t, const char* name) {
    TORCH_CHECK(t.is_cuda(), "geer: ", name, " must be a CUDA tensor");
    TORCH_CHECK(t.is_contiguous(), "geer: ", name, " must be contiguous");
}

void check_float(const at::Tensor& t, const at::Tensor& ref, const char* name) {
    check_input(t, name);
    TORCH_CHECK(t.scalar_type() == ref.scalar_type(), "geer: ", name, " must be ", ref.scalar_type());
}

void check_kind(const at::Tensor& t, at::ScalarType type, const char* name) {
    check_input(t, name);
    TORCH_CHECK(t.scalar_type() == type, "geer: ", name, " must be ", type);
}

template <typename T> const T* cptr(const at::Tensor& t) { return t.numel() ? t.data_ptr<T>() : nullptr; }
template <typename T> T* mptr(at::Tensor& t) { return t.numel() ? t.data_ptr<T>() : nullptr; }
const uint8_t* bptr(const at::Tensor& t) { return t.numel() ? reinterpret_cast<const uint8_t*>(t.data_ptr<bool>()) : nullptr; }
uint8_t* mbptr(at::Tensor& t) { return t.numel() ? reinterpret_cast<uint8_t*>(t.data_ptr<bool>()) : nullptr; }

cudaStream_t stream() { return c10::cuda::getCurrentCUDAStream().stream(); }

// Small per-view constants (camera centre, rotation) stay on the device: the kernels read them in place
// (a host copy here would be a device-to-host sync in every forward and backward).
void check_view_constant(const at::Tensor& t, const at::Tensor& ref, int64_t count, const char* name) {
    check_float(t, ref, name);
    TORCH_CHECK(t.numel() == count, "geer: ", name, " must hold ", count, " values, got ", t.numel());
}

template <typename F> void dispatch(const at::Tensor& t, F&& f) {
    if (t.scalar_type() == at::kFloat) f(float{});
    else if (t.scalar_type() == at::kDouble) f(double{});
    else TORCH_CHECK(false, "geer: float32 or float64 expected, got ", t.scalar_type());
}

template <typename T>
geer::PreprocessArgs<T> preprocess_args(const at::Tensor& means_c, const at::Tensor& quats, const at::Tensor& scales,
                                        const at::Tensor& opacities, const at::Tensor& sh, const at::Tensor& sh_dirs,
                                        const at::Tensor& rot_c, int64_t sh_degree, bool paper_lambda,
                                        const std::optional<at::Tensor>& sh_degrees) {
    check_float(means_c, means_c, "means_c");
    check_float(quats, means_c, "quats");
    check_float(scales, means_c, "scales");
    if (opacities.defined()) check_float(opacities, means_c, "opacities");
    TORCH_CHECK(sh_degree >= -1 && sh_degree <= 3, "geer: sh_degree must be in -1..3");
    geer::PreprocessArgs<T> a{};
    a.n = int(means_c.size(0));
    a.means_c = cptr<T>(means_c);
    a.quats = cptr<T>(quats);
    a.scales = cptr<T>(scales);
    a.opacities = opacities.defined() ? cptr<T>(opacities) : nullptr;
    a.sh_degree = int(sh_degree);
    if (sh_degree >= 0) {
        check_float(sh, means_c, "sh");
        check_float(sh_dirs, means_c, "sh_dirs");
        TORCH_CHECK(sh.dim() == 3 && sh.size(1) >= (sh_degree + 1) * (sh_degree + 1) && sh.size(2) == 3,
                    "geer: sh must be [N, K >= (degree+1)^2, 3]");
        a.sh = cptr<T>(sh);
        a.sh_k = int(sh.size(1));
        a.sh_dirs = cptr<T>(sh_dirs);
        if (sh_degrees.has_value() && sh_degrees->numel() > 0) {
            check_kind(*sh_degrees, at::kByte, "sh_degrees");
            TORCH_CHECK(sh_degrees->numel() == a.n, "geer: sh_degrees must hold one degree per Gaussian");
            a.sh_degrees = sh_degrees->data_ptr<uint8_t>();
        }
    }
    check_view_constant(rot_c, means_c, 9, "rot_c");
    a.rot_c = cptr<T>(rot_c);
    a.paper_lambda = paper_lambda ? 1 : 0;
    return a;
}

// ------------------------------------------------------------------------------------ stage 1
std::vector<at::Tensor> preprocess_forward(at::Tensor means_c, at::Tensor quats, at::Tensor scales,
                                           at::Tensor opacities, at::Tensor sh, at::Tensor sh_dirs,
                                           at::Tensor rot_c, int64_t sh_degree, bool paper_lambda,
                                           std::optional<at::Tensor> sh_degrees) {
    const c10::cuda::OptionalCUDAGuard guard(device_of(means_c));
    const int64_t n = means_c.size(0);
    auto opts = means_c.options();
    auto whiten = at::empty({n, 3, 3}, opts), o_u = at::empty({n, 3}, opts), rgb = at::zeros({n, 3}, opts);
    auto bounds = at::empty({n, 4}, opts);
    auto alive = at::empty({n}, opts.dtype(at::kBool)), inside = at::empty({n}, opts.dtype(at::kBool));
    dispatch(means_c, [&](auto tag) {
        using T = decltype(tag);
        auto a = preprocess_args<T>(means_c, quats, scales, opacities, sh, sh_dirs, rot_c, sh_degree, paper_lambda,
                                     sh_degrees);
        a.whiten = mptr<T>(whiten);
        a.o_u = mptr<T>(o_u);
        a.rgb = mptr<T>(rgb);
        a.bounds = mptr<T>(bounds);
        a.alive = mbptr(alive);
        a.inside = mbptr(inside);
        geer::launch_preprocess_forward<T>(a, stream());
    });
    return {whiten, o_u, rgb, bounds, alive, inside};
}

// ------------------------------------------------------------------------------------ stage 2
// -> (ids sorted by (tile, depth order), ranges [T,2], counts [N] tiles per Gaussian, tests [N] tile tests).
std::vector<at::Tensor> associate(at::Tensor bounds, at::Tensor alive, at::Tensor order, at::Tensor node_bounds,
                                  at::Tensor node_active, int64_t tiles_x, int64_t tiles_y, at::Tensor gauss_cones,
                                  at::Tensor tile_cones) {
    const c10::cuda::OptionalCUDAGuard guard(device_of(bounds));
    check_float(bounds, bounds, "bounds");
    check_kind(alive, at::kBool, "alive");
    check_kind(order, at::kInt, "order");
    check_float(node_bounds, bounds, "node_bounds");
    check_kind(node_active, at::kBool, "node_active");
    TORCH_CHECK(tiles_x < (1 << 16) && tiles_y < (1 << 16), "geer: at most 65535 tiles along an axis");
    const int64_t n = bounds.size(0), n_tiles = tiles_x * tiles_y;
    // Empty cones: the box test alone (the association before the cone test).
    const bool cones = gauss_cones.numel() > 0 && tile_cones.numel() > 0;
    if (cones) {
        check_float(gauss_cones, bounds, "gauss_cones");
        check_float(tile_cones, bounds, "tile_cones");
        TORCH_CHECK(gauss_cones.numel() == geer::kGaussConeValues * n && tile_cones.numel() == geer::kTileConeValues * n_tiles,
                    "geer: gauss_cones must be [N,9] and tile_cones [tiles,10]");
    }
    TORCH_CHECK(node_bounds.size(0) == geer::make_tile_pyramid(int(tiles_x), int(tiles_y)).n_nodes &&
                    node_active.size(0) == node_bounds.size(0),
                "geer: node_bounds / node_active must hold the tile pyramid of a ", tiles_x, " x ", tiles_y, " grid");
    auto iopts = bounds.options().dtype(at::kInt);
    auto ranges = at::zeros({n_tiles, 2}, iopts);
    auto counts = at::zeros({n}, iopts), tests = at::zeros({n}, iopts);
    at::Tensor ids_sorted;
    dispatch(bounds, [&](auto tag) {
        using T = decltype(tag);
        geer::AssociateArgs<T> a{};
        a.n = int(n);
        a.bounds = cptr<T>(bounds);
        a.alive = bptr(alive);
        a.order = cptr<int32_t>(order);
        a.node_bounds = cptr<T>(node_bounds);
        a.node_active = bptr(node_active);
        a.gauss_cones = cones ? cptr<T>(gauss_cones) : nullptr;
        a.tile_cones = cones ? cptr<T>(tile_cones) : nullptr;
        a.tiles_x = int(tiles_x);
        a.tiles_y = int(tiles_y);
        auto boxes = at::empty({n}, bounds.options().dtype(at::kLong));
        auto* box_ptr = reinterpret_cast<uint64_t*>(mptr<int64_t>(boxes));
        geer::launch_count_tiles<T>(a, mptr<int32_t>(counts), box_ptr, mptr<int32_t>(tests), stream());
        auto inclusive = at::cumsum(counts, 0, at::kLong);
        const int64_t m = n ? inclusive[n - 1].item<int64_t>() : 0;  // one host sync: the pair count
        TORCH_CHECK(m < (int64_t(1) << 31), "geer: more than 2^31 (tile, Gaussian) pairs");
        auto offsets = (inclusive - counts).contiguous();
        auto keys = at::empty({m}, bounds.options().dtype(at::kLong));
        auto ids = at::empty({m}, iopts);
        geer::launch_emit_pairs<T>(a, box_ptr, mptr<int64_t>(offsets), reinterpret_cast<uint64_t*>(mptr<int64_t>(keys)),
                                   mptr<int32_t>(ids), mptr<int32_t>(tests), stream());
        int tile_bits = 0;
        while ((int64_t(1) << tile_bits) < n_tiles) ++tile_bits;
        const int end_bit = 32 + tile_bits;
        auto keys_sorted = at::empty_like(keys);
        ids_sorted = at::empty_like(ids);
        const size_t temp_bytes = geer::sort_pairs_temp_bytes(m, end_bit);
        auto temp = at::empty({int64_t(temp_bytes)}, bounds.options().dtype(at::kByte));
        geer::sort_pairs(mptr<uint8_t>(temp), temp_bytes, reinterpret_cast<const uint64_t*>(cptr<int64_t>(keys)),
                         reinterpret_cast<uint64_t*>(mptr<int64_t>(keys_sorted)), cptr<int32_t>(ids),
                         mptr<int32_t>(ids_sorted), m, end_bit, stream());
        geer::launch_tile_ranges(reinterpret_cast<const uint64_t*>(cptr<int64_t>(keys_sorted)), m,
                                 mptr<int32_t>(ranges), stream());
    });
    return {ids_sorted, ranges, counts, tests};
}

// ------------------------------------------------------------------------------------ stage 3
template <typename T>
geer::RenderArgs<T> render_args(const at::Tensor& whiten, const at::Tensor& o_u, const at::Tensor& rgb,
                                const at::Tensor& opacities, const at::Tensor& pbf_pieces, const at::Tensor& dirs,
                                const at::Tensor& ray_bounds, const at::Tensor& warp_bounds, const at::Tensor& valid,
                                const at::Tensor& ids, const at::Tensor& ranges, int64_t height, int64_t width,
                                int64_t tile_size, const at::Tensor& origins) {
    check_float(whiten, whiten, "whiten");
    check_float(o_u, whiten, "o_u");
    check_float(rgb, whiten, "rgb");
    check_float(opacities, whiten, "opacities");
    check_float(pbf_pieces, whiten, "pbf_pieces");
    check_float(dirs, whiten, "dirs");
    check_float(ray_bounds, whiten, "ray_bounds");
    check_float(warp_bounds, whiten, "warp_bounds");
    check_kind(valid, at::kBool, "valid");
    check_kind(ids, at::kInt, "ids");
    check_kind(ranges, at::kInt, "ranges");
    TORCH_CHECK(tile_size >= 1 && tile_size <= 32, "geer: tile_size must be in 1..32 (one thread per ray)");
    TORCH_CHECK(dirs.size(0) == height * width, "geer: dirs must hold height * width rays");
    TORCH_CHECK(pbf_pieces.numel() == 8 * whiten.size(0), "geer: pbf_pieces must be [N,8]");
    TORCH_CHECK(ray_bounds.numel() == 4 * dirs.size(0), "geer: ray_bounds must be [R,4]");
    const int64_t n_tiles = ((height + tile_size - 1) / tile_size) * ((width + tile_size - 1) / tile_size);
    TORCH_CHECK(ranges.size(0) == n_tiles, "geer: ranges must hold one row per tile");
    TORCH_CHECK(warp_bounds.numel() == 4 * n_tiles * geer::warps_per_tile(int(tile_size)),
                "geer: warp_bounds must be [tiles * warps per tile, 4]");
    const bool with_origins = origins.numel() > 0;  // empty: every ray from the camera centre
    if (with_origins) {
        check_float(origins, whiten, "origins");
        TORCH_CHECK(origins.numel() == 3 * dirs.size(0), "geer: origins must be [R,3] or empty");
    }
    geer::RenderArgs<T> a{};
    a.n = int(whiten.size(0));
    a.origins = with_origins ? cptr<T>(origins) : nullptr;
    a.whiten = cptr<T>(whiten);
    a.o_u = cptr<T>(o_u);
    a.rgb = cptr<T>(rgb);
    a.opacities = cptr<T>(opacities);
    a.pbf_pieces = cptr<T>(pbf_pieces);
    a.dirs = cptr<T>(dirs);
    a.ray_bounds = cptr<T>(ray_bounds);
    a.warp_bounds = cptr<T>(warp_bounds);
    a.valid = bptr(valid);
    a.ids = cptr<int32_t>(ids);
    a.ranges = cptr<int32_t>(ranges);
    a.height = int(height);
    a.width = int(width);
    a.tile_size = int(tile_size);
    return a;
}

// Each ray in its own order where order_lower [N] is given (geer_order.h): the entries' release bounds [M], made
// on the device and set in a (kept alive by the returned tensor); empty for the per-view order. The kernels hold
// kGpuWindow pending pairs a ray (window 0, the exact order, runs it too: exact while a ray holds at most that).
template <typename T>
at::Tensor order_bounds(geer::RenderArgs<T>& a, const at::Tensor& whiten, const at::Tensor& ids,
                        const at::Tensor& order_lower, int64_t order_window) {
    if (order_lower.numel() == 0) return at::empty({0}, whiten.options());
    check_float(order_lower, whiten, "order_lower");
    TORCH_CHECK(order_lower.numel() == whiten.size(0), "geer: order_lower must be [N]");
    TORCH_CHECK(order_window == 0 || order_window == geer::kGpuWindow, "geer: the CUDA kernels hold ",
                geer::kGpuWindow, " pending pairs a ray (order 'ray' or 'ray:", geer::kGpuWindow, "'), got a window of ",
                order_window);
    auto bounds = at::empty({std::max<int64_t>(ids.numel(), 1)}, whiten.options());  // non-empty: the mode
    geer::launch_release_bounds<T>(a, cptr<T>(order_lower), mptr<T>(bounds), stream());
    a.order_bounds = cptr<T>(bounds);
    a.order_lower = cptr<T>(order_lower);
    return bounds;
}

std::vector<at::Tensor> render_forward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                                       at::Tensor pbf_pieces, at::Tensor dirs, at::Tensor ray_bounds,
                                       at::Tensor warp_bounds, at::Tensor valid, at::Tensor ids,
                                       at::Tensor ranges, int64_t height, int64_t width, int64_t tile_size,
                                       bool /* record: the CPU build's blended_lanes, see below */,
                                       at::Tensor origins, at::Tensor order_lower, int64_t order_window) {
    const c10::cuda::OptionalCUDAGuard guard(device_of(whiten));
    const int64_t r = height * width;
    auto opts = whiten.options();
    auto out_rgb = at::empty({r, 3}, opts), depth = at::empty({r}, opts), acc = at::empty({r}, opts);
    auto t_final = at::empty({r}, opts), median = at::empty({r}, opts);
    auto n_contrib = at::empty({r}, opts.dtype(at::kInt));
    auto max_weight = at::zeros({whiten.size(0)}, opts);
    dispatch(whiten, [&](auto tag) {
        using T = decltype(tag);
        auto a = render_args<T>(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids,
                                ranges, height, width, tile_size, origins);
        geer::RenderOutputs<T> out{mptr<T>(out_rgb), mptr<T>(depth), mptr<T>(acc), mptr<T>(t_final),
                                   mptr<int32_t>(n_contrib), mptr<T>(max_weight), mptr<T>(median)};
        auto bounds = order_bounds<T>(a, whiten, ids, order_lower, order_window);
        if (bounds.numel() > 0) geer::launch_render_forward_ordered<T>(a, out, stream());
        else geer::launch_render_forward<T>(a, out, stream());
    });
    // The CPU build also records which lanes blended each entry for its backward; the kernels do not (a
    // 32-bit word per entry and warp), and their backward re-derives them: an empty record.
    return {out_rgb, depth, acc, t_final, n_contrib, at::empty({0}, opts.dtype(at::kInt)), max_weight, median};
}

// -> ([N,16] gradient rows (geer_launchers.h RenderGradArgs::grads), absgrad [N,2], empty when absgrad_rows is,
// dL/d(ray directions) [R,3], empty unless dir_grad, dL/d(ray origins) [R,3], empty unless dir_grad and origins).
std::vector<at::Tensor> render_backward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb, at::Tensor opacities,
                                        at::Tensor pbf_pieces, at::Tensor dirs, at::Tensor ray_bounds,
                                        at::Tensor warp_bounds, at::Tensor valid, at::Tensor ids, at::Tensor ranges,
                                        int64_t height, int64_t width, int64_t tile_size, at::Tensor t_final,
                                        at::Tensor n_contrib,
                                        at::Tensor /* blended_lanes: empty, see render_forward */, at::Tensor g_rgb,
                                        at::Tensor g_depth, at::Tensor g_acc, at::Tensor absgrad_rows,
                                        bool dir_grad, at::Tensor origins, at::Tensor order_lower,
                                        int64_t order_window, at::Tensor ray_totals) {
    const c10::cuda::OptionalCUDAGuard guard(device_of(whiten));
    const int64_t n = whiten.size(0);
    auto opts = whiten.options();
    auto grads = at::zeros({n, geer::kGradValues}, opts);
    const bool with_absgrad = absgrad_rows.numel() > 0;
    auto absgrad = with_absgrad ? at::zeros({n, geer::kAbsgradValues}, opts) : at::empty({0}, opts);
    auto g_dirs = dir_grad ? at::zeros({height * width, 3}, opts) : at::empty({0}, opts);
    const bool origin_grad = dir_grad && origins.numel() > 0;
    auto g_origins = origin_grad ? at::zeros({height * width, 3}, opts) : at::empty({0}, opts);
    dispatch(whiten, [&](auto tag) {
        using T = decltype(tag);
        auto a = render_args<T>(whiten, o_u, rgb, opacities, pbf_pieces, dirs, ray_bounds, warp_bounds, valid, ids,
                                ranges, height, width, tile_size, origins);
        check_float(t_final, whiten, "t_final");
        check_kind(n_contrib, at::kInt, "n_contrib");
        check_float(g_rgb, whiten, "g_rgb");
        check_float(g_depth, whiten, "g_depth");
        check_float(g_acc, whiten, "g_acc");
        if (with_absgrad) {
            check_float(absgrad_rows, whiten, "absgrad_rows");
            TORCH_CHECK(absgrad_rows.numel() == geer::kAbsgradRow * n, "geer: absgrad_rows must be [N,6]");
        }
        geer::RenderGradArgs<T> g{cptr<T>(t_final), cptr<int32_t>(n_contrib), cptr<T>(g_rgb), cptr<T>(g_depth),
                                  cptr<T>(g_acc), mptr<T>(grads),
                                  with_absgrad ? cptr<T>(absgrad_rows) : nullptr, mptr<T>(absgrad),
                                  dir_grad ? mptr<T>(g_dirs) : nullptr, origin_grad ? mptr<T>(g_origins) : nullptr,
                                  nullptr};
        auto bounds = order_bounds<T>(a, whiten, ids, order_lower, order_window);
        if (bounds.numel() > 0) {
            check_float(ray_totals, whiten, "ray_totals");
            TORCH_CHECK(ray_totals.numel() == height * width, "geer: ray_totals must be [R]");
            g.ray_totals = cptr<T>(ray_totals);
            geer::launch_render_backward_ordered<T>(a, g, stream());
        } else {
            geer::launch_render_backward<T>(a, g, stream());
        }
    });
    return {grads, absgrad, g_dirs, g_origins};
}

// ------------------------------------------------------------------------------------ stage 4
std::vector<at::Tensor> preprocess_backward(at::Tensor means_c, at::Tensor quats, at::Tensor scales, at::Tensor sh,
                                            at::Tensor sh_dirs, at::Tensor rot_c, int64_t sh_degree,
                                            at::Tensor g_whiten, at::Tensor g_o_u, at::Tensor g_rgb, bool pose_grad,
                                            std::optional<at::Tensor> sh_degrees) {
    const c10::cuda::OptionalCUDAGuard guard(device_of(means_c));
    const int64_t n = means_c.size(0);
    auto opts = means_c.options();
    auto g_mc = at::empty({n, 3}, opts), g_q = at::empty({n, 4}, opts), g_s = at::empty({n, 3}, opts);
    auto g_sh = sh_degree >= 0 ? at::empty_like(sh) : at::empty({0}, opts);
    auto g_dirs = at::zeros({n, 3}, opts);
    auto g_rot_c = pose_grad ? at::empty({n, 3, 3}, opts) : at::empty({0}, opts);
    dispatch(means_c, [&](auto tag) {
        using T = decltype(tag);
        auto a = preprocess_args<T>(means_c, quats, scales, at::Tensor(), sh, sh_dirs, rot_c, sh_degree, false,
                                     sh_degrees);
        check_float(g_whiten, means_c, "g_whiten");
        check_float(g_o_u, means_c, "g_o_u");
        if (sh_degree >= 0) check_float(g_rgb, means_c, "g_rgb");
        geer::PreprocessGradArgs<T> g{cptr<T>(g_whiten), cptr<T>(g_o_u), sh_degree >= 0 ? cptr<T>(g_rgb) : nullptr,
                                      mptr<T>(g_mc),     mptr<T>(g_q),   mptr<T>(g_s),
                                      sh_degree >= 0 ? mptr<T>(g_sh) : nullptr, mptr<T>(g_dirs),
                                      pose_grad ? mptr<T>(g_rot_c) : nullptr};
        geer::launch_preprocess_backward<T>(a, g, stream());
    });
    return {g_mc, g_q, g_s, g_sh, g_dirs, g_rot_c};
}

// ------------------------------------------------------------------------------------ checks
// A trivial kernel with `threads` per block on `like`'s device; returns the block size it saw. Over 1024
// threads the launch is refused and this raises (tests/test_cuda_gpu.py: a failed launch raises at its call).
at::Tensor launch_probe(at::Tensor like, int64_t threads) {
    const c10::cuda::OptionalCUDAGuard guard(device_of(like));
    check_input(like, "like");
    auto out = at::full({1}, -1, like.options().dtype(at::kInt));
    geer::launch_probe(int(threads), mptr<int32_t>(out), stream());
    return out;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "3DGEER CUDA kernels (geer_ns.render.cuda_backend)";
    namespace py = pybind11;
    // sh_degrees (each Gaussian's own SH degree, uint8 [N]) last and optional: callers without it are unchanged.
    m.def("preprocess_forward", &preprocess_forward, py::arg("means_c"), py::arg("quats"), py::arg("scales"),
          py::arg("opacities"), py::arg("sh"), py::arg("sh_dirs"), py::arg("rot_c"), py::arg("sh_degree"),
          py::arg("paper_lambda"), py::arg("sh_degrees") = py::none());
    m.def("associate", &associate);
    m.def("render_forward", &render_forward);
    m.def("render_backward", &render_backward);
    m.def("preprocess_backward", &preprocess_backward, py::arg("means_c"), py::arg("quats"), py::arg("scales"),
          py::arg("sh"), py::arg("sh_dirs"), py::arg("rot_c"), py::arg("sh_degree"), py::arg("g_whiten"),
          py::arg("g_o_u"), py::arg("g_rgb"), py::arg("pose_grad"), py::arg("sh_degrees") = py::none());
    m.def("launch_probe", &launch_probe);
}
