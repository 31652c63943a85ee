#pragma once

// The fast sampler's per-pixel loops (omniscape_torch/render/fast.py) and the camera grid of
// render/kernels.py as PyTorch custom ops, torch.ops.omniscape_torch.{build_lut, sample_lut,
// sample_grid, sample_rays, camera_grid}, built on first use by
// omniscape_torch/render/extension.py (torch.utils.cpp_extension). The ops take tensors and
// read their sizes and strides; the loops below take pointers, sizes and strides (in elements).
//
// The image is grid_sample(cubemap_to_atlas(cube, pad, border), grid, align_corners=False,
// padding_mode="zeros") without the atlas: a grid point becomes atlas pixels as grid_sample's
// CPU kernel computes them, x = fma(g + 1, size / 2, -0.5) (evaluated in double for a float
// grid and rounded once, which is exact); a tap on an interior texel of a face reads the cube,
// a tap on the border ("ring") texel t reads sum_m weight[t, m] * cube[src[t, m]] (the border
// plan of cubemap_to_atlas, fast._ring_offsets), a tap outside the atlas reads 0; bilinear
// weights and their order are grid_sample's (nw, ne, sw, se). Built with -ffp-contract=off, so
// every sum is evaluated in the order written here.
//
// The cube is read through its strides: channels-first (B, 6, C, F, F) and channels-last
// (B, 6, F, F, C) memory alike, no copy. Its elements: float32 and float64 (blended in their
// own precision), float16, bfloat16 and uint8 (blended in float32; uint8 rounded to nearest
// and saturated, or written as float32 scaled to [0, 1]), or any element of 2, 4 or 8 bytes
// sampled nearest (copied: integer labels, exact).
//
// Per pixel, its "code" is the offset of the top-left tap (nearest: the texel) within one
// sample and channel of the cube when every tap is an interior texel of one face (99% of the
// pixels), -1 when every tap lies outside the atlas or the pixel is not valid (it reads `fill`:
// 0, or the ignore index of labels), -2 for an edge pixel, whose taps are read one by one
// through the border.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>
#include <optional>
#ifdef __SSE4_1__
#include <immintrin.h>
#endif
#include <type_traits>
#include <utility>

// The face table, per case 2 axis + (dominant component < 0) and then the zero ray: the face,
// then r and b as (axis, sign). Generated from cubemap/faces.py (the only face table) by
// extension.py, which passes it as -DOS_FACE_CASES=..., so a new table is a new build.
#ifndef OS_FACE_CASES
#error "OS_FACE_CASES is undefined: build this file through omniscape_torch/render/extension.py"
#endif

namespace {

constexpr int32_t kOutside = -1;
constexpr int32_t kEdge = -2;
constexpr int64_t kSegment = 256;  // pixels of a row per unit of work of the samplers
constexpr int64_t kChunk = 4096;  // grid points per unit of work of the table
constexpr int64_t kAhead = 16;    // pixels between a prefetch and the read (-12% time)
// Work of fewer pixels runs on the calling thread: waking a second one costs more than it
// saves, and on a busy machine (other processes on every core) the wait until it is scheduled
// is a time slice (a 128 x 128 uint8 image, 0.44 ms on one thread: 16 ms median on two, at load
// 6 on 2 cores).
constexpr int64_t kParallelPixels = 1 << 15;
constexpr int64_t kRun = 8;       // units of work a thread claims at a time

// ------------------------------------------------------------------------------------------
// Elements: what a cube of T is blended in (W), and how a value is written as O (the cube's
// own type, or float32 for an 8-bit or half-precision cube)
// ------------------------------------------------------------------------------------------

template <typename T>
struct Work {
    using type = float;
};
template <>
struct Work<double> {
    using type = double;
};
template <typename T>
using W = typename Work<T>::type;

// Cubes of T are blended (bilinear; ring texels are weighted sums): floating and uint8 ones.
// The others (the integer elements of 2, 4 or 8 bytes, as unsigned bits) are copied.
template <typename T>
constexpr bool kBlends = !std::is_integral_v<T> || std::is_same_v<T, uint8_t>;

// The levels 0..255 as floats: an 8-bit texel converted by a load from this table (scalar
// int -> float conversions cost 9% of the channels-first 8-bit pass).
struct Levels {
    float value[256];
    constexpr Levels() : value() {
        for (int i = 0; i < 256; ++i) {
            value[i] = float(i);
        }
    }
};
constexpr Levels kLevels{};

// A texel of T as the number it is blended as.
template <typename T>
inline W<T> value(T v) {
    if constexpr (std::is_same_v<T, uint8_t>) {
        return kLevels.value[v];
    } else {
        return static_cast<W<T>>(v);
    }
}

// A blended value written as O: uint8 rounded to nearest (half up, as OpenCV's fixed point
// rounds) and saturated; a uint8 cube written as float scaled to [0, 1]; otherwise converted
// (8-bit ids as int64: the id, never blended).
template <typename T, typename O>
inline O store(W<T> v) {
    if constexpr (std::is_same_v<O, uint8_t>) {
        return static_cast<uint8_t>(std::min(std::max(v, W<T>(0)), W<T>(255)) + W<T>(0.5));
    } else if constexpr (std::is_same_v<T, uint8_t> && std::is_floating_point_v<O>) {
        return static_cast<O>(v * W<T>(1.0 / 255.0));
    } else {
        return static_cast<O>(v);
    }
}

// A texel copied (nearest): the element itself where O is T, an 8-bit id widened (an int64
// label image), else converted as by store.
template <typename T, typename O>
inline O copy(T v) {
    if constexpr (std::is_same_v<T, O>) {
        return v;
    } else if constexpr (std::is_integral_v<T> && std::is_integral_v<O>) {
        return static_cast<O>(v);
    } else {
        return store<T, O>(static_cast<W<T>>(v));
    }
}

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

#ifdef __SSE4_1__
// The blend of interior() for 8-bit channels-last texels of N = 3 or 4 channels (x86 with
// SSE4.1; elsewhere interior() itself): a texel's channels in one 4-byte load, blended as a
// vector of 4 floats (the same operations in the same order as interior's, so the same
// values), rounded half up and saturated to bytes (packus) or scaled to [0, 1], and written
// with one store of 4 channels (output pixels N apart; N = 3: the 4th is the next pixel's
// first, written after it; the segment's last pixel writes 3). For N = 3 a load reads a byte
// beyond the texel: pixels whose last tap lies beyond `safe` (the cube's last texels) go
// through interior(). The taps of a pixel kAhead on are prefetched.
template <typename O, int N, typename Taps>
void interior_rgb8(const uint8_t* __restrict cube, Taps t, int64_t m, const Layout& L,
                   int64_t safe, O fill, O* __restrict out, int64_t out_pix) {
    const int64_t dx = L.texel, dy = L.row;
    const auto texel = [](const uint8_t* q) {
        int32_t v;
        std::memcpy(&v, q, 4);
        return _mm_cvtepi32_ps(_mm_cvtepu8_epi32(_mm_cvtsi32_si128(v)));
    };
    for (int64_t p = 0; p < m; ++p) {
        const int64_t k = t.code(p);
        O* o = out + p * out_pix;
        if (k < 0) {
            for (int n = 0; n < N; ++n) {
                o[n] = fill;
            }
            continue;
        }
        if (k > safe) {
            interior<uint8_t, O, N>(cube, 1, t + p, 1, L, true, fill, o, 1, 0);
            continue;
        }
        if (p + kAhead < m) {   // the taps of a pixel ahead: not a stream the CPU foresees
            const int64_t ahead = std::max<int64_t>(t.code(p + kAhead), 0);
            __builtin_prefetch(cube + ahead);
            __builtin_prefetch(cube + ahead + dy);
        }
        const float x = float(t.fx(p)), y = float(t.fy(p)), e = 1 - x, s = 1 - y;
        const uint8_t* q = cube + k;
        __m128 acc = _mm_mul_ps(texel(q), _mm_set1_ps(s * e));   // blend()'s order
        acc = _mm_add_ps(acc, _mm_mul_ps(texel(q + dx), _mm_set1_ps(s * x)));
        acc = _mm_add_ps(acc, _mm_mul_ps(texel(q + dy), _mm_set1_ps(y * e)));
        acc = _mm_add_ps(acc, _mm_mul_ps(texel(q + dy + dx), _mm_set1_ps(y * x)));
        // stores of a constant size (a variable one is a loop), from registers
        const bool whole = N == 4 || p + 1 < m;
        if constexpr (std::is_same_v<O, uint8_t>) {
            const __m128i levels = _mm_cvttps_epi32(_mm_add_ps(acc, _mm_set1_ps(0.5f)));
            const int32_t v = _mm_cvtsi128_si32(
                _mm_packus_epi16(_mm_packus_epi32(levels, levels), levels));
            whole ? std::memcpy(o, &v, 4) : std::memcpy(o, &v, N);
        } else {
            const __m128 v = _mm_mul_ps(acc, _mm_set1_ps(float(1.0 / 255.0)));
            if (whole) {
                _mm_storeu_ps(o, v);
            } else {
                alignas(16) float w[4];
                _mm_store_ps(w, v);
                std::memcpy(o, w, N * sizeof(float));
            }
        }
    }
}
#endif

#ifdef __SSE4_1__
// The four taps (nw, ne, sw, se) of one channel of a cube with texel stride 1 as floats: the two
// taps of a row in one load (8-bit: 2 bytes; half precision: 4 bytes). Half precision needs
// F16C; without it only 8-bit planes take this path.
template <typename T>
constexpr bool kPlanesPath = std::is_same_v<T, uint8_t> || std::is_same_v<T, c10::BFloat16>
#ifdef __F16C__
                             || std::is_same_v<T, c10::Half>
#endif
    ;

template <typename T>
inline __m128 row_taps(const T* q, int64_t dy) {
    if constexpr (std::is_same_v<T, uint8_t>) {
        uint16_t north, south;
        std::memcpy(&north, q, 2);
        std::memcpy(&south, q + dy, 2);
        const int32_t taps = int32_t(north) | (int32_t(south) << 16);
        return _mm_cvtepi32_ps(_mm_cvtepu8_epi32(_mm_cvtsi32_si128(taps)));
    } else {
        int32_t north, south;
        std::memcpy(&north, q, 4);
        std::memcpy(&south, q + dy, 4);
        const __m128i halves = _mm_setr_epi32(north, south, 0, 0);
        if constexpr (std::is_same_v<T, c10::BFloat16>) {   // bfloat16: float's upper half
            return _mm_castsi128_ps(_mm_slli_epi32(_mm_cvtepu16_epi32(halves), 16));
        } else {
#ifdef __F16C__
            return _mm_cvtph_ps(halves);
#endif
        }
    }
}

// Half-precision outputs converted 4 at a time (a scalar conversion per channel cost 8% of the
// bfloat16 pass): bfloat16 always, float16 with F16C.
template <typename O>
constexpr bool kHalfOut = std::is_same_v<O, c10::BFloat16>
#ifdef __F16C__
                          || std::is_same_v<O, c10::Half>
#endif
    ;

// Four floats as four half-precision bit patterns (the low 64 bits, the first lowest), rounded
// as c10's conversions round: to nearest even; a bfloat16 NaN as c10's 0x7FC0, a float16 NaN
// quiet with its sign (F16C; c10 gives 0x7E00: either is NaN).
template <typename O>
inline uint64_t half_bits(__m128 v) {
    __m128i bits;
    if constexpr (std::is_same_v<O, c10::BFloat16>) {
        const __m128i u = _mm_castps_si128(v);
        const __m128i bias = _mm_add_epi32(_mm_and_si128(_mm_srli_epi32(u, 16), _mm_set1_epi32(1)),
                                           _mm_set1_epi32(0x7FFF));
        bits = _mm_srli_epi32(_mm_add_epi32(u, bias), 16);
        bits = _mm_blendv_epi8(bits, _mm_set1_epi32(0x7FC0),
                               _mm_castps_si128(_mm_cmpunord_ps(v, v)));
        bits = _mm_packus_epi32(bits, bits);
    } else {
#ifdef __F16C__
        bits = _mm_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT);
#endif
    }
    return static_cast<uint64_t>(_mm_cvtsi128_si64(bits));
}

