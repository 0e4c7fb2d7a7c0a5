// Stage 1, per Gaussian: whitening W = S^-1 R_v^T, camera centre in the canonical frame o_u, PBF
// angular bounds (opacity-aware lambda), camera-inside flag, and the view-dependent colour (SH).
// The math is geer_math.h (shared with the CPU build that tests/test_csrc_math.py checks).
#include "geer_launchers.h"
#include "geer_math.h"

namespace geer {

template <typename T> __global__ void __launch_bounds__(kThreads) preprocess_forward_kernel(const PreprocessArgs<T> a) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.n) return;
    const Mat3<T> rot_c = load_mat3(a.rot_c);
    const GaussianForward<T> g = preprocess_gaussian(load3(a.means_c + 3 * i), a.quats + 4 * i, a.scales + 3 * i,
                                                     a.opacities[i], rot_c, a.paper_lambda != 0);
    store_mat3(a.whiten + 9 * i, g.w);
    store3(a.o_u + 3 * i, g.o_u);
    for (int k = 0; k < 4; ++k) a.bounds[4 * i + k] = g.bounds[k];
    a.alive[i] = g.alive ? 1 : 0;
    a.inside[i] = g.camera_inside ? 1 : 0;
    if (a.sh_degree >= 0) {
        // Only the bands up to the Gaussian's degree are read.
        const Vec3<T> dir = load3(a.sh_dirs + 3 * i);
        store3(a.rgb + 3 * i, sh_to_color(a.sh + size_t(i) * a.sh_k * 3, gaussian_sh_degree(a.sh_degree, a.sh_degrees, i),
                                          dir));
    }
}

template <typename T> void launch_preprocess_forward(const PreprocessArgs<T>& a, cudaStream_t stream) {
    if (a.n <= 0) return;
    preprocess_forward_kernel<T><<<(a.n + kThreads - 1) / kThreads, kThreads, 0, stream>>>(a);
    GEER_KERNEL_LAUNCH_CHECK("preprocess_forward_kernel");
}

template void launch_preprocess_forward<float>(const PreprocessArgs<float>&, cudaStream_t);
template void launch_preprocess_forward<double>(const PreprocessArgs<double>&, cudaStream_t);

}  // namespace geer
