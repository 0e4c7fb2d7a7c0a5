// CPU build of geer_math.h for tests/test_csrc_math.py: the CUDA pipeline's per-Gaussian, per-pair
// and per-ray math run in plain loops, behind the same operation names and signatures as the CUDA
// extension (bindings.cpp), so geer_ns/render/cuda_backend.py can drive either. What the GPU adds on
// top (shared-memory batches, warp reductions, atomics, radix sort) is not exercised here.
// ATen + pybind only (not torch/extension.h): half the compile time of this test-only build.
#include <ATen/ATen.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <numeric>
#include <vector>

#include "geer_math.h"

namespace {

using geer::GaussFrame;
using geer::Mat3;
using geer::Vec3;

template <typename T> const T* ptr(const at::Tensor& t) { return t.data_ptr<T>(); }
template <typename T> T* mptr(at::Tensor& t) { return t.data_ptr<T>(); }
const uint8_t* bptr(const at::Tensor& t) { return reinterpret_cast<const uint8_t*>(t.data_ptr<bool>()); }
uint8_t* mbptr(at::Tensor& t) { return reinterpret_cast<uint8_t*>(t.data_ptr<bool>()); }

at::Tensor cpu(const at::Tensor& t) { return t.contiguous().cpu(); }

void check_dtype(const at::Tensor& t) {
    TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble,
                "geer cpu_ops: float32 or float64 expected");
}

template <typename T, typename F> auto dispatch(const at::Tensor& t, F&& f) {
    check_dtype(t);
    if (t.scalar_type() == at::kFloat) return f(float{});
    return f(double{});
}

// ------------------------------------------------------------------------------------ stage 1
std::vector<at::Tensor> preprocess_forward(at::Tensor means_c, at::Tensor quats, at::Tensor scales,
                                              at::Tensor opacities, at::Tensor sh, at::Tensor means_w,
                                              at::Tensor cam_center, at::Tensor rot_c, int64_t sh_degree,
                                              bool paper_lambda) {
    means_c = cpu(means_c); quats = cpu(quats); scales = cpu(scales); opacities = cpu(opacities);
    sh = cpu(sh); means_w = cpu(means_w); cam_center = cpu(cam_center); rot_c = cpu(rot_c);
    const int64_t n = means_c.size(0);
    auto opts = means_c.options();
    auto whiten = at::zeros({n, 3, 3}, opts), o_u = at::zeros({n, 3}, opts), rgb = at::zeros({n, 3}, opts);
    auto bounds = at::zeros({n, 4}, opts);
    auto alive = at::zeros({n}, opts.dtype(at::kBool)), inside = at::zeros({n}, opts.dtype(at::kBool));
    dispatch<int>(means_c, [&](auto tag) {
        using T = decltype(tag);
        const Mat3<T> rc = geer::load_mat3(ptr<T>(rot_c));
        const Vec3<T> cam = geer::load3(ptr<T>(cam_center));
        const int64_t k = sh_degree >= 0 ? sh.size(1) : 0;
        for (int64_t i = 0; i < n; ++i) {
            auto g = geer::preprocess_gaussian(geer::load3(ptr<T>(means_c) + 3 * i), ptr<T>(quats) + 4 * i,
                                               ptr<T>(scales) + 3 * i, ptr<T>(opacities)[i], rc, paper_lambda);
            geer::store_mat3(mptr<T>(whiten) + 9 * i, g.w);
            geer::store3(mptr<T>(o_u) + 3 * i, g.o_u);
            for (int j = 0; j < 4; ++j) mptr<T>(bounds)[4 * i + j] = g.bounds[j];
            mbptr(alive)[i] = g.alive;
            mbptr(inside)[i] = g.camera_inside;
            if (sh_degree >= 0) {
                const Vec3<T> dir = geer::load3(ptr<T>(means_w) + 3 * i) - cam;
                geer::store3(mptr<T>(rgb) + 3 * i, geer::sh_to_color(ptr<T>(sh) + 3 * k * i, int(sh_degree), dir));
            }
        }
        return 0;
    });
    return {whiten, o_u, rgb, bounds, alive, inside};
}

