// Per-ray compositing order, shared by the CUDA kernels (render_order.cu) and the CPU build (cpu_render*.cpp):
// each ray blends its kept pairs in the order of their peaks on the ray as travelled, max(t*, 0) (the depth the
// renderer reports; ties, e.g. every Gaussian that contains the camera at 0, in list order), instead of the
// tile list's one order per view. docs/renderer.md, "Compositing order".
//
// A ray walks its tile's list front to back as in the per-view order, but keeps the pairs it evaluates and keeps
// (q <= q_max) in a min-heap of pending pairs. Each list entry j carries a release bound: the smallest key any
// entry at or after j can have on any ray of the tile (tile_release_bounds, from per-Gaussian lower bounds). A
// pending pair whose key is at most the bound of the entry about to be visited comes before every pair still
// unvisited, so it is blended then, in heap order: the exact order, and the early stop stays exact (a ray stops
// at the first pair of its own order that would take T below T_MIN; every later pair comes after it). A window
// of K pending pairs (the GPU's, and the fast mode) blends the smallest of K + 1 when it is full: the order is
// then exact while a ray holds at most K pending pairs, StopThePop's approximation beyond.
//
// The backward takes each pair's gradient front to back in the order the forward blended them, from the ray's
// total V = sum_i w_i v_i (v_i = gC . c_i + gZ z_i + gA): dL/dalpha_i = T_i v_i - (V - sum_{j <= i} w_j v_j) /
// (1 - alpha_i). The kernels replay the forward's walk (same evaluations, releases and stop) to find that order;
// the CPU build's forward records it (the list positions each ray blended, in order).
#pragma once

#include "geer_ray.h"

