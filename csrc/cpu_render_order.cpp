// Stage 3 of the CPU build in each ray's own order (geer_order.h), forward and backward: the tile loops of
// cpu_render.cpp / cpu_render_backward.cpp, with each ray's pending pairs in a heap. Evaluation in packs of rays
// where the build has AVX2 (the keep test of every pair); the heaps, blends and gradients one ray at a time,
// as a GPU thread (render_order.cu) runs them. The kernels' path (kPacks false) gives the same bits.
#include <algorithm>
#include <vector>

#include "cpu_render.h"
#include "geer_order.h"

namespace geer_cpu {

namespace {

using geer::Pending;

// The CPU's heap of pending pairs: a window of `capacity` pairs (the GPU's WindowHeap, the same bits), or,
// with capacity 0, as many as a ray holds (the exact order).
template <typename T> struct VectorHeap {
    std::vector<Pending<T>> item;
    int size = 0;
    int capacity = 0;
    bool full() {
        if (capacity > 0) return size == capacity;
        if (size == int(item.size())) item.resize(std::max<size_t>(16, 2 * item.size()));
        return false;
    }
    const Pending<T>& top() const { return item[0]; }
    void push(const Pending<T>& p) {
        if (size == int(item.size())) item.resize(std::max<size_t>(16, 2 * item.size()));
        geer::heap_push(item.data(), size, p);
    }
    Pending<T> pop() { return geer::heap_pop(item.data(), size); }
    void clear() { size = 0; }
    Pending<T>* data() { return item.data(); }
};

template <typename T> std::vector<VectorHeap<T>> heaps(int n, int64_t window) {
    std::vector<VectorHeap<T>> h(n);
    for (auto& x : h) x.capacity = int(window);
    return h;
}

// Per warp, a lower bound of its rays' smallest pending key: a warp whose rays hold nothing the bound releases is
// skipped without visiting its 32 heaps (the GPU's threads each test their own).
template <typename T> struct WarpMinima {
    std::vector<T> key;
    explicit WarpMinima(int threads) : key(threads / geer::kWarp, geer::Limits<T>::inf()) {}
    bool due(int w0, T bound) const { return key[w0 / geer::kWarp] <= bound; }
    void taken(int w0, const VectorHeap<T>& h) {
        if (h.size > 0) key[w0 / geer::kWarp] = std::min(key[w0 / geer::kWarp], h.top().key);
    }
    void refresh(int w0, const std::vector<VectorHeap<T>>& heaps) {
        T m = geer::Limits<T>::inf();
        for (int tid = w0; tid < w0 + geer::kWarp; ++tid)
            if (heaps[tid].size > 0) m = std::min(m, heaps[tid].top().key);
        key[w0 / geer::kWarp] = m;
    }
};

// Beyond which key bound a ray takes no entry (geer_order.h may_take: lower < reach): its horizon's key while it
// walks, -inf once it is done.
template <typename T> T reach_of(bool done, const geer::Horizon<T>& h) {
    return done ? -geer::Limits<T>::inf() : h.last.key;
}

// Lanes of L from consecutive values.
template <typename L, typename T> L load_lanes(const T* p) {
    if constexpr (geer::Lane<L>::width == 1) {
        return *p;
    } else {
        L v;
        __builtin_memcpy(&v, p, sizeof(v));
        return v;
    }
}

// A recorded pair in the backward's first pass: its evaluation, the transmittance before it, its blend weight,
// v = gC . c + gZ z + gA, and its list position.
template <typename T> struct RecordedPair {
    geer::PairEval<T> e;
    T t_before, w, v;
    int pos;
};

// A tile's release bounds, indexed by list position.
template <typename T> std::vector<T> release_bounds(const at::Tensor& lower, const int32_t* id, int start, int end) {
    std::vector<T> bound(size_t(end - start) + 1, geer::Limits<T>::inf());  // [end - start]: the list's end
    geer::tile_release_bounds(ptr<T>(lower), id, start, end, bound.data());
    return bound;
}

}  // namespace

// The forward's record for its backward (in render_forward's blended_lanes slot, int32): [tiles + 1] offsets of
// each tile's part in what follows, then per tile its rays' blend counts (one per thread) and their list
// positions, each ray's in the order it blended them.
at::Tensor order_record(const std::vector<std::vector<int32_t>>& tiles) {
    std::vector<int64_t> offset(tiles.size() + 1, 0);
    for (size_t t = 0; t < tiles.size(); ++t) offset[t + 1] = offset[t] + int64_t(tiles[t].size());
    TORCH_CHECK(offset.back() < (int64_t(1) << 31), "geer: the per-ray order's record exceeds 2^31 entries");
    auto out = at::empty({int64_t(tiles.size()) + 1 + offset.back()}, at::kInt);
    int32_t* o = out.data_ptr<int32_t>();
    for (size_t t = 0; t <= tiles.size(); ++t) o[t] = int32_t(offset[t]);
    int32_t* data = o + tiles.size() + 1;
    parallel(int64_t(tiles.size()), 1, [&](int64_t t) { std::copy(tiles[t].begin(), tiles[t].end(), data + offset[t]); });
    return out;
}

// kOrigin: every ray from its own origin (origins [R,3]). Outputs as render_forward's, the record order_record's.
template <typename T, bool kPacks, bool kOrigin>
std::vector<at::Tensor> render_forward_ordered(const RenderInputs& in, bool record, const at::Tensor& lower,
                                               int64_t window) {
    using L = LaneOf<T, kPacks>;
    constexpr int kWidth = geer::Lane<L>::width;
    const int64_t r = in.height * in.width;
    auto opts = in.whiten.options();
    auto out_rgb = at::zeros({r, 3}, opts), depth = at::zeros({r}, opts), acc = at::zeros({r}, opts);
    auto t_final = at::ones({r}, opts), median = at::zeros({r}, opts);
    auto n_contrib = at::zeros({r}, at::kInt);
    const int64_t n_tiles = geer::tile_count(int(in.height), int(in.width), int(in.tile_size));
    std::vector<std::vector<int32_t>> records(record ? n_tiles : 0);
    const auto f = frames<T>(in.whiten, in.o_u, in.rgb, in.opacities, in.pbf_pieces);
    const int32_t* id = in.ids.data_ptr<int32_t>();
    const int32_t* rg = in.ranges.data_ptr<int32_t>();
    const int64_t m = in.ids.numel();
    std::vector<T> entry_weight(size_t(m), T(0));
    parallel_dynamic(geer::tile_count(int(in.height), int(in.width), int(in.tile_size)), [&](int64_t tile) {
        const Block<T, L> blk(int(tile), in.height, in.width, in.tile_size, bptr(in.valid), ptr<T>(in.dirs),
                              ptr<T>(in.ray_bounds), ptr<T>(in.warp_bounds), kOrigin ? ptr<T>(in.origins) : nullptr);
        const int start = rg[2 * tile], end = rg[2 * tile + 1];
        std::vector<geer::RayForward<T>> st(blk.threads);
        for (int tid = 0; tid < blk.threads; ++tid) geer::ray_forward_init(st[tid], blk.valid[tid] != 0);
        auto heap = heaps<T>(blk.threads, window);
        const std::vector<T> bound = release_bounds<T>(lower, id, start, end);
        WarpMinima<T> pending_min(blk.threads);
        std::vector<geer::Horizon<T>> horizon(blk.threads);
        std::vector<T> reach(blk.threads);  // reach_of each ray, contiguous: a pack's in one load
        for (int tid = 0; tid < blk.threads; ++tid) reach[tid] = reach_of(st[tid].done, horizon[tid]);
        std::vector<std::vector<int32_t>> blended(record ? blk.threads : 0);  // each ray's, in its order
        const auto blend_of = [&](int tid) {
            return [&, tid](const Pending<T>& p) {
                return geer::blend_pending(st[tid], p, f[id[start + p.pos]].rgb, [&](int pos, T w) {
                    entry_weight[start + pos] = geer::g_max(entry_weight[start + pos], w);
                    if (record) blended[tid].push_back(pos);
                });
            };
        };
        for (int j = start; j < end; ++j) {
            const int pos = j - start;
            const GaussFrame<T>& frame = f[id[j]];
            const T lower_j = ptr<T>(lower)[id[j]];
            if (pos % geer::Batch<T>::value == 0) {  // the kernels' test, once a batch
                bool all_done = true;
                for (int tid = 0; tid < blk.threads && all_done; ++tid) all_done = st[tid].done;
                if (all_done) break;
            }
            const bool release = geer::release_due(bound.data(), pos);
            for (int w0 = 0; w0 < blk.threads; w0 += geer::kWarp) {
                if (release && pending_min.due(w0, bound[pos])) {
                    for (int tid = w0; tid < w0 + geer::kWarp; ++tid) {
                        if (st[tid].done) continue;
                        geer::release_pending(heap[tid], bound[pos], blend_of(tid));
                        reach[tid] = reach_of(st[tid].done, horizon[tid]);
                    }
                    pending_min.refresh(w0, heap);
                }
                if (!geer::ray_meets_pbf(frame, blk.warp_bounds_of(w0))) continue;
                for (int pk = w0 / kWidth; pk < (w0 + geer::kWarp) / kWidth; ++pk) {
                    using Mask = typename geer::Lane<L>::Mask;
                    const int first = pk * kWidth - w0;
                    // the pack's rays still walking whose stop may come after this entry (geer_order.h may_take)
                    const Mask mine = load_lanes<L>(reach.data() + w0 + first) > geer::splat<L>(lower_j);
                    if (!geer::lane_any(mine)) continue;
                    const Mask open = mine & geer::ray_meets_pbf(frame, blk.bounds[pk].data());
                    if (!geer::lane_any(open)) continue;
                    const geer::PairEval<L> e = geer::eval_pair<T, L, kOrigin>(frame, blk.dir[pk], blk.origin_of(pk));
                    const Mask kept = open & e.keep;
                    for (uint32_t k = geer::lane_bits(kept); k; k &= k - 1) {
                        const int i = __builtin_ctz(k), tid = w0 + first + i;
                        geer::insert_pending(heap[tid], horizon[tid], st[tid].trans, geer::pending_of<T, L>(e, i, pos),
                                             bound[pos + 1], blend_of(tid));
                        pending_min.taken(w0, heap[tid]);
                        reach[tid] = reach_of(st[tid].done, horizon[tid]);
                    }
                }
            }
        }
        for (int tid = 0; tid < blk.threads; ++tid) {
            if (!st[tid].done) geer::release_pending(heap[tid], geer::Limits<T>::inf(), blend_of(tid));
            if (!blk.slot[tid].in_image) continue;
            const int ray = blk.slot[tid].ray;
            const geer::RayForward<T>& s = st[tid];
            for (int c = 0; c < 3; ++c) mptr<T>(out_rgb)[3 * ray + c] = s.rgb[c];
            mptr<T>(depth)[ray] = s.depth;
            mptr<T>(acc)[ray] = s.acc;
            mptr<T>(t_final)[ray] = s.trans;
            n_contrib.data_ptr<int32_t>()[ray] = s.n_contrib;
            mptr<T>(median)[ray] = s.median;
        }
        if (!record) return;
        std::vector<int32_t>& rec = records[tile];
        for (const auto& b : blended) rec.push_back(int32_t(b.size()));
        for (const auto& b : blended) rec.insert(rec.end(), b.begin(), b.end());
    });
    auto max_weight = at::zeros({in.whiten.size(0)}, opts);
    fold_entries(entries_of_gaussians(id, m, in.whiten.size(0)), 1, entry_weight.data(), mptr<T>(max_weight),
                 [](T a, T b) { return geer::g_max(a, b); });
    return {out_rgb, depth, acc, t_final, n_contrib, record ? order_record(records) : at::empty({0}, at::kInt),
            max_weight, median};
}

// The backward of render_forward_ordered. kRecorded: the CPU's path, from the forward's record (order_record):
// per ray its blends again front to back, then the gradients back to front with the suffix sums the per-view
// backward also forms (no cancellation; a pair's evaluation is kept in between). Otherwise the kernels' path: the
// forward's walk replayed (each lane of a warp the cull keeps evaluates the entry, render_order.cu), each pair's
// gradient taken as it is blended from the ray's total (geer_order.h backward_pending: V - prefix, which loses
// ~eps |V| / (1 - alpha) in float32). Both add a tile's pair gradients to the entries' slots ray by ray, each
// ray's in its order. Outputs as render_backward's.
template <typename T, bool kRecorded, bool kDirGrad, bool kOrigin>
std::vector<at::Tensor> render_backward_ordered(const RenderInputs& in, const RayGrads& rg_in, const at::Tensor& lower,
                                                int64_t window) {
    constexpr int kGradValues = geer::kGradValues, kAbsgradValues = geer::kAbsgradValues, kWarp = geer::kWarp;
    const int64_t n = in.whiten.size(0), m = in.ids.numel();
    const int64_t n_tiles = geer::tile_count(int(in.height), int(in.width), int(in.tile_size));
    const bool with_absgrad = rg_in.absgrad_rows.numel() > 0;
    auto opts = in.whiten.options();
    auto grads = at::zeros({n, kGradValues}, opts);
    auto absgrad = with_absgrad ? at::zeros({n, kAbsgradValues}, opts) : at::empty({0}, opts);
    auto g_dirs = kDirGrad ? at::zeros({in.height * in.width, 3}, opts) : at::empty({0}, opts);
    auto g_origins = kDirGrad && kOrigin ? at::zeros({in.height * in.width, 3}, opts) : at::empty({0}, opts);
    const auto f = frames<T>(in.whiten, in.o_u, in.rgb, in.opacities, in.pbf_pieces);
    const int32_t* id = in.ids.data_ptr<int32_t>();
    const int32_t* rg = in.ranges.data_ptr<int32_t>();
    const int32_t* record = rg_in.blended_lanes.data_ptr<int32_t>();
    TORCH_CHECK(!kRecorded || (rg_in.blended_lanes.numel() > n_tiles && record[n_tiles] + n_tiles + 1 ==
                                                                                rg_in.blended_lanes.numel()),
                "geer: the per-ray order's backward needs its forward's record");
    const T* rows = with_absgrad ? ptr<T>(rg_in.absgrad_rows) : nullptr;
    std::vector<T> pair_grad(size_t(m) * kGradValues, T(0));
    std::vector<T> pair_absgrad(with_absgrad ? size_t(m) * kAbsgradValues : 0, T(0));
    parallel_dynamic(n_tiles, [&](int64_t tile) {
        const Block<T, T> blk(int(tile), in.height, in.width, in.tile_size, bptr(in.valid), ptr<T>(in.dirs),
                              ptr<T>(in.ray_bounds), ptr<T>(in.warp_bounds), kOrigin ? ptr<T>(in.origins) : nullptr);
        const int start = rg[2 * tile], end = rg[2 * tile + 1];
        std::vector<geer::RayOrderBackward<T>> st(blk.threads);
        for (int tid = 0; tid < blk.threads; ++tid) {
            const bool ok = blk.valid[tid] != 0;
            const int ray = blk.slot[tid].ray;
            geer::RayOrderBackward<T>& s = st[tid];
            geer::ray_forward_init(s.fwd, ok);
            s.prefix = T(0);
            s.total = ok ? ptr<T>(rg_in.ray_totals)[ray] : T(0);
            for (int c = 0; c < 3; ++c) s.g_rgb[c] = ok ? ptr<T>(rg_in.g_rgb)[3 * ray + c] : T(0);
            s.g_depth = ok ? ptr<T>(rg_in.g_depth)[ray] : T(0);
            s.g_acc = ok ? ptr<T>(rg_in.g_acc)[ray] : T(0);
            s.g_dir = s.g_origin = Vec3<T>{T(0), T(0), T(0)};
        }
        // Each ray's blended pairs' gradients in its order (16 values, absgrad's 2) and their entries.
        constexpr int kRow = kGradValues + kAbsgradValues;
        std::vector<std::vector<T>> blended(blk.threads);
        const auto write_row = [&](const geer::PairGrad<T>& pg, int j, T* row) {
            geer::lane_grad_values(pg, true, row);
            if (rows) geer::lane_absgrad_values(rows + geer::kAbsgradRow * id[j], pg, true, row + kGradValues);
        };
        const auto blend = [&](int tid, int pos) {
            const int j = start + pos;
            geer::PairGrad<T> pg;
            if (!geer::backward_pending<T, kDirGrad, kOrigin>(st[tid], f[id[j]], blk.dir[tid], pos, pg,
                                                              blk.origin_of(tid)))
                return false;
            std::vector<T>& out = blended[tid];
            out.resize(out.size() + kRow, T(0));
            write_row(pg, j, out.data() + out.size() - kRow);
            return true;
        };
        std::vector<std::vector<int32_t>> entries(blk.threads);  // the entries of `blended`, exactly
        const auto blend_of = [&](int tid) {
            return [&, tid](const Pending<T>& p) {
                if (!blend(tid, p.pos)) return false;
                entries[tid].push_back(start + p.pos);
                return true;
            };
        };
        if (kRecorded) {
            const int32_t* part = record + n_tiles + 1 + record[tile];
            const int32_t* seq = part + blk.threads;
            std::vector<RecordedPair<T>> pairs;
            for (int tid = 0; tid < blk.threads; seq += part[tid], ++tid) {
                // the forward's blends again, front to back: each pair's evaluation, T before it, weight and v
                pairs.clear();
                geer::RayOrderBackward<T>& s = st[tid];
                for (int k = 0; k < part[tid]; ++k) {
                    const GaussFrame<T>& g = f[id[start + seq[k]]];
                    RecordedPair<T> r{geer::eval_pair<T, T, kOrigin>(g, blk.dir[tid], blk.origin_of(tid)), s.fwd.trans,
                                      T(0), T(0), seq[k]};
                    const T key = geer::pair_depth<T, T>(r.e);
                    r.w = geer::ray_blend<T, T>(s.fwd, true, r.e.alpha, key, g.rgb, seq[k]);
                    TORCH_CHECK(!s.fwd.done, "geer: the per-ray order's record does not replay (a recorded pair stops "
                                "its ray)");
                    r.v = geer::blend_value<T, T>(s.g_rgb, g.rgb, s.g_depth, key, s.g_acc);
                    pairs.push_back(r);
                }
                // back to front: the suffix sums S_i = sum_{j > i} w_j v_j summed as they grow, no V - prefix
                // cancellation; dL/dalpha_i = T_i v_i - S_i / (1 - alpha_i)
                blended[tid].assign(pairs.size() * kRow, T(0));
                T suffix = T(0);
                for (int k = int(pairs.size()) - 1; k >= 0; --k) {
                    const RecordedPair<T>& r = pairs[k];
                    const T g_alpha = r.t_before * r.v - suffix / (T(1) - r.e.alpha);
                    suffix = suffix + r.w * r.v;
                    const int j = start + r.pos;
                    geer::PairGrad<T> pg;
                    geer::pair_backward_from_alpha<T, T, kDirGrad, kOrigin>(r.e, f[id[j]], r.w, g_alpha, s.g_rgb,
                                                                            s.g_depth, true, pg, s.g_dir, s.g_origin);
                    write_row(pg, j, blended[tid].data() + size_t(k) * kRow);
                }
                for (const RecordedPair<T>& r : pairs) entries[tid].push_back(start + r.pos);
            }
        } else {  // the kernels' walk (render_order.cu walk_tile)
            auto heap = heaps<T>(blk.threads, window);
            const std::vector<T> bound = release_bounds<T>(lower, id, start, end);
            std::vector<geer::Horizon<T>> horizon(blk.threads);
            for (int j = start; j < end; ++j) {
                const int pos = j - start;
                const GaussFrame<T>& frame = f[id[j]];
                const bool release = geer::release_due(bound.data(), pos);
                for (int w0 = 0; w0 < blk.threads; w0 += kWarp) {
                    for (int tid = w0; tid < w0 + kWarp; ++tid)
                        if (release && !st[tid].fwd.done)
                            geer::release_pending(heap[tid], bound[pos], blend_of(tid));
                    if (!geer::ray_meets_pbf(frame, blk.warp_bounds_of(w0))) continue;
                    for (int tid = w0; tid < w0 + kWarp; ++tid) {
                        if (!geer::may_take(st[tid].fwd.done, horizon[tid], ptr<T>(lower)[id[j]]) ||
                            !geer::ray_meets_pbf(frame, blk.bounds[tid].data()))
                            continue;
                        const auto e = geer::eval_pair<T, T, kOrigin>(frame, blk.dir[tid], blk.origin_of(tid));
                        if (e.keep)
                            geer::insert_pending(heap[tid], horizon[tid], st[tid].fwd.trans,
                                                 geer::pending_of<T, T>(e, 0, pos), bound[pos + 1], blend_of(tid));
                    }
                }
            }
            for (int tid = 0; tid < blk.threads; ++tid)
                if (!st[tid].fwd.done) geer::release_pending(heap[tid], geer::Limits<T>::inf(), blend_of(tid));
        }
        for (int tid = 0; tid < blk.threads; ++tid) {  // the entries' slots, ray by ray
            const T* row = blended[tid].data();
            for (int32_t j : entries[tid]) {
                T* slot = pair_grad.data() + size_t(j) * kGradValues;
                for (int i = 0; i < kGradValues; ++i) slot[i] += row[i];
                if (rows)
                    for (int i = 0; i < kAbsgradValues; ++i)
                        pair_absgrad[size_t(j) * kAbsgradValues + i] += row[kGradValues + i];
                row += kRow;
            }
            if (!kDirGrad || !blk.valid[tid]) continue;
            const int ray = blk.slot[tid].ray;
            geer::store3(mptr<T>(g_dirs) + 3 * ray, st[tid].g_dir);
            if (kOrigin) geer::store3(mptr<T>(g_origins) + 3 * ray, st[tid].g_origin);
        }
    });
    const auto plus = [](T a, T b) { return a + b; };
    const EntriesOfGaussians entries = entries_of_gaussians(id, m, n);
    fold_entries(entries, kGradValues, pair_grad.data(), mptr<T>(grads), plus);
    if (rows) fold_entries(entries, kAbsgradValues, pair_absgrad.data(), mptr<T>(absgrad), plus);
    return {grads, absgrad, g_dirs, g_origins};
}

std::vector<at::Tensor> render_forward_ordered_op(bool packs, const RenderInputs& in, bool record,
                                                  const at::Tensor& lower, int64_t window) {
    TORCH_CHECK(window >= 0, "geer: order_window must be >= 0 (0: the exact order)");
    TORCH_CHECK(lower.scalar_type() == in.whiten.scalar_type() && lower.numel() == in.whiten.size(0),
                "geer: order_lower must be [N] of the Gaussians' dtype");
    const bool with_origins = in.origins.numel() > 0;
    return dispatch<int>(in.whiten, [&](auto tag) {
        using T = decltype(tag);
        if (packs && kCpuPacks)
            return with_origins ? render_forward_ordered<T, kCpuPacks, true>(in, record, lower, window)
                                : render_forward_ordered<T, kCpuPacks, false>(in, record, lower, window);
        return with_origins ? render_forward_ordered<T, false, true>(in, record, lower, window)
                            : render_forward_ordered<T, false, false>(in, record, lower, window);
    });
}

std::vector<at::Tensor> render_backward_ordered_op(bool recorded, bool dir_grad, const RenderInputs& in,
                                                   const RayGrads& g, const at::Tensor& lower, int64_t window) {
    TORCH_CHECK(lower.scalar_type() == in.whiten.scalar_type() && lower.numel() == in.whiten.size(0),
                "geer: order_lower must be [N] of the Gaussians' dtype");
    TORCH_CHECK(g.ray_totals.numel() == in.height * in.width, "geer: ray_totals must be [R]");
    const bool origin = in.origins.numel() > 0;
    return dispatch<int>(in.whiten, [&](auto tag) {
        using T = decltype(tag);
        using Fn = std::vector<at::Tensor> (*)(const RenderInputs&, const RayGrads&, const at::Tensor&, int64_t);
        const Fn table[2][2][2] = {
            {{render_backward_ordered<T, false, false, false>, render_backward_ordered<T, false, false, true>},
             {render_backward_ordered<T, false, true, false>, render_backward_ordered<T, false, true, true>}},
            {{render_backward_ordered<T, true, false, false>, render_backward_ordered<T, true, false, true>},
             {render_backward_ordered<T, true, true, false>, render_backward_ordered<T, true, true, true>}}};
        return table[recorded][dir_grad][origin](in, g, lower, window);
    });
}

}  // namespace geer_cpu
