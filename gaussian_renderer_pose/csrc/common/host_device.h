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

// Forced inlining, for the bodies shared by the CPU and CUDA kernels (common/raster.h): the CPU
// kernel's float results depend on the code being inlined into its loops (FMA contraction and
// vectorisation decisions), so the shared bodies must not become out-of-line calls.
#if defined(__CUDACC__)
#define GRP_FORCE_INLINE __host__ __device__ __forceinline__
#elif defined(__GNUC__)
#define GRP_FORCE_INLINE __attribute__((always_inline)) inline
#else
#define GRP_FORCE_INLINE inline
#endif