// A pixel's N channels, packed in v (uint8: a byte each; half precision: 16 bits each, the
// first lowest), written out_chan apart.
template <typename O, int N>
inline void put_packed(uint64_t v, O* o, int64_t out_chan) {
    constexpr int bits = 8 * sizeof(O);
    for (int n = 0; n < N; ++n) {
        if constexpr (std::is_same_v<O, uint8_t>) {
            o[n * out_chan] = static_cast<uint8_t>(v >> (bits * n));
        } else {
            o[n * out_chan] = O(static_cast<uint16_t>(v >> (bits * n)), O::from_bits());
        }
    }
}

// The N blended channels of a pixel (acc's first N lanes) written as store() writes them
// (8-bit: rounded half up and saturated by packus; half precision: half_bits).
template <typename T, typename O, int N>
inline void write_planes(__m128 acc, O* o, int64_t out_chan) {
    if constexpr (std::is_same_v<O, uint8_t>) {
        const __m128i levels = _mm_cvttps_epi32(_mm_add_ps(acc, _mm_set1_ps(0.5f)));
        put_packed<O, N>(uint32_t(_mm_cvtsi128_si32(
            _mm_packus_epi16(_mm_packus_epi32(levels, levels), levels))), o, out_chan);
    } else if constexpr (kHalfOut<O>) {
        put_packed<O, N>(half_bits<O>(acc), o, out_chan);
    } else {
        alignas(16) float v[4];
        _mm_store_ps(v, acc);
        for (int n = 0; n < N; ++n) {
            o[n * out_chan] = store<T, O>(v[n]);
        }
    }
}

#ifdef __AVX2__
// write_planes' conversion of two pixels' blends (one in each 128-bit lane) at once: each
// lane's low 64 bits hold its pixel's 4 values as O (uint8: rounded half up and saturated;
// half precision: as half_bits rounds).
template <typename O>
inline __m256i pair_bits(__m256 acc) {
    if constexpr (std::is_same_v<O, uint8_t>) {
        const __m256i levels = _mm256_cvttps_epi32(_mm256_add_ps(acc, _mm256_set1_ps(0.5f)));
        const __m256i words = _mm256_packus_epi32(levels, levels);
        return _mm256_packus_epi16(words, words);
    } else if constexpr (std::is_same_v<O, c10::BFloat16>) {
        const __m256i u = _mm256_castps_si256(acc);
        const __m256i bias = _mm256_add_epi32(
            _mm256_and_si256(_mm256_srli_epi32(u, 16), _mm256_set1_epi32(1)),
            _mm256_set1_epi32(0x7FFF));
        __m256i bits = _mm256_srli_epi32(_mm256_add_epi32(u, bias), 16);
        bits = _mm256_blendv_epi8(bits, _mm256_set1_epi32(0x7FC0),
                                  _mm256_castps_si256(_mm256_cmp_ps(acc, acc, _CMP_UNORD_Q)));
        return _mm256_packus_epi32(bits, bits);
    } else {   // float16: A's 4 values, then B's, in 128 bits
        const __m128i h = _mm256_cvtps_ph(acc, _MM_FROUND_TO_NEAREST_INT);
        return _mm256_setr_m128i(h, _mm_unpackhi_epi64(h, h));
    }
}

// row_taps of two pixels (texel offsets a and b), one in each 128-bit lane.
template <typename T>
inline __m256 pair_taps(const T* q, int64_t a, int64_t b, int64_t dy) {
    if constexpr (std::is_same_v<T, uint8_t>) {
        uint16_t na, sa, nb, sb;
        std::memcpy(&na, q + a, 2);
        std::memcpy(&sa, q + a + dy, 2);
        std::memcpy(&nb, q + b, 2);
        std::memcpy(&sb, q + b + dy, 2);
        const uint64_t taps = uint64_t(na) | (uint64_t(sa) << 16) | (uint64_t(nb) << 32) |
                              (uint64_t(sb) << 48);
        return _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_cvtsi64_si128(int64_t(taps))));
    } else {
        int32_t na, sa, nb, sb;
        std::memcpy(&na, q + a, 4);
        std::memcpy(&sa, q + a + dy, 4);
        std::memcpy(&nb, q + b, 4);
        std::memcpy(&sb, q + b + dy, 4);
        const __m128i halves = _mm_setr_epi32(na, sa, nb, sb);
        if constexpr (std::is_same_v<T, c10::BFloat16>) {   // bfloat16: float's upper half
            return _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_cvtepu16_epi32(halves), 16));
        } else {
            return _mm256_cvtph_ps(halves);
        }
    }
}
#endif

// The blend of interior() for planes (texel stride 1, N <= 4 channels any stride apart) of
// 8-bit or half-precision texels (x86 with SSE4.1): per channel the four taps as 4 floats
// (row_taps), transposed so that each vector holds one tap of every channel, blended in
// interior's order (nw, ne, sw, se: the same values), then written channel by channel as
// store() writes them (8-bit: rounded half up and saturated by packus). No load reads beyond a
// pixel's taps.
template <typename T, typename O, int N, typename Taps>
void interior_planes(const T* __restrict cube, int64_t src_chan, Taps t, int64_t m,
                     const Layout& L, O fill, O* __restrict out, int64_t out_chan,
                     int64_t out_pix) {
    const int64_t dy = L.row;
    const auto prefetch = [&](int64_t p) {   // the taps of a pixel ahead: not a stream the
        if (p + kAhead < m) {                // CPU foresees
            const int64_t ahead = std::max<int64_t>(t.code(p + kAhead), 0);
            for (int n = 0; n < N; ++n) {
                __builtin_prefetch(cube + n * src_chan + ahead);
                __builtin_prefetch(cube + n * src_chan + ahead + dy);
            }
        }
    };
    const auto one = [&](int64_t p) {
        const int64_t k = t.code(p);
        O* o = out + p * out_pix;
        if (k < 0) {
            for (int n = 0; n < N; ++n) {
                o[n * out_chan] = fill;
            }
            return;
        }
        __m128 tap[4];   // channel n: (nw, ne, sw, se); after the transpose, tap j of every one
        for (int n = 0; n < 4; ++n) {
            tap[n] = n < N ? row_taps(cube + n * src_chan + k, dy) : _mm_setzero_ps();
        }
        _MM_TRANSPOSE4_PS(tap[0], tap[1], tap[2], tap[3]);
        const float x = float(t.fx(p)), y = float(t.fy(p)), e = 1 - x, s = 1 - y;
        __m128 acc = _mm_mul_ps(tap[0], _mm_set1_ps(s * e));   // blend()'s order
        acc = _mm_add_ps(acc, _mm_mul_ps(tap[1], _mm_set1_ps(s * x)));
        acc = _mm_add_ps(acc, _mm_mul_ps(tap[2], _mm_set1_ps(y * e)));
        acc = _mm_add_ps(acc, _mm_mul_ps(tap[3], _mm_set1_ps(y * x)));
        write_planes<T, O, N>(acc, o, out_chan);
    };
    int64_t p = 0;
#ifdef __AVX2__
    // Two pixels at a time, one in each 128-bit lane: the same operations as one() on each
    // (the same values), with half the shuffles, blends and conversions.
    for (; p + 1 < m; p += 2) {
        prefetch(p);
        prefetch(p + 1);
        const int64_t ka = t.code(p), kb = t.code(p + 1);
        if (ka < 0 || kb < 0) {
            one(p);
            one(p + 1);
            continue;
        }
        __m256 tap[4];
        for (int n = 0; n < 4; ++n) {
            tap[n] = n < N ? pair_taps(cube + n * src_chan, ka, kb, dy) : _mm256_setzero_ps();
        }
        // _MM_TRANSPOSE4_PS in each lane
        const __m256 t0 = _mm256_unpacklo_ps(tap[0], tap[1]);
        const __m256 t1 = _mm256_unpackhi_ps(tap[0], tap[1]);
        const __m256 t2 = _mm256_unpacklo_ps(tap[2], tap[3]);
        const __m256 t3 = _mm256_unpackhi_ps(tap[2], tap[3]);
        const __m256 nw = _mm256_shuffle_ps(t0, t2, 0x44), ne = _mm256_shuffle_ps(t0, t2, 0xEE);
        const __m256 sw = _mm256_shuffle_ps(t1, t3, 0x44), se = _mm256_shuffle_ps(t1, t3, 0xEE);
        const float xa = float(t.fx(p)), ya = float(t.fy(p)), xb = float(t.fx(p + 1)),
                    yb = float(t.fy(p + 1));
        // per lane (s e, s x, y e, y x): one() 's weights, each one product
        const __m256 w = _mm256_mul_ps(
            _mm256_setr_ps(1 - ya, 1 - ya, ya, ya, 1 - yb, 1 - yb, yb, yb),
            _mm256_setr_ps(1 - xa, xa, 1 - xa, xa, 1 - xb, xb, 1 - xb, xb));
        __m256 acc = _mm256_mul_ps(nw, _mm256_permute_ps(w, 0x00));   // blend()'s order
        acc = _mm256_add_ps(acc, _mm256_mul_ps(ne, _mm256_permute_ps(w, 0x55)));
        acc = _mm256_add_ps(acc, _mm256_mul_ps(sw, _mm256_permute_ps(w, 0xAA)));
        acc = _mm256_add_ps(acc, _mm256_mul_ps(se, _mm256_permute_ps(w, 0xFF)));
        O *oa = out + p * out_pix, *ob = oa + out_pix;
        if constexpr (std::is_same_v<O, uint8_t> || kHalfOut<O>) {   // both lanes at once
            const __m256i packed = pair_bits<O>(acc);
            put_packed<O, N>(uint64_t(_mm_cvtsi128_si64(_mm256_castsi256_si128(packed))), oa,
                             out_chan);
            put_packed<O, N>(uint64_t(_mm_cvtsi128_si64(_mm256_extracti128_si256(packed, 1))),
                             ob, out_chan);
        } else {
            write_planes<T, O, N>(_mm256_castps256_ps128(acc), oa, out_chan);
            write_planes<T, O, N>(_mm256_extractf128_ps(acc, 1), ob, out_chan);
        }
    }
#endif
    for (; p < m; ++p) {
        prefetch(p);
        one(p);
    }
}
#endif

