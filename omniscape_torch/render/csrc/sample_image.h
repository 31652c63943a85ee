#pragma once

// Perspective images sampled along rays rotated into their pinhole camera (sample_image).
// Part of the fast sampler's kernels (sample_base.h).

#include "sample_rays.h"

namespace {

// ------------------------------------------------------------------------------------------
// Perspective images: rays rotated into a pinhole camera, its image sampled
// ------------------------------------------------------------------------------------------

// The code and bilinear fractions of the pixel at image position (u, v), `inside` the image
// (height x width texels, rows and texels `row`, `texel` apart): the top-left tap (nearest: the
// texel, rounded half to even) where every tap lies in the image, kEdge where an inside
// pixel's taps reach beyond it (read clamped), kOutside where not inside.
template <typename G>
struct PinholeCode {
    int32_t code;
    G fx, fy;
};
template <typename G, bool Bilinear>
inline PinholeCode<G> pinhole_code(G u, G v, bool inside, int32_t w, int32_t h, uint32_t row,
                                   uint32_t texel) {
    const int32_t span = Bilinear ? 1 : 0;
    const G u0 = Bilinear ? std::floor(u) : std::nearbyint(u);
    const G v0 = Bilinear ? std::floor(v) : std::nearbyint(v);
    const int32_t j = static_cast<int32_t>(inside ? u0 : G(0));
    const int32_t i = static_cast<int32_t>(inside ? v0 : G(0));
    const bool interior = (j >= 0) & (j + span < w) & (i >= 0) & (i + span < h);
    const int32_t at = static_cast<int32_t>(static_cast<uint32_t>(i) * row +
                                            static_cast<uint32_t>(j) * texel);
    return PinholeCode<G>{inside ? (interior ? at : kEdge) : kOutside, u - u0, v - v0};
}

// The taps in a perspective image of height x width texels (rows and texels L.row, L.texel
// apart) of `count` rays rotated by `rot` (row-major 3 x 3, Rotate) into the pinhole camera
// k = (fx, fy, cx, cy): pixel u = fx (x / z) + cx, v = fy (y / z) + cy (pinhole_project's
// operations), valid where z > 0, the pixel lies in [-0.5, W - 0.5] x [-0.5, H - 0.5] (Camera's
// image bounds) and `valid` (may be null) holds; written to valid_out. Codes: pinhole_code's;
// xs, ys: the pixels (for the edge pixels).
template <typename G, bool Bilinear, bool Rotate>
void locate_pinhole(const G* __restrict rays, const G* __restrict rot, const G* __restrict k,
                    int64_t count, const uint8_t* __restrict valid, int64_t height,
                    int64_t width, const Layout& L, Split<G> out, G* __restrict xs,
                    G* __restrict ys, uint8_t* __restrict valid_out) {
    const G fx = k[0], fy = k[1], cx = k[2], cy = k[3];
    const G right = G(width) - G(0.5), bottom = G(height) - G(0.5);
    const int32_t w = static_cast<int32_t>(width), h = static_cast<int32_t>(height);
    const uint32_t row = static_cast<uint32_t>(L.row), texel = static_cast<uint32_t>(L.texel);
    G r[9];
    if (Rotate) {
        std::copy(rot, rot + 9, r);
    }
    // the outputs as pointers that alias nothing (through `out` the compiler kept the loop
    // scalar: 3x the time)
    int32_t* __restrict codes = out.codes;
    G* __restrict fxs = out.fxs;
    G* __restrict fys = out.fys;
    for (int64_t p = 0; p < count; ++p) {
        const G x = rays[3 * p], y = rays[3 * p + 1], z = rays[3 * p + 2];
        G px, py, pz;
        rotate<G, Rotate>(r, x, y, z, px, py, pz);
        const bool front = pz > G(0);
        const G depth = front ? pz : G(1);
        const G u = fx * (px / depth) + cx, v = fy * (py / depth) + cy;
        const bool inside = front & (u >= G(-0.5)) & (u <= right) & (v >= G(-0.5)) &
                            (v <= bottom);
        const PinholeCode<G> c = pinhole_code<G, Bilinear>(u, v, inside, w, h, row, texel);
        codes[p] = c.code;
        fxs[p] = c.fx;
        fys[p] = c.fy;
        xs[p] = u;
        ys[p] = v;
        valid_out[p] = inside;   // (unconditional: a conditional store kept the loop scalar)
    }
    if (valid != nullptr) {
        for (int64_t p = 0; p < count; ++p) {
            out.set_code(p, valid[p] ? out.code(p) : kOutside);
            valid_out[p] = valid_out[p] & valid[p];
        }
    }
}

// locate_pinhole's codes of `count` pixels from their image positions xs, ys (as it computed
// them), inside where `keep` is nonzero.
template <typename G, bool Bilinear>
void locate_positions(const G* __restrict xs, const G* __restrict ys,
                      const uint8_t* __restrict keep, int64_t count, int64_t height,
                      int64_t width, const Layout& L, Split<G> out) {
    const int32_t w = static_cast<int32_t>(width), h = static_cast<int32_t>(height);
    const uint32_t row = static_cast<uint32_t>(L.row), texel = static_cast<uint32_t>(L.texel);
    int32_t* __restrict codes = out.codes;
    G* __restrict fxs = out.fxs;
    G* __restrict fys = out.fys;
    for (int64_t p = 0; p < count; ++p) {
        const PinholeCode<G> c = pinhole_code<G, Bilinear>(xs[p], ys[p], keep[p] != 0, w, h,
                                                           row, texel);
        codes[p] = c.code;
        fxs[p] = c.fx;
        fys[p] = c.fy;
    }
}

// A perspective image (B, C, height, width) (any strides: L.row, L.texel; S) sampled along rays
// (rays_batch 0 or 3 P) rotated per sample (rot_batch 0 or 9, rot null: not rotated) into its
// pinhole camera (intrinsics k, k_batch 0 or 4), a segment at a time; the pixels outside read
// `fill`; their validity into valid_out (B, P) where it is not null.
template <typename T, typename O, typename G>
void sample_image(const T* src, const G* rays, int64_t rays_batch, const G* rot,
                  int64_t rot_batch, const G* k, int64_t k_batch, const uint8_t* valid,
                  int64_t valid_batch, int64_t height, int64_t width, const Layout& L,
                  bool bilinear, O fill, Planes S, O* out, uint8_t* valid_out) {
    const Ring<T> none{nullptr, nullptr, 1, 0};   // no border: the taps are clamped
    for_segments(S, [&](int64_t b, int64_t lo, int64_t m) {
        G xs[kSegment], ys[kSegment];
        uint8_t unused[kSegment];
        SplitBuffer<G> buffer;
        const G* ray = rays + b * rays_batch + 3 * lo;
        const G* r = rot == nullptr ? nullptr : rot + b * rot_batch;
        const uint8_t* ok = valid == nullptr ? nullptr : valid + b * valid_batch + lo;
        uint8_t* seen = valid_out == nullptr ? unused : valid_out + b * S.pixels + lo;
        const auto locate = [&](auto bilinear_, auto rotate) {
            locate_pinhole<G, decltype(bilinear_)::value, decltype(rotate)::value>(
                ray, r, k + b * k_batch, m, ok, height, width, L, buffer.taps(), xs, ys, seen);
        };
        using Yes = std::true_type;
        using No = std::false_type;
        if (bilinear) {
            r != nullptr ? locate(Yes{}, Yes{}) : locate(Yes{}, No{});
        } else {
            r != nullptr ? locate(No{}, Yes{}) : locate(No{}, No{});
        }
        sample_span<T, O, G>(src + b * S.src_batch, none, buffer.taps(),
                             ImagePoints<G>{xs, ys, height, width}, m, L, bilinear, fill, S,
                             out + b * S.out_batch + lo * S.out_pix);
    });
}

}  // namespace
