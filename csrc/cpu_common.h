// Helpers of the CPU build's translation units (cpu_ops.cpp, cpu_render.cpp, cpu_render_backward.cpp): tensor
// access, the dtype dispatch and ATen's threads.
#pragma once
#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <atomic>
#include <cstdint>

namespace geer_cpu {

template <typename T> inline const T* ptr(const at::Tensor& t) { return t.data_ptr<T>(); }
template <typename T> inline T* mptr(at::Tensor& t) { return t.data_ptr<T>(); }
inline const uint8_t* bptr(const at::Tensor& t) { return reinterpret_cast<const uint8_t*>(t.data_ptr<bool>()); }
inline uint8_t* mbptr(at::Tensor& t) { return reinterpret_cast<uint8_t*>(t.data_ptr<bool>()); }

inline at::Tensor cpu(const at::Tensor& t) { return t.contiguous().cpu(); }

inline void check_dtype(const at::Tensor& t) {
    TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble,
                "geer cpu_ops: float32 or float64 expected");
}

template <typename T, typename F> auto dispatch(const at::Tensor& t, F&& f) {
    check_dtype(t);
    if (t.scalar_type() == at::kFloat) return f(float{});
    return f(double{});
}

// f(i) for i in [0, n), split over ATen's threads (each index handled by exactly one thread).
template <typename F> void parallel(int64_t n, int64_t grain, F&& f) {
    at::parallel_for(0, n, grain, [&](int64_t begin, int64_t end) {
        for (int64_t i = begin; i < end; ++i) f(i);
    });
}
constexpr int64_t kGaussGrain = 256;

// f(i) for i in [0, n) with each thread taking the next index when done (tiles differ widely in cost).
template <typename F> void parallel_dynamic(int64_t n, F&& f) {
    std::atomic<int64_t> next{0};
    at::parallel_for(0, at::get_num_threads(), 1, [&](int64_t begin, int64_t end) {
        for (int64_t w = begin; w < end; ++w)
            for (int64_t i = next++; i < n; i = next++) f(i);
    });
}

}  // namespace geer_cpu