// An edge pixel at pixel (x, y) of a perspective image (sample_image): its taps clamped to the
// image (grid_sample's border padding: the same values as the coordinate clamped), then read
// for every channel into out[c out_chan]. Not inlined: rare (the image's rim).
template <typename T, typename O, typename G>
__attribute__((noinline)) void image_edge_pixel(const T* image, G x, G y, const Layout& L,
                                                int64_t height, int64_t width, bool bilinear,
                                                const Planes& S, O* out) {
    const auto at = [&](int64_t j, int64_t i) {
        return std::clamp<int64_t>(i, 0, height - 1) * L.row +
               std::clamp<int64_t>(j, 0, width - 1) * L.texel;
    };
    if (!bilinear) {
        const int64_t k = at(static_cast<int64_t>(std::nearbyint(x)),
                             static_cast<int64_t>(std::nearbyint(y)));
        for (int64_t c = 0; c < S.chans; ++c) {
            out[c * S.out_chan] = copy<T, O>(image[c * S.src_chan + k]);
        }
        return;
    }
    if constexpr (kBlends<T>) {   // the other images are sampled nearest
        using V = W<T>;
        const G x0 = std::floor(x), y0 = std::floor(y);
        const int64_t j = static_cast<int64_t>(x0), i = static_cast<int64_t>(y0);
        const int64_t nw = at(j, i), ne = at(j + 1, i), sw = at(j, i + 1), se = at(j + 1, i + 1);
        for (int64_t c = 0; c < S.chans; ++c) {
            const T* q = image + c * S.src_chan;
            out[c * S.out_chan] = store<T, O>(blend<V>(value(q[nw]), value(q[ne]), value(q[sw]),
                                                       value(q[se]), V(x - x0), V(y - y0)));
        }
    }
}

// Where the edge pixels of a segment lie, and how they are read: their grid points (x, y
// pairs, unnormalised as grid_sample does) or atlas pixels (two arrays, from locate_rays),
// through the virtual atlas (edge_pixel); or pixels of a perspective image, clamped to it.
template <typename G>
struct GridPoints {
    const G* grid;
    template <typename T, typename O>
    void edge(const T* cube, const Ring<T>& R, int64_t p, const Layout& L, bool bilinear,
              const Planes& S, O* out) const {
        edge_pixel<T, O, G>(cube, R, unnormalize(grid[2 * p], L.half_x),
                            unnormalize(grid[2 * p + 1], L.half_y), L, bilinear, S, out);
    }
};
template <typename G>
struct AtlasPoints {
    const G *xs, *ys;
    template <typename T, typename O>
    void edge(const T* cube, const Ring<T>& R, int64_t p, const Layout& L, bool bilinear,
              const Planes& S, O* out) const {
        edge_pixel<T, O, G>(cube, R, xs[p], ys[p], L, bilinear, S, out);
    }
};
template <typename G>
struct ImagePoints {
    const G *xs, *ys;
    int64_t height, width;
    template <typename T, typename O>
    void edge(const T* image, const Ring<T>&, int64_t p, const Layout& L, bool bilinear,
              const Planes& S, O* out) const {
        image_edge_pixel<T, O, G>(image, xs[p], ys[p], L, height, width, bilinear, S, out);
    }
};

// Output pixels [lo, lo + m) of sample b: the entries `t` and the `points` (for the edge
// pixels) start at the first of them; the pixels outside read `fill`. Up to 4 channels per
// pass over the pixels (interior), then the edge pixels again.
template <typename T, typename O, typename G, typename Taps, typename Points>
void sample_span(const T* cube, const Ring<T>& R, Taps t, Points points, int64_t m,
                 const Layout& L, bool bilinear, O fill, const Planes& S, O* out) {
    for (int64_t c = 0; c < S.chans; c += 4) {
        const T* q = cube + c * S.src_chan;
        O* o = out + c * S.out_chan;
        const auto run = [&](auto channels) {
            constexpr int N = decltype(channels)::value;
#ifdef __SSE4_1__
            // (int64 ids are copied, never blended)
            if constexpr (std::is_same_v<T, uint8_t> && !std::is_same_v<O, int64_t>) {
                if (bilinear && (N == 3 || N == 4) && S.src_chan == 1 && S.out_chan == 1 &&
                    S.out_pix == N && S.chans == N) {
                    // the last tap's 4-byte load stays inside the cube
                    const int64_t safe = L.last() + (N - 1) - 3 - L.row - L.texel;
                    return interior_rgb8<O, N, Taps>(q, t, m, L, safe, fill, o, S.out_pix);
                }
            }
            if constexpr (kPlanesPath<T> && !std::is_same_v<O, int64_t>) {
                if (bilinear && L.texel == 1) {
                    return interior_planes<T, O, N, Taps>(q, S.src_chan, t, m, L, fill, o,
                                                          S.out_chan, S.out_pix);
                }
            }
#endif
            interior<T, O, N, Taps>(q, S.src_chan, t, m, L, bilinear, fill, o, S.out_chan,
                                    S.out_pix);
        };
        switch (std::min<int64_t>(S.chans - c, 4)) {
            case 1:
                run(std::integral_constant<int, 1>{});
                break;
            case 2:
                run(std::integral_constant<int, 2>{});
                break;
            case 3:
                run(std::integral_constant<int, 3>{});
                break;
            default:
                run(std::integral_constant<int, 4>{});
        }
    }
    for (int64_t p = 0; p < m; ++p) {
        if (t.code(p) == kEdge) {
            points.template edge<T, O>(cube, R, p, L, bilinear, S, out + p * S.out_pix);
        }
    }
}

// fn(i) for i in [0, units), units of about `unit_pixels` pixels each, on PyTorch's intra-op
// threads (at::parallel_for; one thread in DataLoader workers, or below kParallelPixels), every
// thread claiming runs of kRun consecutive units as it gets to them: a thread that the system
// deschedules (a busy machine) delays the call by what it holds, a run, not by half the work.
// Each unit writes pixels of its own, so the result does not depend on who computes what.
template <typename Fn>
void parallel_units(int64_t units, int64_t unit_pixels, Fn fn) {
    const int64_t runs = (units + kRun - 1) / kRun;
    const int64_t grain =
        std::max<int64_t>(1, kParallelPixels / (std::max<int64_t>(unit_pixels, 1) * kRun));
    std::atomic<int64_t> next{0};
    at::parallel_for(0, runs, grain, [&](int64_t, int64_t) {
        for (int64_t r = next.fetch_add(1, std::memory_order_relaxed); r < runs;
             r = next.fetch_add(1, std::memory_order_relaxed)) {
            for (int64_t i = r * kRun, end = std::min(units, i + kRun); i < end; ++i) {
                fn(i);
            }
        }
    });
}

// fn(b, lo, m) for the row segments [lo, lo + m) of kSegment pixels (fewer at a row's end) of
// every sample, the segments spread over the threads (parallel_units), every sample of a segment
// in turn, so that a table or rays shared by the batch are read from memory once. Rows, not
// tiles: the table or rays of a row segment are one stream that the CPU's prefetcher follows
// (tiles of 64 x 16 pixels read 16 short streams and waited for memory: the rays path took 1.6x
// as long, the table path 1.1x, 6 x 512 -> 1024 x 1024 on a 2-core AMD EPYC (Zen 3) VM).
template <typename Fn>
void for_segments(const Planes& S, Fn fn) {
    if (S.pixels == 0 || S.chans == 0) {   // an empty image: nothing to write
        return;
    }
    const int64_t per_row = (S.width + kSegment - 1) / kSegment;
    const int64_t segments = S.pixels / S.width * per_row;
    parallel_units(S.batch * segments, std::min(kSegment, S.width), [&](int64_t index) {
        const int64_t segment = index / S.batch, b = index % S.batch;
        const int64_t y = segment / per_row, x0 = (segment % per_row) * kSegment;
        fn(b, y * S.width + x0, std::min(kSegment, S.width - x0));
    });
}

// Sampling through a lookup table (the entries of a grid; fractions unused for nearest),
// shared by the batch (lut_batch = 0) or one per sample (lut_batch = P).
template <typename T, typename O, typename G>
void sample_lut(const T* src, const Entry<G>* table, const G* grid, int64_t lut_batch,
                const Ring<T>& R, const Layout& L, bool bilinear, O fill, Planes S, O* out) {
    // the top-left tap of the last interior pixel: its 4 taps (nearest: its 1) in the last face
    const int64_t limit = L.last() - (bilinear ? L.row + L.texel : 0);
    for_segments(S, [&](int64_t b, int64_t lo, int64_t m) {
        const int64_t at = b * lut_batch + lo;
        const Packed<G> taps{const_cast<Entry<G>*>(table) + at, limit};   // read only
        sample_span<T, O, G>(src + b * S.src_batch, R, taps, GridPoints<G>{grid + 2 * at}, m, L,
                             bilinear, fill, S, out + b * S.out_batch + lo * S.out_pix);
    });
}

