// A kernel that does nothing but say it ran, launched with a caller-chosen block size: the GPU test that a
// launch the hardware refuses (a block over 1024 threads) raises at its own call, through the same check as
// every real launch (GEER_KERNEL_LAUNCH_CHECK, geer_launchers.h).
#include "geer_launchers.h"

namespace geer {

__global__ void probe_kernel(int32_t* out) {
    if (blockIdx.x == 0 && threadIdx.x == 0) *out = int32_t(blockDim.x);
}

void launch_probe(int threads, int32_t* out, cudaStream_t stream) {
    probe_kernel<<<1, threads, 0, stream>>>(out);
    GEER_KERNEL_LAUNCH_CHECK("probe_kernel");
}

}  // namespace geer