namespace geer {

// A kept pair waiting to be blended: its key max(t*, 0), its alpha and its position in the tile's list.
template <typename T> struct Pending {
    T key;
    T alpha;
    int pos;
};

// The order of the blend: by key, ties by list position. float32: keys are >= 0 (+0 at most), so their bits order
// like them, and (key bits, position) as one 64-bit integer compares both without a branch.
template <typename T> GEER_HD bool comes_before(const Pending<T>& a, const Pending<T>& b) {
    return a.key < b.key || (a.key == b.key && a.pos < b.pos);
}
GEER_HD uint64_t order_word(const Pending<float>& p) {
#if defined(__CUDA_ARCH__)
    const uint32_t bits = __float_as_uint(p.key);
#else
    uint32_t bits;
    __builtin_memcpy(&bits, &p.key, sizeof(bits));
#endif
    return (uint64_t(bits) << 32) | uint32_t(p.pos);
}
template <> GEER_HD bool comes_before<float>(const Pending<float>& a, const Pending<float>& b) {
    return order_word(a) < order_word(b);
}

// A binary min-heap of pending pairs over `item` (capacity slots). A window of kWindow pairs in a thread's own
// array (the GPU, the fast mode); the CPU build's exact order uses a growing vector (cpu_render.h GrowingHeap).
template <typename T> GEER_HD void heap_push(Pending<T>* item, int& size, const Pending<T>& p) {
    int i = size++;
    while (i > 0) {
        const int parent = (i - 1) / 2;
        if (!comes_before(p, item[parent])) break;
        item[i] = item[parent];
        i = parent;
    }
    item[i] = p;
}

template <typename T> GEER_HD Pending<T> heap_pop(Pending<T>* item, int& size) {
    const Pending<T> top = item[0];
    const Pending<T> last = item[--size];
    int i = 0;
    for (;;) {
        int child = 2 * i + 1;
        if (child >= size) break;
        if (child + 1 < size && comes_before(item[child + 1], item[child])) ++child;
        if (!comes_before(item[child], last)) break;
        item[i] = item[child];
        i = child;
    }
    if (size > 0) item[i] = last;
    return top;
}

// The CUDA kernels' window (render_order.cu): a thread's pending pairs in local memory.
constexpr int kGpuWindow = 64;

template <typename T, int kWindow> struct WindowHeap {
    Pending<T> item[kWindow];
    int size = 0;
    GEER_HD bool full() { return size == kWindow; }
    GEER_HD const Pending<T>& top() const { return item[0]; }
    GEER_HD void push(const Pending<T>& p) { heap_push(item, size, p); }
    GEER_HD Pending<T> pop() { return heap_pop(item, size); }
    GEER_HD void clear() { size = 0; }
    GEER_HD Pending<T>* data() { return item; }
};

// The release bounds of a tile's entries [start, end), by list position: bound[j - start] = min over k >= j of
// lower[ids[k]], the smallest key an entry at or after j can have. lower: per Gaussian (render/order.py
// key_lower_bounds).
template <typename T>
GEER_HD void tile_release_bounds(const T* lower, const int32_t* ids, int start, int end, T* bound) {
    T m = Limits<T>::inf();
    for (int j = end - 1; j >= start; --j) {
        m = g_min(m, lower[ids[j]]);
        bound[j - start] = m;
    }
}

// Whether a ray releases before the entry at list position pos: where the bound rose (a pair taken since the
// last release has a key at or above the bound then, so waiting for the next rise keeps the order). bound: the
// tile's bounds by list position.
template <typename T> GEER_HD bool release_due(const T* bound, int pos) { return pos == 0 || bound[pos] != bound[pos - 1]; }

// ------------------------------------------------------------------------------------------ the walk
// blend(p): blend pending pair p into the ray (forward: blend_pending; backward: backward_pending and the
// gradient's sums); false once the ray has stopped there. Both return false once the ray has stopped.

// Blend the pending pairs whose key is at most `bound` (all of them at the list's end: bound = inf).
template <typename T, typename Heap, typename Blend> GEER_HD bool release_pending(Heap& h, T bound, Blend&& blend) {
    while (h.size > 0 && h.top().key <= bound) {
        if (!blend(h.pop())) {
            h.clear();
            return false;
        }
    }
    return true;
}

// What a ray knows of its stop: `after`, its transmittance once it has blended every pair it blended or holds;
// once that is below T_MIN, `last`, the pair at which its stop falls among the held ones (set_horizon). Pairs
// after `last` in the order are never blended (every held pair before it comes first): they are not taken, and
// the ray is done once the release bound passes `last`.
template <typename T> struct Horizon {
    T after = T(1);
    Pending<T> last{Limits<T>::inf(), T(0), 0x7fffffff};
};

// The ray's held pairs already take it below T_MIN: sort them (in place: a heap sort, then reversed, so that
// the ascending array is again a min-heap), find the first whose blend would take T (from `trans`) below T_MIN,
// and drop those after it. Rounding may find none (the product in another order): then every pair stays.
template <typename T, typename Heap> GEER_HD void set_horizon(Heap& h, Horizon<T>& hz, T trans) {
    Pending<T>* item = h.data();
    const int n = h.size;
    for (int size = n; size > 0;) {
        const Pending<T> top = heap_pop(item, size);
        item[size] = top;  // descending: item[n - 1] the first
    }
    for (int i = 0; i < n / 2; ++i) {
        const Pending<T> x = item[i];
        item[i] = item[n - 1 - i];
        item[n - 1 - i] = x;
    }
    T t = trans;
    for (int i = 0; i < n; ++i) {
        const T after = t * (T(1) - item[i].alpha);  // ray_blend's product
        if (after < T(kTMin)) {
            hz.last = item[i];
            h.size = i + 1;
            return;
        }
        t = after;
    }
    hz.after = t;
}

// Whether a ray still walking may take the entry of a Gaussian whose key bound is `lower`: not once its horizon
// lies at or before that bound (every pair of the entry would come after the horizon, and be dropped).
template <typename T> GEER_HD bool may_take(bool done, const Horizon<T>& hz, T lower) {
    return !done && hz.last.key > lower;
}

// Take a kept pair into the walk; a full window first blends the smallest of its pairs and p. trans: the ray's
// transmittance (the blends update it); next_bound: the release bound of the entry after p's. A pair before
// every held one and at or below next_bound comes before every pair held or still to come: it is blended at once
// (where the heap would release it first anyway).
template <typename T, typename Heap, typename Blend>
GEER_HD bool insert_pending(Heap& h, Horizon<T>& hz, const T& trans, const Pending<T>& p, T next_bound,
                            Blend&& blend) {
    if (comes_before(hz.last, p)) return true;  // never blended
    hz.after = hz.after * (T(1) - p.alpha);
    bool go = true;
    if (p.key <= next_bound && (h.size == 0 || comes_before(p, h.top()))) {
        go = blend(p);
    } else if (!h.full()) {
        h.push(p);
    } else if (comes_before(p, h.top())) {
        go = blend(p);
    } else {
        const Pending<T> first = h.pop();
        h.push(p);
        go = blend(first);
    }
    if (!go) {
        h.clear();
        return false;
    }
    if (hz.after < T(kTMin) && hz.last.key == Limits<T>::inf()) set_horizon(h, hz, trans);
    return true;
}

// ------------------------------------------------------------------------------------------ forward
// Blend the pending pair p into s (rgb: its Gaussian's colour); on_blend(pos, weight) is told of each blend.
// Returns false once the ray stops (the pair is then not blended).
template <typename T, typename OnBlend>
GEER_HD bool blend_pending(RayForward<T>& s, const Pending<T>& p, const T* rgb, OnBlend&& on_blend) {
    const T w = ray_blend<T, T>(s, true, p.alpha, p.key, rgb, p.pos);
    if (s.done) return false;
    on_blend(p.pos, w);
    return true;
}

// A kept pair's pending record (the forward's eval_pair, lane i).
template <typename T, typename L> GEER_HD Pending<T> pending_of(const PairEval<L>& e, int lane, int pos) {
    const T key = lane_get(pair_depth<T, L>(e), lane);
    return Pending<T>{key, lane_get(e.alpha, lane), pos};
}

// ------------------------------------------------------------------------------------------ backward
// The backward's state of one ray: the forward's running transmittance and blend state (replayed), the
// prefix sum_{j <= i} w_j v_j and the total V.
template <typename T> struct RayOrderBackward {
    RayForward<T> fwd;  // the replayed forward (trans, done, ...)
    T prefix;
    T total;
    T g_rgb[3];
    T g_depth;
    T g_acc;
    Vec3<T> g_dir;
    Vec3<T> g_origin;
};

// The gradient of the pair at list position pos of Gaussian frame g, blended now (the forward's blend_pending;
// its key and alpha re-evaluated, the same bits): sets pg and returns true, or returns false where the ray stops
// there. kDirGrad, kOrigin: as ray_backward_step.
template <typename T, bool kDirGrad, bool kOrigin>
GEER_HD bool backward_pending(RayOrderBackward<T>& s, const GaussFrame<T>& g, const Vec3<T>& d, int pos,
                              PairGrad<T>& pg, const Vec3<T>* origin) {
    const PairEval<T> e = eval_pair<T, T, kOrigin>(g, d, origin);
    const T key = pair_depth<T, T>(e);
    const T t_before = s.fwd.trans;
    const T w = ray_blend<T, T>(s.fwd, true, e.alpha, key, g.rgb, pos);
    if (s.fwd.done) return false;
    const T v = blend_value<T, T>(s.g_rgb, g.rgb, s.g_depth, key, s.g_acc);
    s.prefix = s.prefix + w * v;
    const T g_alpha = t_before * v - (s.total - s.prefix) / (T(1) - e.alpha);
    pair_backward_from_alpha<T, T, kDirGrad, kOrigin>(e, g, w, g_alpha, s.g_rgb, s.g_depth, true, pg, s.g_dir,
                                                      s.g_origin);
    return true;
}

}  // namespace geer