// Output pixels [lo, lo + m) of one sample at grid points `g` (their `valid`, may be null):
// their taps computed into the stack, then sampled.
template <typename T, typename O, typename G>
void sample_points(const T* cube, const G* g, const uint8_t* valid, int64_t m, const Ring<T>& R,
                   const Layout& L, bool bilinear, O fill, const Planes& S, O* out) {
    SplitBuffer<G> buffer;
    locate<G>(g, m, valid, L, bilinear, buffer.taps());
    sample_span<T, O, G>(cube, R, buffer.taps(), GridPoints<G>{g}, m, L, bilinear, fill, S,
                         out);
}

// A grid used once (grid_batch = 0: one grid for the batch, else 2 P): the codes computed in
// the sampling pass, a segment at a time. Pixels where `valid` (bool, valid_batch = 0 or P;
// null: all valid) is false read `fill`, as if outside the atlas.
template <typename T, typename O, typename G>
void sample_grid(const T* src, const G* grid, int64_t grid_batch, const uint8_t* valid,
                 int64_t valid_batch, const Ring<T>& R, const Layout& L, bool bilinear, O fill,
                 Planes S, O* out) {
    for_segments(S, [&](int64_t b, int64_t lo, int64_t m) {
        sample_points<T, O, G>(src + b * S.src_batch, grid + b * grid_batch + 2 * lo,
                               valid == nullptr ? nullptr : valid + b * valid_batch + lo, m, R,
                               L, bilinear, fill, S, out + b * S.out_batch + lo * S.out_pix);
    });
}

// The face table (OS_FACE_CASES): the 6 cases of cubemap.grid._CASES, then its _ZERO_CASE.
constexpr int32_t kFaceCases[] = {OS_FACE_CASES};
static_assert(sizeof(kFaceCases) / sizeof(kFaceCases[0]) == 7 * 5,
              "OS_FACE_CASES: expected 7 cases of 5 integers");

template <int K, int Col>
constexpr int32_t case_entry() {
    return kFaceCases[5 * K + Col];
}

// Column Col of case K (K = 6: the zero ray) for the rotated ray (px, py, pz): 0 the face,
// 1 r . p, 3 b . p. Templates, so that every case is a plain selection of a component (the
// loop vectorises; a loop over the table did not).
template <typename G, int K, int Col>
inline G case_value(G px, G py, G pz) {
    if constexpr (Col == 0) {
        return G(case_entry<K, 0>());
    } else {
        constexpr int32_t axis = case_entry<K, Col>();
        const G v = axis == 0 ? px : (axis == 1 ? py : pz);
        if constexpr (case_entry<K, Col + 1>() > 0) {
            return v;
        } else {
            return -v;
        }
    }
}

// cubemap.grid.grid_xy's pick: the value of case 2 axis + neg, or of the zero case.
template <typename G, int Col>
inline G pick(bool use_x, bool use_y, bool neg, bool zero, G px, G py, G pz) {
    const G pos = use_x ? case_value<G, 0, Col>(px, py, pz)
                        : (use_y ? case_value<G, 2, Col>(px, py, pz)
                                 : case_value<G, 4, Col>(px, py, pz));
    const G ngt = use_x ? case_value<G, 1, Col>(px, py, pz)
                        : (use_y ? case_value<G, 3, Col>(px, py, pz)
                                 : case_value<G, 5, Col>(px, py, pz));
    return zero ? case_value<G, 6, Col>(px, py, pz) : (neg ? ngt : pos);
}

// p = R (x, y, z) for a row-major 3 x 3 R (r), in this order of operations (the compiled
// grid's: cubemap.grid.rotated_grid_xy), or (x, y, z) itself without a rotation.
template <typename G, bool Rotate>
inline void rotate(const G* r, G x, G y, G z, G& px, G& py, G& pz) {
    if (Rotate) {
        px = r[0] * x + r[1] * y;
        px = px + r[2] * z;
        py = r[3] * x + r[4] * y;
        py = py + r[5] * z;
        pz = r[6] * x + r[7] * y;
        pz = pz + r[8] * z;
    } else {
        px = x;
        py = y;
        pz = z;
    }
}

// The axis of a ray's cube face: its largest component's (x before y before z on ties, as
// cubemap.grid picks it), as (use_x, use_y, that component); ray_grid and locate_rays share it.
// Out-parameters, inlined: returned as a struct into a structured binding, it kept
// locate_rays' loop scalar (sample_rays 2x the time).
template <typename G>
__attribute__((always_inline)) inline void major_axis(G px, G py, G pz, bool& use_x,
                                                      bool& use_y, G& comp) {
    const G ax = std::fabs(px), ay = std::fabs(py), az = std::fabs(pz);
    use_x = (ax >= ay) & (ax >= az);
    use_y = !use_x & (ay >= az);
    comp = use_x ? px : (use_y ? py : pz);
}

// The atlas grid of `count` rays (x, y, z at rays[3 p ..]) rotated by `rot` (row-major 3 x 3,
// null: none), into grid[2 p], grid[2 p + 1]: cubemap.grid.rotated_grid_xy and grid_xy, the same
// operations in the same order (so the grid is inductor's, bit for bit).
template <typename G, bool Rotate>
void ray_grid(const G* __restrict rays, const G* __restrict rot, int64_t count,
              const Layout& L, G* __restrict grid) {
    const G f = G(L.face) / G(2), c = G(L.face - 1) / G(2), n = G(L.n), pad = G(L.pad);
    const G n6 = G(6 * L.n);
    G r[9];
    if (Rotate) {
        std::copy(rot, rot + 9, r);
    }
    for (int64_t p = 0; p < count; ++p) {
        const G x = rays[3 * p], y = rays[3 * p + 1], z = rays[3 * p + 2];
        G px, py, pz;
        rotate<G, Rotate>(r, x, y, z, px, py, pz);
        bool use_x, use_y;
        G comp;
        major_axis(px, py, pz, use_x, use_y, comp);
        const bool neg = comp < 0, zero = comp == 0;
        const G num_r = pick<G, 1>(use_x, use_y, neg, zero, px, py, pz);
        const G num_b = pick<G, 3>(use_x, use_y, neg, zero, px, py, pz);
        const G face = pick<G, 0>(use_x, use_y, neg, zero, px, py, pz);
        G depth = neg ? -comp : comp;
        depth = zero ? G(1) : depth;
        const G u = c + f * num_r / depth;
        const G v = c + f * num_b / depth;
        const G row0 = face * n;
        grid[2 * p] = (G(2) * (u + pad) + G(1)) / n - G(1);
        grid[2 * p + 1] = (G(2) * (v + pad + row0) + G(1)) / n6 - G(1);
    }
}

template <typename G>
void ray_grid(const G* rays, const G* rot, int64_t count, const Layout& L, G* grid) {
    if (rot != nullptr) {
        ray_grid<G, true>(rays, rot, count, L, grid);
    } else {
        ray_grid<G, false>(rays, rot, count, L, grid);
    }
}

// Column Col (1: r, 3: b) of the rotated ray (px, py, pz) in the two cases of dominant axis A
// (0 x, 1 y, 2 z; `neg`: the negative one): the component and sign of the face table chosen at
// compile time, so that a case is a component or its negation (a loop over the table did not
// vectorise, nor did selections among the seven cases at once).
template <typename G, int A, int Col>
inline G axis_value(bool neg, G px, G py, G pz) {
    constexpr int32_t axis = case_entry<2 * A, Col>(), sign = case_entry<2 * A, Col + 1>();
    if constexpr (axis == case_entry<2 * A + 1, Col>()) {
        const G v = axis == 0 ? px : (axis == 1 ? py : pz);
        const G pos = sign > 0 ? v : -v;
        if constexpr (sign == case_entry<2 * A + 1, Col + 1>()) {
            return pos;
        } else {
            return neg ? -pos : pos;
        }
    } else {
        return neg ? case_value<G, 2 * A + 1, Col>(px, py, pz)
                   : case_value<G, 2 * A, Col>(px, py, pz);
    }
}

// The bilinear taps of `count` rays rotated by `rot` (row-major 3 x 3, null: none): each ray's
// face and face pixel (u, v) as ray_grid finds them (the rotation, the dominant axis, r . p and
// b . p over a . p), then its atlas pixel x = u + pad, y = v + pad + face n straight away (what
// grid_sample unnormalises the grid of ray_grid to, up to float rounding: two divisions and a
// double-precision unnormalisation fewer per pixel), its code and fractions as locate computes
// them, and the atlas pixel into xs, ys (for the edge pixels). Nearest sampling goes through the
// grid itself (sample_rays): rounding to a texel is not continuous, so its ties are grid_sample's.
template <typename G, bool Rotate>
void locate_rays(const G* __restrict rays, const G* __restrict rot, int64_t count,
                 const uint8_t* __restrict valid, const Layout& L, Split<G> out,
                 G* __restrict xs, G* __restrict ys) {
    const G f = G(L.face) / G(2), centre = G(L.pad) + G(L.face - 1) / G(2), n = G(L.n);
    const int32_t face = static_cast<int32_t>(L.face), pad = static_cast<int32_t>(L.pad);
    const uint32_t stride = static_cast<uint32_t>(L.face_stride);
    const uint32_t row = static_cast<uint32_t>(L.row), texel = static_cast<uint32_t>(L.texel);
    G r[9];
    if (Rotate) {
        std::copy(rot, rot + 9, r);
    }
    for (int64_t p = 0; p < count; ++p) {
        const G x = rays[3 * p], y = rays[3 * p + 1], z = rays[3 * p + 2];
        G px, py, pz;
        rotate<G, Rotate>(r, x, y, z, px, py, pz);
        bool use_x, use_y;
        G comp;
        major_axis(px, py, pz, use_x, use_y, comp);
        const G depth = std::fabs(comp);
        const bool neg = comp < 0, zero = depth == 0;
        // every case computed, then selected: no branch, so the loop vectorises
        const G rx = axis_value<G, 0, 1>(neg, px, py, pz);
        const G ry = axis_value<G, 1, 1>(neg, px, py, pz);
        const G rz = axis_value<G, 2, 1>(neg, px, py, pz);
        const G bx = axis_value<G, 0, 3>(neg, px, py, pz);
        const G by = axis_value<G, 1, 3>(neg, px, py, pz);
        const G bz = axis_value<G, 2, 3>(neg, px, py, pz);
        const G num_r = use_x ? rx : (use_y ? ry : rz);
        const G num_b = use_x ? bx : (use_y ? by : bz);
        const int32_t kx = neg ? case_entry<1, 0>() : case_entry<0, 0>();
        const int32_t ky = neg ? case_entry<3, 0>() : case_entry<2, 0>();
        const int32_t kz = neg ? case_entry<5, 0>() : case_entry<4, 0>();
        // the zero ray: the centre of the zero case's face (its components are all 0)
        const int32_t k = zero ? case_entry<6, 0>() : (use_x ? kx : (use_y ? ky : kz));
        const G scale = f / (zero ? G(1) : depth);
        const G u = num_r * scale + centre, v = num_b * scale + centre;   // in the padded face
        const G u0 = std::floor(u), v0 = std::floor(v);
        const bool finite = (u0 >= G(-1)) & (u0 <= n) & (v0 >= G(-1)) & (v0 <= n);   // not NaN
        const int32_t j = static_cast<int32_t>(finite ? u0 : G(0));
        const int32_t i = static_cast<int32_t>(finite ? v0 : G(0));
        const bool interior = (i >= pad) & (i + 1 < pad + face) & (j >= pad) & (j + 1 < pad + face);
        const int32_t at = static_cast<int32_t>(static_cast<uint32_t>(k) * stride +
                                                static_cast<uint32_t>(i - pad) * row +
                                                static_cast<uint32_t>(j - pad) * texel);
        out.set(p, interior ? at : (finite ? kEdge : kOutside), u - u0, v - v0);
        xs[p] = u;
        ys[p] = v + G(k) * n;
    }
    if (valid != nullptr) {
        for (int64_t p = 0; p < count; ++p) {
            out.set_code(p, valid[p] ? out.code(p) : kOutside);
        }
    }
}

