// Stage 4, per Gaussian (PreprocessCUDA of paper App. C.2): the render backward's dL/dW, dL/d(o_u)
// and dL/d(colour) become dL/d(view-space mean), dL/dquat, dL/dscale (C.4-C.6, incl. the o_u part of
// dL/dW), the SH coefficient / view-direction gradients and, when asked, each Gaussian's share of dL/d(camera
// rotation). Math: geer_math.h.
#include "geer_launchers.h"
#include "geer_math.h"

namespace geer {

template <typename T>
__global__ void __launch_bounds__(kThreads) preprocess_backward_kernel(const PreprocessArgs<T> a, const PreprocessGradArgs<T> g) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.n) return;
    Vec3<T> g_mean_c;
    preprocess_backward_gaussian(load3(a.means_c + 3 * i), a.quats + 4 * i, a.scales + 3 * i, load_mat3(a.rot_c),
                                 g.g_whiten + 9 * i, load3(g.g_o_u + 3 * i), g_mean_c, g.g_quats + 4 * i,
                                 g.g_scales + 3 * i, g.g_rot_c ? g.g_rot_c + 9 * i : nullptr);
    store3(g.g_means_c + 3 * i, g_mean_c);
    if (a.sh_degree < 0) return;
    T* g_sh = g.g_sh + size_t(i) * a.sh_k * 3;
    const int degree = gaussian_sh_degree(a.sh_degree, a.sh_degrees, i);
    for (int k = 3 * num_sh_bases(degree); k < 3 * a.sh_k; ++k) g_sh[k] = T(0);  // bands above its degree
    Vec3<T> g_dir;
    const Vec3<T> dir = load3(a.sh_dirs + 3 * i);
    sh_backward(a.sh + size_t(i) * a.sh_k * 3, degree, dir, load3(g.g_rgb + 3 * i), g_sh, g_dir);
    store3(g.g_sh_dirs + 3 * i, g_dir);
}

template <typename T>
void launch_preprocess_backward(const PreprocessArgs<T>& a, const PreprocessGradArgs<T>& g, cudaStream_t stream) {
    if (a.n <= 0) return;
    preprocess_backward_kernel<T><<<(a.n + kThreads - 1) / kThreads, kThreads, 0, stream>>>(a, g);
    GEER_KERNEL_LAUNCH_CHECK("preprocess_backward_kernel");
}

template void launch_preprocess_backward<float>(const PreprocessArgs<float>&, const PreprocessGradArgs<float>&,
                                                cudaStream_t);
template void launch_preprocess_backward<double>(const PreprocessArgs<double>&, const PreprocessGradArgs<double>&,
                                                 cudaStream_t);

}  // namespace geer