// ------------------------------------------------------------------------------------ stage 2
std::vector<at::Tensor> associate(at::Tensor bounds, at::Tensor alive, at::Tensor rank,
                                     at::Tensor tile_bounds, at::Tensor active, at::Tensor col_bounds,
                                     at::Tensor row_bounds, int64_t tiles_x, int64_t tiles_y, bool separable) {
    bounds = cpu(bounds); alive = cpu(alive); rank = cpu(rank).to(at::kInt); tile_bounds = cpu(tile_bounds);
    active = cpu(active); col_bounds = cpu(col_bounds); row_bounds = cpu(row_bounds);
    const int64_t n = bounds.size(0), n_tiles = tile_bounds.size(0);
    std::vector<uint64_t> keys;
    std::vector<int32_t> gids;
    dispatch<int>(bounds, [&](auto tag) {
        using T = decltype(tag);
        geer::TileGrid<T> grid{ptr<T>(tile_bounds), bptr(active), int(n_tiles), int(tiles_x), int(tiles_y),
                               separable, separable ? ptr<T>(col_bounds) : nullptr,
                               separable ? ptr<T>(row_bounds) : nullptr};
        // Count, scan, emit: the two passes of associate.cu.
        std::vector<int64_t> offsets(n + 1, 0);
        for (int64_t i = 0; i < n; ++i)
            offsets[i + 1] = offsets[i] + geer::for_each_overlapping_tile(ptr<T>(bounds) + 4 * i, bptr(alive)[i] != 0,
                                                                         grid, [](int) {});
        keys.resize(offsets[n]);
        gids.resize(offsets[n]);
        for (int64_t i = 0; i < n; ++i) {
            int64_t out = offsets[i];
            const int r = ptr<int32_t>(rank)[i];
            geer::for_each_overlapping_tile(ptr<T>(bounds) + 4 * i, bptr(alive)[i] != 0, grid, [&](int tile) {
                keys[out] = geer::pair_key(tile, r);
                gids[out] = int32_t(i);
                ++out;
            });
        }
        return 0;
    });
    std::vector<int64_t> order(keys.size());
    std::iota(order.begin(), order.end(), 0);
    std::sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return keys[a] < keys[b]; });
    const int64_t m = int64_t(keys.size());
    auto ids = at::empty({m}, at::kInt);
    auto ranges = at::zeros({n_tiles, 2}, at::kInt);
    for (int64_t j = 0; j < m; ++j) {
        ids.data_ptr<int32_t>()[j] = gids[order[j]];
        const uint32_t tile = uint32_t(keys[order[j]] >> 32);
        if (j == 0 || uint32_t(keys[order[j - 1]] >> 32) != tile) ranges.data_ptr<int32_t>()[2 * tile] = int32_t(j);
        if (j == m - 1 || uint32_t(keys[order[j + 1]] >> 32) != tile)
            ranges.data_ptr<int32_t>()[2 * tile + 1] = int32_t(j + 1);
    }
    return {ids, ranges};
}

// ------------------------------------------------------------------------------------ stage 3
template <typename T>
std::vector<GaussFrame<T>> frames(const at::Tensor& whiten, const at::Tensor& o_u, const at::Tensor& rgb,
                                  const at::Tensor& opac) {
    const int64_t n = whiten.size(0);
    std::vector<GaussFrame<T>> f(n);
    for (int64_t i = 0; i < n; ++i)
        geer::make_frame(ptr<T>(whiten) + 9 * i, ptr<T>(o_u) + 3 * i, ptr<T>(rgb) + 3 * i, ptr<T>(opac)[i], f[i]);
    return f;
}

// Calls f(tile, ray) for every in-image ray slot, in the tile layout of raygrid._tile_ray_indices.
template <typename F> void for_each_tile_ray(int64_t height, int64_t width, int64_t ts, F&& f) {
    const int64_t tx = (width + ts - 1) / ts, ty = (height + ts - 1) / ts;
    for (int64_t tile = 0; tile < tx * ty; ++tile)
        for (int64_t k = 0; k < ts * ts; ++k) {
            const int64_t row = (tile / tx) * ts + k / ts, col = (tile % tx) * ts + k % ts;
            if (row < height && col < width) f(tile, row * width + col);
        }
}