// sample_grid of the grid of rays (rays_batch = 0: one set for the batch, else 3 P) rotated
// per sample (rot_batch = 0 or 9; rot null: not rotated), a segment at a time, without storing
// a grid: bilinear taps straight from the rays (locate_rays), nearest ones through the grid of
// the segment (ray_grid, on the stack).
template <typename T, typename O, typename G>
void sample_rays(const T* src, const G* rays, int64_t rays_batch, const G* rot,
                 int64_t rot_batch, const uint8_t* valid, int64_t valid_batch, const Ring<T>& R,
                 const Layout& L, bool bilinear, O fill, Planes S, O* out) {
    for_segments(S, [&](int64_t b, int64_t lo, int64_t m) {
        const T* cube = src + b * S.src_batch;
        const G* ray = rays + b * rays_batch + 3 * lo;
        const G* r = rot == nullptr ? nullptr : rot + b * rot_batch;
        const uint8_t* ok = valid == nullptr ? nullptr : valid + b * valid_batch + lo;
        O* o = out + b * S.out_batch + lo * S.out_pix;
        if (!bilinear) {
            G g[2 * kSegment];
            ray_grid<G>(ray, r, m, L, g);
            return sample_points<T, O, G>(cube, g, ok, m, R, L, false, fill, S, o);
        }
        G xs[kSegment], ys[kSegment];
        SplitBuffer<G> buffer;
        if (r != nullptr) {
            locate_rays<G, true>(ray, r, m, ok, L, buffer.taps(), xs, ys);
        } else {
            locate_rays<G, false>(ray, r, m, ok, L, buffer.taps(), xs, ys);
        }
        sample_span<T, O, G>(cube, R, buffer.taps(), AtlasPoints<G>{xs, ys}, m, L, true, fill,
                             S, o);
    });
}


// ------------------------------------------------------------------------------------------
// Perspective images: rays rotated into a pinhole camera, its image sampled
// ------------------------------------------------------------------------------------------

