// Host/device annotation shared by the CPU and (future) CUDA kernels.
// Every per-Gaussian helper in csrc/common is marked GRP_HD so that a .cu file can include the
// same headers: it expands to `__host__ __device__` under nvcc and to nothing otherwise.
#pragma once

#if defined(__CUDACC__)
#define GRP_HD __host__ __device__
#else
#define GRP_HD
#endif

#define GRP_INLINE GRP_HD inline