std::vector<at::Tensor> render_forward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb,
                                          at::Tensor opacities, at::Tensor dirs, at::Tensor valid, at::Tensor ids,
                                          at::Tensor ranges, int64_t height, int64_t width, int64_t tile_size) {
    whiten = cpu(whiten); o_u = cpu(o_u); rgb = cpu(rgb); opacities = cpu(opacities);
    dirs = cpu(dirs); valid = cpu(valid); ids = cpu(ids); ranges = cpu(ranges);
    const int64_t r = height * width;
    auto opts = whiten.options();
    auto out_rgb = at::zeros({r, 3}, opts), depth = at::zeros({r}, opts), acc = at::zeros({r}, opts);
    auto t_final = at::ones({r}, opts);
    auto n_contrib = at::zeros({r}, at::kInt);
    dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        const auto f = frames<T>(whiten, o_u, rgb, opacities);
        for_each_tile_ray(height, width, tile_size, [&](int64_t tile, int64_t ray) {
            const int start = ranges.data_ptr<int32_t>()[2 * tile], end = ranges.data_ptr<int32_t>()[2 * tile + 1];
            geer::RayForward<T> st;
            geer::ray_forward_init(st, bptr(valid)[ray] != 0);
            const Vec3<T> d = geer::load3(ptr<T>(dirs) + 3 * ray);
            for (int j = start; j < end && !st.done; ++j)
                geer::ray_forward_step(st, f[ids.data_ptr<int32_t>()[j]], d, j - start);
            for (int c = 0; c < 3; ++c) mptr<T>(out_rgb)[3 * ray + c] = st.rgb[c];
            mptr<T>(depth)[ray] = st.depth;
            mptr<T>(acc)[ray] = st.acc;
            mptr<T>(t_final)[ray] = st.trans;
            n_contrib.data_ptr<int32_t>()[ray] = st.n_contrib;
        });
        return 0;
    });
    return {out_rgb, depth, acc, t_final, n_contrib};
}

std::vector<at::Tensor> render_backward(at::Tensor whiten, at::Tensor o_u, at::Tensor rgb,
                                           at::Tensor opacities, at::Tensor dirs, at::Tensor valid,
                                           at::Tensor ids, at::Tensor ranges,
                                           int64_t height, int64_t width, int64_t tile_size, at::Tensor t_final,
                                           at::Tensor n_contrib, at::Tensor g_rgb, at::Tensor g_depth,
                                           at::Tensor g_acc) {
    whiten = cpu(whiten); o_u = cpu(o_u); rgb = cpu(rgb); opacities = cpu(opacities);
    dirs = cpu(dirs); valid = cpu(valid); ids = cpu(ids); ranges = cpu(ranges); t_final = cpu(t_final);
    n_contrib = cpu(n_contrib); g_rgb = cpu(g_rgb); g_depth = cpu(g_depth); g_acc = cpu(g_acc);
    const int64_t n = whiten.size(0);
    auto opts = whiten.options();
    auto gw = at::zeros({n, 3, 3}, opts), go = at::zeros({n, 3}, opts), gc = at::zeros({n, 3}, opts);
    auto gs = at::zeros({n}, opts);
    dispatch<int>(whiten, [&](auto tag) {
        using T = decltype(tag);
        const auto f = frames<T>(whiten, o_u, rgb, opacities);
        for_each_tile_ray(height, width, tile_size, [&](int64_t tile, int64_t ray) {
            if (!bptr(valid)[ray]) return;
            const int start = ranges.data_ptr<int32_t>()[2 * tile];
            geer::RayBackward<T> st;
            st.trans = ptr<T>(t_final)[ray];
            st.rec = T(0);
            for (int c = 0; c < 3; ++c) st.g_rgb[c] = ptr<T>(g_rgb)[3 * ray + c];
            st.g_depth = ptr<T>(g_depth)[ray];
            st.g_acc = ptr<T>(g_acc)[ray];
            const Vec3<T> d = geer::load3(ptr<T>(dirs) + 3 * ray);
            for (int pos = n_contrib.data_ptr<int32_t>()[ray] - 1; pos >= 0; --pos) {
                const int g = ids.data_ptr<int32_t>()[start + pos];
                geer::PairGrad<T> p;
                if (!geer::ray_backward_step(st, f[g], d, p)) continue;
                for (int i = 0; i < 9; ++i) mptr<T>(gw)[9 * g + i] += p.w[i];
                for (int i = 0; i < 3; ++i) {
                    mptr<T>(go)[3 * g + i] += p.o[i];
                    mptr<T>(gc)[3 * g + i] += p.rgb[i];
                }
                mptr<T>(gs)[g] += p.opacity;
            }
        });
        return 0;
    });
    return {gw, go, gc, gs};
}