// The taps in a perspective image of height x width texels (rows and texels L.row, L.texel
// apart) of `count` rays rotated by `rot` (row-major 3 x 3, Rotate) into the pinhole camera
// k = (fx, fy, cx, cy): pixel u = fx (x / z) + cx, v = fy (y / z) + cy (pinhole_project's
// operations), valid where z > 0, the pixel lies in [-0.5, W - 0.5] x [-0.5, H - 0.5] (Camera's
// image bounds) and `valid` (may be null) holds; written to valid_out. Codes as
// locate's: the top-left tap (nearest: the texel, rounded half to even) where every tap lies
// in the image, kEdge where a valid pixel's taps reach beyond it (read clamped), kOutside where
// invalid; xs, ys: the pixels (for the edge pixels).
template <typename G, bool Bilinear, bool Rotate>
void locate_pinhole(const G* __restrict rays, const G* __restrict rot, const G* __restrict k,
                    int64_t count, const uint8_t* __restrict valid, int64_t height,
                    int64_t width, const Layout& L, Split<G> out, G* __restrict xs,
                    G* __restrict ys, uint8_t* __restrict valid_out) {
    const G fx = k[0], fy = k[1], cx = k[2], cy = k[3];
    const G right = G(width) - G(0.5), bottom = G(height) - G(0.5);
    const int32_t w = static_cast<int32_t>(width), h = static_cast<int32_t>(height);
    const uint32_t row = static_cast<uint32_t>(L.row), texel = static_cast<uint32_t>(L.texel);
    const int32_t span = Bilinear ? 1 : 0;
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
        const G u0 = Bilinear ? std::floor(u) : std::nearbyint(u);
        const G v0 = Bilinear ? std::floor(v) : std::nearbyint(v);
        const int32_t j = static_cast<int32_t>(inside ? u0 : G(0));
        const int32_t i = static_cast<int32_t>(inside ? v0 : G(0));
        const bool interior = (j >= 0) & (j + span < w) & (i >= 0) & (i + span < h);
        const int32_t at = static_cast<int32_t>(static_cast<uint32_t>(i) * row +
                                                static_cast<uint32_t>(j) * texel);
        codes[p] = inside ? (interior ? at : kEdge) : kOutside;
        fxs[p] = u - u0;
        fys[p] = v - v0;
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


// ------------------------------------------------------------------------------------------
// Antialiasing of sample_image: the footprint rule of render/antialias.py through a mip pyramid
// ------------------------------------------------------------------------------------------

// A level of the mip pyramid of one image sample: height x width texels of `chans` channels,
// channel c of texel (i, j) at i row + j texel + c chan. Level 0 is the image (its strides);
// level k + 1 the 2 x 2 average of level k (an odd last row or column the average of the
// texels it holds, as avg_pool2d(2, ceil_mode=True)), channels-last and contiguous; uint8
// levels rounded half up.
template <typename T>
struct MipLevel {
    const T* data;
    int64_t height, width, row, texel, chan;
};

// What a 2 x 2 box sums in: uint16 for uint8 (4 x 255 fits), the work type otherwise.
template <typename T>
using BoxSum = std::conditional_t<std::is_same_v<T, uint8_t>, uint16_t, W<T>>;

template <typename T>
inline T box_mean(BoxSum<T> four) {
    if constexpr (std::is_same_v<T, uint8_t>) {
        return static_cast<uint8_t>((four + 2) >> 2);
    } else {
        return static_cast<T>(four * W<T>(0.25));
    }
}

// The level below `from` (its ceil halves) into dst, channels-last and contiguous. An odd last
// row or column counts twice, so that every mean is of four terms: the texels it holds. Rows
// of 8-bit texels of 3 or 4 channels, channels-last, take a vector path (x86 SSE4.1): two
// texels of both rows widened to 16 bits, summed, and the second texel's lanes shifted onto
// the first's (the same sums, in integers: the same bytes).
template <typename T>
MipLevel<T> mip_halve(const MipLevel<T>& from, int64_t chans, T* dst) {
    using S = BoxSum<T>;
    const int64_t height = (from.height + 1) / 2, width = (from.width + 1) / 2;
    const bool packed = from.chan == 1 && from.texel == chans;   // channels-last rows
    parallel_units(height, 4 * from.width, [&](int64_t i) {
        const T* a = from.data + 2 * i * from.row;
        const T* b = 2 * i + 1 < from.height ? a + from.row : a;
        T* o = dst + i * width * chans;
        int64_t done = 0;   // output texels written by the vector path
#ifdef __SSE4_1__
        if constexpr (std::is_same_v<T, uint8_t>) {
            if (packed && (chans == 3 || chans == 4)) {
                // pairs whose 8-byte loads stay within the row (the last pair's may not);
                // the 4-byte stores run one byte into the next texel for 3 channels, which
                // the next store (or the tail below) rewrites
                const int64_t pairs = from.width / 2;
                const int64_t safe = chans == 4 ? pairs : std::max<int64_t>(pairs - 1, 0);
                const int shift = int(chans) * 2;   // bytes of a texel's 16-bit lanes
                for (int64_t j = 0; j < safe; ++j) {
                    __m128i x, y;
                    x = _mm_cvtepu8_epi16(_mm_loadl_epi64(
                        reinterpret_cast<const __m128i*>(a + 2 * j * chans)));
                    y = _mm_cvtepu8_epi16(_mm_loadl_epi64(
                        reinterpret_cast<const __m128i*>(b + 2 * j * chans)));
                    __m128i s = _mm_add_epi16(x, y);
                    s = _mm_add_epi16(s, shift == 6 ? _mm_srli_si128(s, 6) : _mm_srli_si128(s, 8));
                    s = _mm_srli_epi16(_mm_add_epi16(s, _mm_set1_epi16(2)), 2);
                    const int32_t v = _mm_cvtsi128_si32(_mm_packus_epi16(s, s));
                    if (chans == 4 || j + 1 < width) {
                        std::memcpy(o + j * chans, &v, 4);
                    } else {
                        std::memcpy(o + j * chans, &v, 3);
                    }
                }
                done = safe;
            }
        }
#endif
        for (int64_t j = done; j < width; ++j) {
            const int64_t x0 = 2 * j, x1 = std::min(2 * j + 1, from.width - 1);
            for (int64_t c = 0; c < chans; ++c) {
                const int64_t c0 = c * from.chan + x0 * from.texel;
                const int64_t c1 = c * from.chan + x1 * from.texel;
                o[j * chans + c] = box_mean<T>(S(S(a[c0]) + S(a[c1]) + S(b[c0]) + S(b[c1])));
            }
        }
    });
    return MipLevel<T>{dst, height, width, width * chans, chans, 1};
}

// acc (chans) += weight x the bilinear value of level M at (x, y) (its pixels, centres at
// integers), the position clamped to the level (border padding). N > 0: chans == N, known at
// compile time (the channels' loop unrolled: 1.6x faster for 3 float32 planes).
template <int N, typename T>
inline void mip_tap(const MipLevel<T>& M, int64_t chans, W<T> x, W<T> y, W<T> weight,
                    W<T>* acc) {
    using V = W<T>;
    if constexpr (N > 0) {
        chans = N;
    }
    x = std::min(std::max(x, V(0)), V(M.width - 1));
    y = std::min(std::max(y, V(0)), V(M.height - 1));
    const int64_t j = static_cast<int64_t>(x), i = static_cast<int64_t>(y);
    const V fx = x - V(j), fy = y - V(i);
    const int64_t dj = j + 1 < M.width ? M.texel : 0, di = i + 1 < M.height ? M.row : 0;
    const T* p = M.data + i * M.row + j * M.texel;
    const V top = weight * (V(1) - fy), bottom = weight * fy;
    const V w00 = top * (V(1) - fx), w01 = top * fx, w10 = bottom * (V(1) - fx),
            w11 = bottom * fx;
    for (int64_t c = 0; c < chans; ++c) {
        const T* q = p + c * M.chan;
        acc[c] += w00 * value(q[0]) + w01 * value(q[dj]) + w10 * value(q[di]) +
                  w11 * value(q[di + dj]);
    }
}

#ifdef __SSE4_1__
// mip_tap (weight 1) for 8-bit channels-last levels of N = 3 or 4 channels (texel stride N,
// channel stride 1) as 4 floats (the 4th lane junk for N = 3): a texel's channels in one
// 4-byte load (interior_rgb8's), read one by one where a load would pass the level's last
// byte (an offset beyond `safe`).
template <int N>
inline __m128 mip_tap8(const MipLevel<uint8_t>& M, int64_t safe, float x, float y) {
    x = std::min(std::max(x, 0.0f), float(M.width - 1));
    y = std::min(std::max(y, 0.0f), float(M.height - 1));
    const int64_t j = static_cast<int64_t>(x), i = static_cast<int64_t>(y);
    const float fx = x - float(j), fy = y - float(i);
    const int64_t dj = j + 1 < M.width ? M.texel : 0, di = i + 1 < M.height ? M.row : 0;
    const int64_t at = i * M.row + j * M.texel;
    const uint8_t* q = M.data + at;
    int32_t v[4];
    if (__builtin_expect(at + di + dj <= safe, 1)) {   // loads of a constant size (a variable
        std::memcpy(&v[0], q, 4);                      // one was a byte loop, whose stores
        std::memcpy(&v[1], q + dj, 4);                 // stalled the load: 2x the time)
        std::memcpy(&v[2], q + di, 4);
        std::memcpy(&v[3], q + di + dj, 4);
    } else {
        const int64_t d[4] = {0, dj, di, di + dj};
        for (int n = 0; n < 4; ++n) {
            uint8_t bytes[4] = {0, 0, 0, 0};
            std::memcpy(bytes, q + d[n], N);
            std::memcpy(&v[n], bytes, 4);
        }
    }
    const auto texel = [&](int n) {
        return _mm_cvtepi32_ps(_mm_cvtepu8_epi32(_mm_cvtsi32_si128(v[n])));
    };
    const float top = 1.0f - fy, bottom = fy;
    const __m128 w00 = _mm_set1_ps(top * (1.0f - fx)), w01 = _mm_set1_ps(top * fx);
    const __m128 w10 = _mm_set1_ps(bottom * (1.0f - fx)), w11 = _mm_set1_ps(bottom * fx);
    return _mm_add_ps(_mm_add_ps(_mm_add_ps(_mm_mul_ps(w00, texel(0)), _mm_mul_ps(w01, texel(1))),
                                 _mm_mul_ps(w10, texel(2))),
                      _mm_mul_ps(w11, texel(3)));
}

// mip_tap8 for an 8-bit level of N planes (texel stride 1, channels M.chan apart): a channel's
// four taps in one vector (row_taps: two bytes of each row), times their weights, summed (a dot
// product); at the level's last row or column one by one, the taps clamped.
template <int N>
inline __m128 mip_tap8_planes(const MipLevel<uint8_t>& M, float x, float y) {
    x = std::min(std::max(x, 0.0f), float(M.width - 1));
    y = std::min(std::max(y, 0.0f), float(M.height - 1));
    const int64_t j = static_cast<int64_t>(x), i = static_cast<int64_t>(y);
    const float fx = x - float(j), fy = y - float(i);
    const uint8_t* q = M.data + i * M.row + j;
    const __m128 w = _mm_setr_ps((1.0f - fx) * (1.0f - fy), fx * (1.0f - fy),
                                 (1.0f - fx) * fy, fx * fy);
    // channel c's sum in lane c, combined in registers (values stored one by one and loaded
    // as a vector stalled the load: a third of the filter's time)
    __m128 d[4];
    if (j + 1 < M.width && i + 1 < M.height) {
        for (int c = 0; c < N; ++c) {
            d[c] = _mm_dp_ps(row_taps<uint8_t>(q + c * M.chan, M.row), w, 0xF1);
        }
    } else {   // the last row or column: its taps clamped
        const int64_t dj = j + 1 < M.width ? 1 : 0, di = i + 1 < M.height ? M.row : 0;
        for (int c = 0; c < N; ++c) {
            const uint8_t* t = q + c * M.chan;
            const __m128 taps = _mm_setr_ps(value(t[0]), value(t[dj]), value(t[di]),
                                             value(t[di + dj]));
            d[c] = _mm_dp_ps(taps, w, 0xF1);
        }
    }
    return _mm_movelh_ps(_mm_unpacklo_ps(d[0], d[1]),
                         N == 4 ? _mm_unpacklo_ps(d[2], d[3]) : d[2]);
}
#endif

// The footprint filter (antialias.py's rule, its taps in two by two): a pixel whose Jacobian
// column (finite differences of the image positions to the next output pixel: forward where
// both pixels are valid, else backward, else 0) is longer than `limit` pixels is the mean of 4
// bilinear lookups at (u, v) + (+-1/4) du + (+-1/4) dv, each in the mip level
// k = floor(log2(rho / 2)) (rho: the longer column's length; clamped to [0, last]), whose
// texels (2^k source pixels) are at most half a tap's share of the footprint across.
constexpr int kMipTaps = 4;

// floor(log2(x)) of a positive normal x, from its bits (vectorises; std::ilogb does not).
inline int32_t exponent(float x) {
    uint32_t bits;
    std::memcpy(&bits, &x, 4);
    return int32_t((bits >> 23) & 0xff) - 127;
}
inline int32_t exponent(double x) {
    uint64_t bits;
    std::memcpy(&bits, &x, 8);
    return int32_t((bits >> 52) & 0x7ff) - 1023;
}

// 2^n for n in the normal range, from its bits.
template <typename G>
inline G power_of_two(int32_t n) {
    if constexpr (std::is_same_v<G, float>) {
        const uint32_t bits = uint32_t(n + 127) << 23;
        float x;
        std::memcpy(&x, &bits, 4);
        return x;
    } else {
        const uint64_t bits = uint64_t(n + 1023) << 52;
        double x;
        std::memcpy(&x, &bits, 8);
        return x;
    }
}

// The footprints of the pixels [lo, lo + m) of row i (m <= kSegment) of an h x w output: into
// level (-1 where the pixel does not minify, else k) and, when X is not null, the taps' level-k
// positions X[t * kSegment + p], Y[...]. us, vs, ok: the image positions and validity, padded
// by one element before and after (index -1 and h w are readable, ok 0 there).
template <typename G>
void mip_footprints(const G* __restrict us, const G* __restrict vs,
                    const uint8_t* __restrict ok, int64_t i, int64_t lo, int64_t m, int64_t h,
                    int64_t w, G limit, int32_t last, int32_t* __restrict level,
                    G* __restrict X, G* __restrict Y) {
    const int64_t row = i * w;
    // the rows above and below (the row itself where there is none: its differences are 0)
    const int64_t up = i > 0 ? row - w : row, down = i + 1 < h ? row + w : row;
    const bool has_up = i > 0, has_down = i + 1 < h;
    for (int64_t p = lo; p < lo + m; ++p) {
        const int64_t at = row + p;
        const bool here = ok[at] != 0;
        const bool right = (p + 1 < w) & (ok[at + 1] != 0) & here;
        const bool left = (p > 0) & (ok[at - 1] != 0) & here;
        const bool below = has_down & (ok[down + p] != 0) & here;
        const bool above = has_up & (ok[up + p] != 0) & here;
        const G ax = right ? us[at + 1] - us[at] : (left ? us[at] - us[at - 1] : G(0));
        const G ay = right ? vs[at + 1] - vs[at] : (left ? vs[at] - vs[at - 1] : G(0));
        const G bx = below ? us[down + p] - us[at] : (above ? us[at] - us[up + p] : G(0));
        const G by = below ? vs[down + p] - vs[at] : (above ? vs[at] - vs[up + p] : G(0));
        const G a = ax * ax + ay * ay, b = bx * bx + by * by;
        const bool minifies = here & ((a > limit) | (b > limit));
        // k = floor(log2(rho / 2)) = floor(log2(rho^2) / 2) - 1 from the exponent of rho^2
        // (a positive normal number where the pixel minifies), and 2^-k from its bits
        const int32_t k = std::min(std::max(exponent(std::max(a, b)) / 2 - 1, 0), last);
        const G scale = power_of_two<G>(-k);
        level[p - lo] = minifies ? k : -1;
        if (X != nullptr) {
            const G cx = (us[at] + G(0.5)) * scale - G(0.5);
            const G cy = (vs[at] + G(0.5)) * scale - G(0.5);
            const G qa = G(0.25) * scale, qb = G(0.25) * scale;
            for (int t = 0; t < kMipTaps; ++t) {
                const G sa = (t & 1) ? qa : -qa, sb = (t & 2) ? qb : -qb;
                X[t * kSegment + (p - lo)] = cx + sa * ax + sb * bx;
                Y[t * kSegment + (p - lo)] = cy + sa * ay + sb * by;
            }
        }
    }
}

// sample_image's pixels of images (B, C, H, W) along rays whose footprint minifies the image,
// filtered (mip_footprints) through a mip pyramid built here, only the levels they read, per
// sample (once for an image shared by the batch); out's other pixels are left as they are.
template <typename T, typename O, typename G>
void mip_image(const T* src, int64_t src_batch, int64_t src_chan, const G* rays,
               int64_t rays_batch, const G* rot, int64_t rot_batch, const G* k, int64_t k_batch,
               const uint8_t* valid, int64_t height, int64_t width, const Layout& L, G limit,
               Planes S, O* out) {
    using V = W<T>;
    const int64_t h = S.pixels / S.width, w = S.width, chans = S.chans;
    const int64_t segments = (w + kSegment - 1) / kSegment;
    // positions and validity padded by one element at both ends
    std::unique_ptr<G[]> u_mem(new G[S.pixels + 2]), v_mem(new G[S.pixels + 2]);
    std::unique_ptr<uint8_t[]> ok_mem(new uint8_t[S.pixels + 2]);
    G* us = u_mem.get() + 1;
    G* vs = v_mem.get() + 1;
    uint8_t* ok = ok_mem.get() + 1;
    us[-1] = us[S.pixels] = vs[-1] = vs[S.pixels] = G(0);
    ok[-1] = ok[S.pixels] = 0;
    std::vector<int32_t> peaks(h * segments);
    int32_t depth = 0;   // the deepest level of a full pyramid
    while ((int64_t(1) << depth) < std::max(height, width)) {
        ++depth;
    }
    // an image of at most 4 texels an output pixel: its whole pyramid (at most 1/3 of its
    // texels) costs less than the pass that finds the levels read (the footprints of every
    // pixel once more), and the levels read are the same (clamped to the deepest either way)
    const bool whole = height * width <= 4 * S.pixels;
    std::vector<std::vector<T>> memory;
    std::vector<MipLevel<T>> levels;
    const T* built = nullptr;
    for (int64_t b = 0; b < S.batch; ++b) {
        const G* ray = rays + b * rays_batch;
        const G* r = rot == nullptr ? nullptr : rot + b * rot_batch;
        const G* kb = k + b * k_batch;
        std::memcpy(ok, valid + b * S.pixels, S.pixels);
        const G fx = kb[0], fy = kb[1], cx = kb[2], cy = kb[3];
        // the pixels' image positions, as locate_pinhole computes them, and the deepest level
        // each row segment reads
        const auto first = [&](auto rotate_) {
            constexpr bool R = decltype(rotate_)::value;
            parallel_units(h, w, [&](int64_t i) {
                for (int64_t p = i * w; p < (i + 1) * w; ++p) {
                    G px, py, pz;
                    rotate<G, R>(r, ray[3 * p], ray[3 * p + 1], ray[3 * p + 2], px, py, pz);
                    const G z = pz > G(0) ? pz : G(1);
                    us[p] = fx * (px / z) + cx;
                    vs[p] = fy * (py / z) + cy;
                }
            });
        };
        r != nullptr ? first(std::true_type{}) : first(std::false_type{});
        if (whole) {   // every level, every segment: no pass to find them
            std::fill(peaks.begin(), peaks.end(), depth);
        } else {
            parallel_units(h, w, [&](int64_t i) {
                int32_t level[kSegment];
                for (int64_t s = 0; s < segments; ++s) {
                    const int64_t lo = s * kSegment, m = std::min(kSegment, w - lo);
                    mip_footprints<G>(us, vs, ok, i, lo, m, h, w, limit, depth, level, nullptr,
                                      nullptr);
                    int32_t peak = -1;
                    for (int64_t p = 0; p < m; ++p) {
                        peak = std::max(peak, level[p]);
                    }
                    peaks[i * segments + s] = peak;
                }
            });
        }
        const int32_t peak = *std::max_element(peaks.begin(), peaks.end());
        if (peak < 0) {
            continue;   // nothing minifies
        }
        const T* image = src + b * src_batch;
        if (image != built) {
            levels.assign(1, MipLevel<T>{image, height, width, L.row, L.texel, src_chan});
            memory.clear();
            built = image;
        }
        while (static_cast<int32_t>(levels.size()) <= peak) {
            const MipLevel<T> top = levels.back();
            memory.emplace_back(((top.height + 1) / 2) * ((top.width + 1) / 2) * chans);
            levels.push_back(mip_halve(top, chans, memory.back().data()));
        }
        const int32_t last = peak;
        O* o_b = out + b * S.out_batch;
#ifdef __SSE4_1__
        // 8-bit images of 3 or 4 channels: the vector taps, channels-last (the pyramid's levels
        // and a channels-last image) or planes (a channels-first image's level 0)
        int vector = 0;
        int64_t safe[64];
        bool planes = false;
        if constexpr (std::is_same_v<T, uint8_t>) {
            if (chans == 3 || chans == 4) {
                vector = int(chans);
                planes = !(src_chan == 1 && L.texel == chans);
                vector = planes && L.texel != 1 ? 0 : vector;
                for (int32_t m = 0; m <= last; ++m) {
                    const MipLevel<T>& M = levels[m];
                    safe[m] = (M.height - 1) * M.row + (M.width - 1) * M.texel + chans - 4;
                }
            }
        }
#endif
        parallel_units(h * segments, std::min(kSegment, w), [&](int64_t index) {
            const int64_t i = index / segments, lo = (index % segments) * kSegment;
            const int64_t m = std::min(kSegment, w - lo);
            if (peaks[index] < 0) {
                return;
            }
            int32_t level[kSegment];
            G X[kMipTaps * kSegment], Y[kMipTaps * kSegment];
            mip_footprints<G>(us, vs, ok, i, lo, m, h, w, limit, last, level, X, Y);
            std::vector<V> acc(chans);
            for (int64_t p = 0; p < m; ++p) {
                if (level[p] < 0) {
                    continue;
                }
                const MipLevel<T>& M = levels[level[p]];
                O* o = o_b + (i * w + lo + p) * S.out_pix;
                const V weight = V(1) / V(kMipTaps);
#ifdef __SSE4_1__
                if constexpr (std::is_same_v<T, uint8_t>) {
                    if (vector != 0) {
                        const int64_t sm = safe[level[p]];
                        const bool plane = planes && level[p] == 0;
                        __m128 sum = _mm_setzero_ps();
                        for (int t = 0; t < kMipTaps; ++t) {
                            const float x = float(X[t * kSegment + p]);
                            const float y = float(Y[t * kSegment + p]);
                            sum = _mm_add_ps(
                                sum, plane ? (vector == 3 ? mip_tap8_planes<3>(M, x, y)
                                                          : mip_tap8_planes<4>(M, x, y))
                                           : (vector == 3 ? mip_tap8<3>(M, sm, x, y)
                                                          : mip_tap8<4>(M, sm, x, y)));
                        }
                        alignas(16) float v[4];
                        _mm_store_ps(v, _mm_mul_ps(sum, _mm_set1_ps(weight)));
                        for (int64_t c = 0; c < chans; ++c) {
                            o[c * S.out_chan] = store<T, O>(v[c]);
                        }
                        continue;
                    }
                }
#endif
                // the sums of N channels known at compile time in a local array (registers:
                // through the heap vector each tap's sums went to memory and back, 1.1-1.4x
                // the time), any other number in `acc`
                const auto taps = [&](auto n_) {
                    constexpr int N = decltype(n_)::value;
                    V local[N > 0 ? N : 1] = {};
                    V* sums = N > 0 ? local : acc.data();
                    if (N == 0) {
                        std::fill(acc.begin(), acc.end(), V(0));
                    }
                    for (int t = 0; t < kMipTaps; ++t) {
                        mip_tap<N>(M, chans, V(X[t * kSegment + p]), V(Y[t * kSegment + p]),
                                   weight, sums);
                    }
                    for (int64_t c = 0; c < chans; ++c) {
                        o[c * S.out_chan] = store<T, O>(sums[c]);
                    }
                };
                if (chans == 3) {
                    taps(std::integral_constant<int, 3>{});
                } else if (chans == 1) {
                    taps(std::integral_constant<int, 1>{});
                } else if (chans == 4) {
                    taps(std::integral_constant<int, 4>{});
                } else {
                    taps(std::integral_constant<int, 0>{});
                }
            }
        });
    }
}

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


// ------------------------------------------------------------------------------------------
// The ops: tensors in, checked, then the loops above per cube element (float32, float64,
// float16, bfloat16, uint8; or the element size 2, 4, 8 bytes of a cube sampled nearest, whose
// elements are copied: any dtype, exact), output element (the cube's, or float32 for a uint8,
// float16 or bfloat16 cube) and grid dtype (float64 for a float64 cube, float32 for the other
// blended ones, either for a copied cube). `fill`: the value of the pixels outside (an
// integer: the ignore index of labels), converted to the output element (two's complement for
// the copied elements).
// ------------------------------------------------------------------------------------------

namespace {

constexpr int64_t kMaxOffset = int64_t(1) << 31;  // the codes are int32

bool blends(const at::Tensor& t) {
    const auto s = t.scalar_type();
    return s == at::kFloat || s == at::kDouble || s == at::kHalf || s == at::kBFloat16 ||
           s == at::kByte;
}

// The grid dtype a blended cube is sampled with.
at::ScalarType work_dtype(const at::Tensor& cube) {
    return cube.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
}

// Calls fn(T{}, O{}, G{}) with T the cube's element type, O the output's and G the grid's.
template <typename Fn>
void dispatch(const at::Tensor& cube, const at::Tensor& out, at::ScalarType grid, Fn fn) {
    const bool to_float = out.scalar_type() == at::kFloat;
    if (cube.scalar_type() == at::kByte && out.scalar_type() == at::kLong) {   // 8-bit ids
        return grid == at::kFloat ? fn(uint8_t{}, int64_t{}, float{})
                                  : fn(uint8_t{}, int64_t{}, double{});
    }
    const auto with_grid = [&](auto element) {
        using E = decltype(element);
        if (grid == at::kFloat) {
            fn(element, E{}, float{});
        } else {
            fn(element, E{}, double{});
        }
    };
    switch (cube.scalar_type()) {
        case at::kFloat:
            return fn(float{}, float{}, float{});
        case at::kDouble:
            return fn(double{}, double{}, double{});
        case at::kHalf:
            return to_float ? fn(c10::Half{}, float{}, float{})
                            : fn(c10::Half{}, c10::Half{}, float{});
        case at::kBFloat16:
            return to_float ? fn(c10::BFloat16{}, float{}, float{})
                            : fn(c10::BFloat16{}, c10::BFloat16{}, float{});
        case at::kByte:
            return to_float ? fn(uint8_t{}, float{}, float{}) : with_grid(uint8_t{});
        default:
            break;
    }
    switch (cube.element_size()) {
        case 1:
            return with_grid(uint8_t{});
        case 2:
            return with_grid(uint16_t{});
        case 4:
            return with_grid(uint32_t{});
        default:
            return with_grid(uint64_t{});
    }
}

void check_cpu(const char* op, const char* name, const at::Tensor& t) {
    TORCH_CHECK(t.device().is_cpu(), op, ": ", name, ": expected a CPU tensor, got one on ",
                t.device());
}

void check_contiguous(const char* op, const char* name, const at::Tensor& t) {
    check_cpu(op, name, t);
    TORCH_CHECK(t.is_contiguous(), op, ": ", name, ": expected a contiguous tensor, got strides ",
                t.strides(), " for shape ", t.sizes());
}

// (B', ...) with B' 1 (shared by the batch) or B.
void check_batch(const char* op, const char* name, const at::Tensor& t, int64_t batch) {
    TORCH_CHECK(t.size(0) == 1 || t.size(0) == batch, op, ": ", name, ": expected batch 1 or ",
                batch, ", got shape ", t.sizes());
}

// face, pad and the strides (face, row, texel) of a layout whose offsets fit the int32 codes.
Layout check_layout(const char* op, int64_t face, int64_t pad, at::IntArrayRef strides) {
    TORCH_CHECK(face >= 1 && pad >= 0 && face + 2 * pad < kMaxOffset / 6, op,
                ": face, pad: expected F >= 1 and pad >= 0, got ", face, " and ", pad);
    TORCH_CHECK(strides.size() == 3 && strides[0] >= 0 && strides[1] >= 0 && strides[2] >= 0,
                op, ": strides: expected (face, row, texel) >= 0, got ", strides);
    const Layout L = layout(face, pad, strides[0], strides[1], strides[2]);
    TORCH_CHECK(L.last() < kMaxOffset, op, ": cube: too large for int32 offsets (strides ",
                strides, ")");
    return L;
}

// The elements a sampler reads from t (a cube or an image): blended ones (float32, float64,
// float16, bfloat16, uint8) for bilinear sampling, or any of 1, 2, 4 or 8 bytes, copied, for
// nearest.
void check_elements(const char* op, const char* name, const at::Tensor& t, bool bilinear) {
    if (bilinear) {
        TORCH_CHECK(blends(t), op, ": ", name, ": bilinear sampling needs float32, float64, "
                    "float16, bfloat16 or uint8, got ", t.scalar_type());
    } else {
        const int64_t size = t.element_size();
        TORCH_CHECK(blends(t) || size == 1 || size == 2 || size == 4 || size == 8, op, ": ",
                    name, ": nearest sampling copies elements of 1, 2, 4 or 8 bytes, got ",
                    t.scalar_type());
    }
}

// cube (B, 6, C, F, F) on the CPU, any strides; its element type one the loops read; offsets
// within a sample and channel that fit the int32 codes.
Layout check_cube(const char* op, const at::Tensor& cube, bool bilinear, int64_t pad) {
    check_cpu(op, "cube", cube);
    TORCH_CHECK(cube.dim() == 5 && cube.size(1) == 6 && cube.size(3) == cube.size(4) &&
                    cube.size(3) >= 1,
                op, ": cube: expected shape (B, 6, C, F, F), got ", cube.sizes());
    check_elements(op, "cube", cube, bilinear);
    return check_layout(op, cube.size(4), pad, {cube.stride(1), cube.stride(3), cube.stride(4)});
}

// A grid-like input (B', ..., last) in the dtype the cube is sampled with.
void check_points(const char* op, const char* name, const at::Tensor& t, const at::Tensor& cube,
                  bool bilinear, int64_t dim, int64_t last) {
    check_contiguous(op, name, t);
    TORCH_CHECK(t.dim() == dim && t.size(dim - 1) == last, op, ": ", name, ": expected ", dim,
                " dimensions, the last of size ", last, ", got shape ", t.sizes());
    check_batch(op, name, t, cube.size(0));
    if (cube.is_floating_point() || (bilinear && blends(cube))) {
        TORCH_CHECK(t.scalar_type() == work_dtype(cube), op, ": ", name, ": expected ",
                    work_dtype(cube), " for a ", cube.scalar_type(), " cube, got ",
                    t.scalar_type());
    } else {
        TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble, op, ": ",
                    name, ": expected float32 or float64, got ", t.scalar_type());
    }
}

// out (B, C, H, W) in the cube's dtype (or float32 for a uint8, float16 or bfloat16 cube), its
// pixels row-major `pix` elements apart: planes (pix 1, any channel stride) or channels-last
// (channel stride 1, pix >= C).
void check_out(const char* op, const at::Tensor& out, const at::Tensor& cube, int64_t height,
               int64_t width, bool bilinear) {
    check_cpu(op, "out", out);
    const auto s = cube.scalar_type();
    const bool ids = !bilinear && s == at::kByte;   // 8-bit ids may widen to int64
    TORCH_CHECK(out.scalar_type() == s || (out.scalar_type() == at::kFloat &&
                                           (s == at::kByte || s == at::kHalf ||
                                            s == at::kBFloat16)) ||
                    (ids && out.scalar_type() == at::kLong),
                op, ": out: expected ", s, s == at::kByte || s == at::kHalf ||
                s == at::kBFloat16 ? " or float32" : "", ids ? " or int64" : "", ", got ",
                out.scalar_type());
    TORCH_CHECK(out.dim() == 4 && out.size(0) == cube.size(0) && out.size(1) == cube.size(2) &&
                    out.size(2) == height && out.size(3) == width,
                op, ": out: expected shape (", cube.size(0), ", ", cube.size(2), ", ", height,
                ", ", width, "), got ", out.sizes());
    const int64_t pix = out.stride(3), chans = out.size(1);
    TORCH_CHECK(out.numel() == 0 ||
                    ((out.stride(2) == width * pix || height == 1) &&
                     (out.stride(0) != 0 || out.size(0) == 1) &&
                     ((pix == 1 && (out.stride(1) != 0 || chans == 1)) ||
                      (out.stride(1) == 1 && pix >= chans))),
                op, ": out: expected H x W planes or channels-last pixels, got strides ",
                out.strides());
}

// valid (1 or B, H, W) bool, or none.
void check_valid(const char* op, const std::optional<at::Tensor>& valid, int64_t batch,
                 int64_t height, int64_t width) {
    if (!valid.has_value()) {
        return;
    }
    check_contiguous(op, "valid", *valid);
    TORCH_CHECK(valid->scalar_type() == at::kBool, op, ": valid: expected bool, got ",
                valid->scalar_type());
    TORCH_CHECK(valid->dim() == 3 && valid->size(1) == height && valid->size(2) == width, op,
                ": valid: expected shape (1 or ", batch, ", ", height, ", ", width, "), got ",
                valid->sizes());
    check_batch(op, "valid", *valid, batch);
}

// The ring (fast._ring_offsets): ring_src (N, K) int64 offsets within a sample and channel of
// the cube, N = 6 (n^2 - F^2) border texels (any N >= 1 without a border), and ring_weight of
// the same shape in the dtype the cube is blended in (float64 for float64, else float32), or
// none (copies).
void check_ring(const char* op, const at::Tensor& ring_src,
                const std::optional<at::Tensor>& ring_weight, const at::Tensor& cube,
                int64_t pad) {
    const int64_t f = cube.size(4), n = f + 2 * pad;
    check_contiguous(op, "ring_src", ring_src);
    TORCH_CHECK(ring_src.scalar_type() == at::kLong, op, ": ring_src: expected int64, got ",
                ring_src.scalar_type());
    TORCH_CHECK(ring_src.dim() == 2 && ring_src.size(1) >= 1 &&
                    (pad == 0 ? ring_src.size(0) >= 1 : ring_src.size(0) == 6 * (n * n - f * f)),
                op, ": ring_src: expected shape (", 6 * (n * n - f * f),
                ", K) for F = ", f, " and pad = ", pad, ", got ", ring_src.sizes());
    if (ring_weight.has_value()) {
        check_contiguous(op, "ring_weight", *ring_weight);
        TORCH_CHECK(blends(cube) && ring_weight->scalar_type() == work_dtype(cube), op,
                    ": ring_weight: expected ", work_dtype(cube), " for a ", cube.scalar_type(),
                    " cube (none for copied elements), got ", ring_weight->scalar_type());
        TORCH_CHECK(ring_weight->sizes() == ring_src.sizes(), op,
                    ": ring_weight: expected the shape of ring_src ", ring_src.sizes(), ", got ",
                    ring_weight->sizes());
    }
}

template <typename T>
Ring<T> ring(const at::Tensor& ring_src, const std::optional<at::Tensor>& ring_weight,
             const Layout& L) {
    return Ring<T>{ring_src.const_data_ptr<int64_t>(),
                   ring_weight.has_value()
                       ? static_cast<const W<T>*>(ring_weight->const_data_ptr())
                       : nullptr,
                   ring_src.size(1), L.last()};
}

Planes planes(const at::Tensor& cube, const at::Tensor& out) {
    return Planes{out.size(0),   out.size(1),    out.size(2) * out.size(3),
                  out.size(3),   cube.stride(0), cube.stride(2),
                  out.stride(0), out.stride(1),  out.stride(3)};
}

template <typename T>
const T* elements(const at::Tensor& t) {
    return static_cast<const T*>(t.const_data_ptr());
}

const uint8_t* mask(const std::optional<at::Tensor>& valid) {
    return valid.has_value() ? static_cast<const uint8_t*>(valid->const_data_ptr()) : nullptr;
}

// Elements between the samples of an input shared by the batch (0) or not.
int64_t batch_stride(const at::Tensor& t) {
    return t.size(0) == 1 ? 0 : t.stride(0);
}

int64_t batch_stride(const std::optional<at::Tensor>& t) {
    return t.has_value() ? batch_stride(*t) : 0;
}

// The fill value as O: an int, its two's complement bits for the copied elements.
template <typename O>
O fill_value(int64_t fill) {
    if constexpr (std::is_integral_v<O>) {
        return static_cast<O>(fill);
    } else {
        return static_cast<O>(static_cast<float>(fill));
    }
}

// A lookup table (B', P, 3) for a grid (B', P, 2): int32 entries for a float32 grid, int64
// for a float64 one.
void check_table(const char* op, const at::Tensor& table, const at::Tensor& grid) {
    check_contiguous(op, "table", table);
    const auto entry = grid.scalar_type() == at::kFloat ? at::kInt : at::kLong;
    TORCH_CHECK(table.scalar_type() == entry, op, ": table: expected ", entry, " for a ",
                grid.scalar_type(), " grid, got ", table.scalar_type());
    TORCH_CHECK(table.dim() == 3 && table.size(0) == grid.size(0) &&
                    table.size(1) == grid.size(1) && table.size(2) == 3,
                op, ": table: expected shape (", grid.size(0), ", ", grid.size(1), ", 3), got ",
                table.sizes());
}

// build_lut: the entries (code, fraction bits) of grid (B', P, 2) into table (B', P, 3), int32
// for a float32 grid, int64 for a float64 one, for cubes of faces `face` with the strides
// (face, row, texel) of one channel.

}  // namespace
