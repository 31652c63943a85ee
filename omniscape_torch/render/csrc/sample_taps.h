#pragma once

// The padded cube and the taps of a pixel in it: its layout and border (ring), where a
// pixel's taps lie (locate), their bilinear blend, and the edge and interior pixels read one
// channel at a time (scalar). Part of the fast sampler's kernels (sample_base.h).

#include "sample_base.h"

namespace {

// ------------------------------------------------------------------------------------------
// The padded cube and its border
// ------------------------------------------------------------------------------------------

// The padded cube: faces of `face` texels with a border of `pad`, `n = face + 2 pad` per
// padded side; the cube's strides between faces, rows and texels of one channel (elements).
// A perspective image (sample_image) is a layout of one face of height x width texels, no
// border: only row, texel and last are read.
struct Layout {
    int64_t face, pad, n;
    int64_t face_stride, row, texel;
    double half_x, half_y;  // n / 2 and 6 n / 2: the unnormalisation of grid_sample
    int64_t last_at;        // the largest offset of a texel

    // the offset of texel (i, j) of face k
    int64_t at(int64_t k, int64_t i, int64_t j) const {
        return k * face_stride + i * row + j * texel;
    }
    // the largest offset of a texel of the cube (or image)
    int64_t last() const { return last_at; }
};

Layout layout(int64_t face, int64_t pad, int64_t face_stride, int64_t row, int64_t texel) {
    const int64_t n = face + 2 * pad;
    Layout L{face, pad, n, face_stride, row, texel, 0.5 * n, 3.0 * n, 0};
    L.last_at = L.at(5, face - 1, face - 1);
    return L;
}

Layout image_layout(int64_t height, int64_t width, int64_t row, int64_t texel) {
    return Layout{1, 0, 0, 0, row, texel, 0.0, 0.0, (height - 1) * row + (width - 1) * texel};
}

// The border texels (row-major over the padded faces, interior skipped): texel t reads the
// cube (one sample and channel) at src[t k .. t k + k) with weight[...], or at src[t k] alone
// when weight is null (a copy: exact for any dtype). The offsets are an input of the ops:
// clamped to [0, last] where read (edge pixels only; checking them all per call cost 5%).
template <typename T>
struct Ring {
    const int64_t* src;
    const W<T>* weight;
    int64_t k, last;
    int64_t at(const int64_t* s, int64_t m) const { return std::clamp<int64_t>(s[m], 0, last); }
};

// A pixel's taps, its code and bilinear fractions, where locate writes them and interior reads
// them: side by side in a lookup table (one stream to read: three arrays were 10% slower), in
// three arrays on the stack when computed in the sampling pass (vectorised stores: side by side
// was 10% slower there). The code of an Entry is as wide as G, so that it has no padding (the
// table is an int32 or int64 tensor (P, 3)).
template <typename G>
struct Entry {
    std::conditional_t<sizeof(G) == 8, int64_t, int32_t> code;
    G fx, fy;
};

// A table is an input of its own (sample_lut): a code beyond `limit`, the last top-left tap
// whose taps all lie in the cube, reads as outside, so that no table reads past the cube.
template <typename G>
struct Packed {
    Entry<G>* e;
    int64_t limit;
    int64_t code(int64_t p) const { return e[p].code > limit ? kOutside : e[p].code; }
    G fx(int64_t p) const { return e[p].fx; }
    G fy(int64_t p) const { return e[p].fy; }
    void set(int64_t p, int32_t code, G fx, G fy) const { e[p] = Entry<G>{code, fx, fy}; }
    void set_code(int64_t p, int32_t code) const { e[p].code = code; }
    Packed operator+(int64_t d) const { return Packed{e + d, limit}; }
};

template <typename G>
struct Split {
    int32_t* codes;
    G *fxs, *fys;
    int64_t code(int64_t p) const { return codes[p]; }
    G fx(int64_t p) const { return fxs[p]; }
    G fy(int64_t p) const { return fys[p]; }
    void set(int64_t p, int32_t code, G fx, G fy) const {
        codes[p] = code;
        fxs[p] = fx;
        fys[p] = fy;
    }
    void set_code(int64_t p, int32_t code) const { codes[p] = code; }
    Split operator+(int64_t d) const { return Split{codes + d, fxs + d, fys + d}; }
};

// The three arrays of a segment of pixels, on the stack.
template <typename G>
struct SplitBuffer {
    int32_t code[kSegment];
    G fx[kSegment], fy[kSegment];
    Split<G> taps() { return Split<G>{code, fx, fy}; }
};

// The samples and channels of the cube and of the output image: the output's pixels are
// `out_pix` apart in row-major order (1: planes (B, C, H, W); C: channels-last (B, H, W, C)).
struct Planes {
    int64_t batch, chans, pixels, width;
    int64_t src_batch, src_chan;           // strides of the cube
    int64_t out_batch, out_chan, out_pix;  // strides of the output
};

inline float unnormalize(float g, double half) {
    return static_cast<float>(static_cast<double>(g + 1.0f) * half - 0.5);
}

inline double unnormalize(double g, double half) {
    return (g + 1.0) * half - 0.5;
}

// Codes and bilinear fractions of `count` grid points; `valid` (bool, may be null) false ->
// outside. Branch-free int32 arithmetic (`&` for `&&`) that the compiler vectorises; the
// offsets of interior texels fit in int32 (checked by the ops), those of the other pixels are
// computed modulo 2^32 (unsigned: defined) and discarded.
template <typename G, bool Bilinear, typename Taps>
void locate(const G* __restrict grid, int64_t count, const uint8_t* __restrict valid,
            const Layout& L, Taps out) {
    const int32_t n = static_cast<int32_t>(L.n), f = static_cast<int32_t>(L.face);
    const int32_t pad = static_cast<int32_t>(L.pad);
    const uint32_t stride = static_cast<uint32_t>(L.face_stride);
    const uint32_t row = static_cast<uint32_t>(L.row), texel = static_cast<uint32_t>(L.texel);
    const int32_t span = Bilinear ? 1 : 0;
    const G lo = -2, hi_x = static_cast<G>(n + 1), hi_y = static_cast<G>(6 * n + 1);
    for (int64_t p = 0; p < count; ++p) {
        const G x = unnormalize(grid[2 * p], L.half_x);
        const G y = unnormalize(grid[2 * p + 1], L.half_y);
        // round: half to even under the default rounding mode, as grid_sample rounds
        const G x0 = Bilinear ? std::floor(x) : std::nearbyint(x);
        const G y0 = Bilinear ? std::floor(y) : std::nearbyint(y);
        // beyond the atlas by more than a texel (or NaN): outside; keeps the casts small
        const bool near = (x0 >= lo) & (x0 <= hi_x) & (y0 >= lo) & (y0 <= hi_y);
        const int32_t j = static_cast<int32_t>(near ? x0 : lo);
        const int32_t r = static_cast<int32_t>(near ? y0 : lo);
        const int32_t k = (r >= n) + (r >= 2 * n) + (r >= 3 * n) + (r >= 4 * n) + (r >= 5 * n) +
                          (r >= 6 * n) - (r < 0);  // face of row r
        const int32_t i = r - k * n;
        const bool interior = (k >= 0) & (k < 6) & (i >= pad) & (i + span < pad + f) &
                              (j >= pad) & (j + span < pad + f);
        const bool touches = near & (x0 + span >= 0) & (x0 < n) & (y0 + span >= 0) &
                             (y0 < 6 * n);  // a tap inside the atlas
        const int32_t at = static_cast<int32_t>(static_cast<uint32_t>(k) * stride +
                                                static_cast<uint32_t>(i - pad) * row +
                                                static_cast<uint32_t>(j - pad) * texel);
        out.set(p, interior ? at : (touches ? kEdge : kOutside), x - x0, y - y0);
    }
    if (valid != nullptr) {
        for (int64_t p = 0; p < count; ++p) {
            out.set_code(p, valid[p] ? out.code(p) : kOutside);
        }
    }
}

template <typename G, typename Taps>
void locate(const G* grid, int64_t count, const uint8_t* valid, const Layout& L, bool bilinear,
            Taps out) {
    if (bilinear) {
        locate<G, true>(grid, count, valid, L, out);
    } else {
        locate<G, false>(grid, count, valid, L, out);
    }
}

// Bilinear blend of four taps: grid_sample's weights and order (nw, ne, sw, se).
template <typename V>
inline V blend(V nw, V ne, V sw, V se, V fx, V fy) {
    const V e = 1 - fx, s = 1 - fy;
    V acc = nw * (s * e);
    acc = acc + ne * (s * fx);
    acc = acc + sw * (fy * e);
    acc = acc + se * (fy * fx);
    return acc;
}

// Where texel (column j, row r) of the virtual atlas of one sample and channel is read: `at`
// in the cube (kCube), ring texel `at` (kRing), or nowhere (kZero:
// outside the atlas, 0). Located once per tap, then read for every channel.
enum Kind : int32_t { kZero, kCube, kRing };
struct Tap {
    int64_t at;
    Kind kind;
};

inline Tap atlas_tap(int64_t j, int64_t r, const Layout& L) {
    const int64_t n = L.n, f = L.face, p = L.pad;
    if (j < 0 || j >= n || r < 0 || r >= 6 * n) {
        return Tap{0, kZero};
    }
    const int64_t k = r / n, i = r - k * n;
    if (i >= p && i < p + f && j >= p && j < p + f) {
        return Tap{L.at(k, i - p, j - p), kCube};
    }
    // index among the ring texels (row-major over the padded faces, interior skipped)
    const int64_t pos = i < p       ? i * n + j
                        : i < p + f ? p * n + (i - p) * 2 * p + (j < p ? j : j - f)
                                    : p * n + f * 2 * p + (i - p - f) * n + j;
    return Tap{k * (n * n - f * f) + pos, kRing};
}

// Texel t of the virtual atlas of one sample and channel: blended cubes read it as W (a ring
// texel is a weighted sum), copied ones as the element itself (their ring has one tap).
template <typename T>
inline auto read(const T* cube, const Ring<T>& R, const Tap& t) {
    using V = std::conditional_t<kBlends<T>, W<T>, T>;
    if (t.kind != kRing) {
        return t.kind == kCube ? static_cast<V>(cube[t.at]) : V(0);
    }
    const int64_t* src = R.src + t.at * R.k;
    if constexpr (kBlends<T>) {
        if (R.weight != nullptr) {
            // summed in the plan's order up to the row's first zero weight: the rows list
            // their nonzero weights first (fast._ring_offsets), then zeros, which add nothing
            const W<T>* w = R.weight + t.at * R.k;
            V acc = static_cast<V>(cube[R.at(src, 0)]) * w[0];
            for (int64_t m = 1; m < R.k && w[m] != V(0); ++m) {
                acc = acc + static_cast<V>(cube[R.at(src, m)]) * w[m];
            }
            return acc;
        }
    }
    return static_cast<V>(cube[R.at(src, 0)]);
}

// A value read by `read` written as O.
template <typename T, typename O, typename V>
inline O emit(V v) {
    if constexpr (std::is_same_v<V, T>) {
        return copy<T, O>(v);
    } else {
        return store<T, O>(v);
    }
}

// An edge pixel at atlas pixel (x, y) of one sample: its taps located once, then read through
// the virtual atlas for every channel into out[c out_chan]. Not inlined: rare, and inlined into
// sample_span it slowed the whole pass by 10% (1M pixels, 0.2% of them edge pixels).
template <typename T, typename O, typename G>
__attribute__((noinline)) void edge_pixel(const T* cube, const Ring<T>& R, G x, G y,
                                          const Layout& L, bool bilinear, const Planes& S,
                                          O* out) {
    if (!bilinear) {
        const Tap t = atlas_tap(static_cast<int64_t>(std::nearbyint(x)),
                                static_cast<int64_t>(std::nearbyint(y)), L);
        for (int64_t c = 0; c < S.chans; ++c) {
            out[c * S.out_chan] = emit<T, O>(read(cube + c * S.src_chan, R, t));
        }
        return;
    }
    if constexpr (kBlends<T>) {   // the other cubes are sampled nearest
        using V = W<T>;
        const G x0 = std::floor(x), y0 = std::floor(y);
        const int64_t j = static_cast<int64_t>(x0), r = static_cast<int64_t>(y0);
        const Tap nw = atlas_tap(j, r, L), ne = atlas_tap(j + 1, r, L);
        const Tap sw = atlas_tap(j, r + 1, L), se = atlas_tap(j + 1, r + 1, L);
        for (int64_t c = 0; c < S.chans; ++c) {
            const T* q = cube + c * S.src_chan;
            out[c * S.out_chan] = store<T, O>(blend<V>(read(q, R, nw), read(q, R, ne),
                                                       read(q, R, sw), read(q, R, se),
                                                       V(x - x0), V(y - y0)));
        }
    }
}

// N channels of pixels [0, m) as if every pixel were interior (the outside ones read `fill`):
// per pixel the tap offset and weights once, then the N channels' taps. Scalar: gathers
// vectorised by the compiler were slower (AVX-512 on AMD EPYC: 36 -> 47 ms for 8 x 1M pixels),
// so was a channel at a time (36 against 30 ms).
template <typename T, typename O, int N, typename Taps>
__attribute__((optimize("no-tree-vectorize")))
void interior(const T* __restrict cube, int64_t src_chan, Taps t, int64_t m, const Layout& L,
              bool bilinear, O fill, O* __restrict out, int64_t out_chan, int64_t out_pix) {
    const int64_t dx = L.texel, dy = L.row;
    if constexpr (kBlends<T>) {
        if (bilinear) {
            using V = W<T>;
            for (int64_t p = 0; p < m; ++p) {
                const int64_t k = std::max<int64_t>(t.code(p), 0);
                const bool inside = t.code(p) >= 0;
                if (p + kAhead < m) {   // the taps of a pixel ahead: not a stream the CPU foresees
                    const int64_t ahead = std::max<int64_t>(t.code(p + kAhead), 0);
                    for (int n = 0; n < N; ++n) {
                        __builtin_prefetch(cube + n * src_chan + ahead);
                        __builtin_prefetch(cube + n * src_chan + ahead + dy);
                    }
                }
                const V x = V(t.fx(p)), y = V(t.fy(p)), e = 1 - x, s = 1 - y;
                const V w0 = s * e, w1 = s * x, w2 = y * e, w3 = y * x;  // blend()'s order
                for (int n = 0; n < N; ++n) {
                    const T* q = cube + n * src_chan + k;
                    V acc = value(q[0]) * w0;
                    acc = acc + value(q[dx]) * w1;
                    acc = acc + value(q[dy]) * w2;
                    acc = acc + value(q[dy + dx]) * w3;
                    out[n * out_chan + p * out_pix] = inside ? store<T, O>(acc) : fill;
                }
            }
            return;
        }
    }
    for (int64_t p = 0; p < m; ++p) {
        const int64_t k = std::max<int64_t>(t.code(p), 0);
        const bool inside = t.code(p) >= 0;
        for (int n = 0; n < N; ++n) {
            const O v = copy<T, O>(cube[n * src_chan + k]);
            out[n * out_chan + p * out_pix] = inside ? v : fill;
        }
    }
}

}  // namespace
