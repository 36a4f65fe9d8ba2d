// The constants that decide visibility and blending, written once (mirrored as named constants in
// gaussian_renderer_pose/reference). Values are upstream diff-gaussian-rasterization's.
#pragma once

namespace grp {

constexpr int kNumChannels = 3;        // RGB
constexpr int kBlockX = 16;            // tile width in pixels
constexpr int kBlockY = 16;            // tile height in pixels
constexpr int kBlockSize = kBlockX * kBlockY;

constexpr float kDilation = 0.3f;          // low-pass filter added to the 2D covariance diagonal
constexpr float kAlphaMax = 0.99f;         // alpha = min(kAlphaMax, o * G)
constexpr float kAlphaMin = 1.0f / 255.0f; // skip a Gaussian at a pixel when alpha < kAlphaMin
constexpr float kTransmittanceMin = 1e-4f; // stop a pixel when T * (1 - alpha) < this
constexpr float kNearPlane = 0.2f;         // cull when view-space z <= this
constexpr float kFrustumClamp = 1.3f;      // tx/tz is clamped to +-kFrustumClamp * tanfov in J
constexpr float kSigmaRadius = 3.0f;       // radius = ceil(kSigmaRadius * sqrt(lambda_max))
constexpr float kAntialiasMinRatio = 0.000025f;  // antialiasing: sqrt(max(this, det0 / det))
constexpr float kProjEps = 0.0000001f;     // p_w = 1 / (p_hom.w + kProjEps)
constexpr float kMinDiscriminant = 0.1f;   // lambda = mid +- sqrt(max(this, mid^2 - det))

}  // namespace grp