// ------------------------------------------------------------------------------------ stage 4
std::vector<at::Tensor> preprocess_backward(at::Tensor means_c, at::Tensor quats, at::Tensor scales,
                                               at::Tensor sh, at::Tensor means_w, at::Tensor cam_center,
                                               at::Tensor rot_c, int64_t sh_degree, at::Tensor g_whiten,
                                               at::Tensor g_o_u, at::Tensor g_rgb) {
    means_c = cpu(means_c); quats = cpu(quats); scales = cpu(scales); sh = cpu(sh); means_w = cpu(means_w);
    cam_center = cpu(cam_center); rot_c = cpu(rot_c); g_whiten = cpu(g_whiten); g_o_u = cpu(g_o_u);
    g_rgb = cpu(g_rgb);
    const int64_t n = means_c.size(0);
    auto opts = means_c.options();
    auto g_mc = at::zeros({n, 3}, opts), g_q = at::zeros({n, 4}, opts), g_s = at::zeros({n, 3}, opts);
    auto g_sh = at::zeros_like(sh), g_mw = at::zeros({n, 3}, opts);
    dispatch<int>(means_c, [&](auto tag) {
        using T = decltype(tag);
        const Mat3<T> rc = geer::load_mat3(ptr<T>(rot_c));
        const Vec3<T> cam = geer::load3(ptr<T>(cam_center));
        const int64_t k = sh_degree >= 0 ? sh.size(1) : 0;
        for (int64_t i = 0; i < n; ++i) {
            Vec3<T> gm;
            geer::preprocess_backward_gaussian(geer::load3(ptr<T>(means_c) + 3 * i), ptr<T>(quats) + 4 * i,
                                               ptr<T>(scales) + 3 * i, rc, ptr<T>(g_whiten) + 9 * i,
                                               geer::load3(ptr<T>(g_o_u) + 3 * i), gm, mptr<T>(g_q) + 4 * i,
                                               mptr<T>(g_s) + 3 * i);
            geer::store3(mptr<T>(g_mc) + 3 * i, gm);
            if (sh_degree < 0) continue;
            Vec3<T> gd;
            const Vec3<T> dir = geer::load3(ptr<T>(means_w) + 3 * i) - cam;
            geer::sh_backward(ptr<T>(sh) + 3 * k * i, int(sh_degree), dir, geer::load3(ptr<T>(g_rgb) + 3 * i),
                              mptr<T>(g_sh) + 3 * k * i, gd);
            geer::store3(mptr<T>(g_mw) + 3 * i, gd);
        }
        return 0;
    });
    return {g_mc, g_q, g_s, g_sh, g_mw};
}

// ------------------------------------------------------------------------------------ primitives
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
            geer::make_frame(ptr<T>(whiten) + 9 * i, ptr<T>(o_u) + 3 * i, zero, ptr<T>(opac)[i], f);
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
            geer::make_frame(ptr<T>(whiten) + 9 * i, ptr<T>(o_u) + 3 * i, zero, T(1), f);
            const Vec3<T> d = geer::load3(ptr<T>(dirs) + 3 * i);
            auto e = geer::eval_pair(f, d);
            Vec3<T> g;
            geer::pair_response_backward(e, geer::load3(ptr<T>(o_u) + 3 * i), d, ptr<T>(g_d2)[i], ptr<T>(g_t)[i], g,
                                         mptr<T>(gw) + 9 * i);
            geer::store3(mptr<T>(go) + 3 * i, g);
        }
        return 0;
    });
    return {go, gw};
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
    m.doc() = "geer_math.h on the CPU (tests only)";
    m.def("preprocess_forward", &preprocess_forward);
    m.def("associate", &associate);
    m.def("render_forward", &render_forward);
    m.def("render_backward", &render_backward);
    m.def("preprocess_backward", &preprocess_backward);
    m.def("pair_eval", &pair_eval);
    m.def("pair_backward", &pair_backward);
    m.def("mirror_tangent", &mirror_tangent);
    m.def("interval_pieces", &interval_pieces);
}
