#pragma once

// Radially symmetric cameras straight to the atlas grid or their rays (camera_grid,
// camera_rays). Part of the fast sampler's kernels (sample_base.h).

#include "sample_rays.h"

namespace {

// ------------------------------------------------------------------------------------------
// Cameras straight to the atlas grid: radially symmetric models through a radius -> ray table
// ------------------------------------------------------------------------------------------

// One camera of camera_grid: pixel (u, v) -> m = M (u - cx, v - cy), rho = |m|; the unit ray
// (S(rho) m, C(rho)) with S and C interpolated linearly in a table of K entries (S = sin(theta)
// / rho, C = cos(theta), tabulated from the model's own unprojection); valid where rho < end
// (the model's domain) and the ray lies in the cones cos_fov <= C < cos_blind. The entries are
// evenly spaced in rho (root = 0: index rho scale) or, where the domain ends (a fold, where
// theta(rho) has a square-root singularity), in w = sqrt(root^2 - rho) (index (root - w)
// scale; root^2 the last radius tabulated, within rounding of the end), in which theta is
// smooth up to the end.
template <typename G>
struct RadialCamera {
    const G* affine;   // cx, cy, M00, M01, M10, M11
    const G* limits;   // scale, root, end, cos_fov, cos_blind
    const G* table;    // (2, K): S, then C
    int64_t entries;
};

// The camera-frame rays of pixels [lo, lo + m) (m <= kSegment) of a row-major image `width`
// wide, and their validity. Three loops: the radii and table positions (vectorised), the table
// reads (scalar: GCC does not vectorise gathers for AMD CPUs, and they were slow there), the
// rays and validity (vectorised).
template <typename G>
void radial_rays(const RadialCamera<G>& cam, int64_t width, int64_t lo, int64_t m, G* rays,
                 uint8_t* valid) {
    const G cx = cam.affine[0], cy = cam.affine[1];
    const G m00 = cam.affine[2], m01 = cam.affine[3], m10 = cam.affine[4], m11 = cam.affine[5];
    const G scale = cam.limits[0], root = cam.limits[1], end = cam.limits[2];
    const G cos_fov = cam.limits[3], cos_blind = cam.limits[4];
    const bool folded = root > 0;
    const G last = G(cam.entries - 2);
    const int64_t row = lo / width, col = lo % width;   // a segment lies within one row
    const G dv = G(row) - cy;
    G mxs[kSegment], mys[kSegment], rhos[kSegment], ts[kSegment], ss[kSegment], cs[kSegment];
    int32_t index[kSegment];
    for (int64_t p = 0; p < m; ++p) {
        // the column as an int32 (exact): AVX2 converts no int64 to floats, so an int64 column
        // kept this loop from vectorising (it took 70% of the camera pass)
        const G du = G(static_cast<int32_t>(col + p)) - cx;
        const G mx = m00 * du + m01 * dv, my = m10 * du + m11 * dv;
        const G rho = std::sqrt(mx * mx + my * my);
        const G at = folded ? (root - std::sqrt(std::max(root * root - rho, G(0)))) * scale
                            : rho * scale;
        // in [0, last], NaN to 0 (a NaN parameter: the pixel reads entry 0, and is invalid)
        const G base = std::floor(at >= G(0) ? (at <= last ? at : last) : G(0));
        mxs[p] = mx;
        mys[p] = my;
        rhos[p] = rho;
        index[p] = static_cast<int32_t>(base);
        ts[p] = at - base;
    }
    const G* __restrict sines = cam.table;                  // S
    const G* __restrict cosines = cam.table + cam.entries;  // C
    for (int64_t p = 0; p < m; ++p) {
        const int32_t i = index[p];
        ss[p] = sines[i] + ts[p] * (sines[i + 1] - sines[i]);
        cs[p] = cosines[i] + ts[p] * (cosines[i + 1] - cosines[i]);
    }
    for (int64_t p = 0; p < m; ++p) {
        const G c = cs[p];
        rays[3 * p] = ss[p] * mxs[p];
        rays[3 * p + 1] = ss[p] * mys[p];
        rays[3 * p + 2] = c;
        valid[p] = (rhos[p] < end) & (c >= cos_fov) & (c < cos_blind);
    }
}

// The atlas grid (B, H, W, 2) of B cameras (their rays rotated by rot, row-major 3 x 3 each),
// the invalid pixels at (-2, -2), outside the atlas, and the validity (B, H, W); or, with
// `rays` instead of `grid` (rot and L unused), their camera-frame rays (B, H, W, 3).
template <typename G>
void radial_grid(const G* affine, const G* limits, const G* table, int64_t entries,
                 int64_t table_batch, const G* rot, int64_t batch, int64_t height, int64_t width, const Layout& L,
                 G* grid, G* rays, uint8_t* valid) {
    const int64_t pixels = height * width;
    const int64_t segments = (width + kSegment - 1) / kSegment;
    parallel_units(batch * height * segments, std::min(kSegment, width), [&](int64_t index) {
        G buffer[3 * kSegment];
        const int64_t b = index / (height * segments), rest = index % (height * segments);
        const int64_t y = rest / segments, x0 = (rest % segments) * kSegment;
        const int64_t m = std::min(kSegment, width - x0), lo = y * width + x0;
        const RadialCamera<G> cam{affine + 6 * b, limits + 5 * b,
                                  table + table_batch * b, entries};
        uint8_t* ok = valid + b * pixels + lo;
        G* r = rays == nullptr ? buffer : rays + 3 * (b * pixels + lo);
        radial_rays<G>(cam, width, lo, m, r, ok);
        if (grid == nullptr) {
            return;
        }
        G* g = grid + 2 * (b * pixels + lo);
        ray_grid<G, true>(r, rot + 9 * b, m, L, g);
        for (int64_t p = 0; p < m; ++p) {
            g[2 * p] = ok[p] ? g[2 * p] : G(-2);
            g[2 * p + 1] = ok[p] ? g[2 * p + 1] : G(-2);
        }
    });
}

}  // namespace
