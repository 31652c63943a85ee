#pragma once

// The antialiasing of sample_image (mip_image): antialias.py's footprint rule through a mip
// pyramid. Part of the fast sampler's kernels (sample_base.h).

#include "sample_rays.h"

namespace {

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

// The deepest level of a full pyramid of a height x width image (its 1 x 1 level).
inline int32_t mip_depth(int64_t height, int64_t width) {
    int32_t depth = 0;
    while ((int64_t(1) << depth) < std::max(height, width)) {
        ++depth;
    }
    return depth;
}

// The mip pyramid of one image sample: level 0 the image itself (its strides), the levels
// below built as far as a call reads them (reach), kept while the image is the same.
template <typename T>
struct MipPyramid {
    std::vector<std::vector<T>> memory;
    std::vector<MipLevel<T>> levels;
    const T* built = nullptr;

    void reach(const T* image, int64_t height, int64_t width, const Layout& L, int64_t src_chan,
               int64_t chans, int32_t peak) {
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
    }
};

// The deepest level each row segment of an h x w output reads (-1: none minifies) into peaks
// (h x segments), and the deepest of all: mip_footprints' levels, or `depth` everywhere for
// `whole` (an image of at most 4 texels an output pixel: its whole pyramid, at most 1/3 of its
// texels, costs less than the pass that finds the levels read, the footprints of every pixel
// once more, and the levels read are the same, clamped to the deepest either way).
template <typename G>
int32_t mip_peaks(const G* us, const G* vs, const uint8_t* ok, int64_t h, int64_t w, G limit,
                  int32_t depth, bool whole, std::vector<int32_t>& peaks) {
    const int64_t segments = (w + kSegment - 1) / kSegment;
    peaks.resize(h * segments);
    if (whole) {
        std::fill(peaks.begin(), peaks.end(), depth);
        return depth;
    }
    parallel_units(h, w, [&](int64_t i) {
        int32_t level[kSegment];
        for (int64_t s = 0; s < segments; ++s) {
            const int64_t lo = s * kSegment, m = std::min(kSegment, w - lo);
            mip_footprints<G>(us, vs, ok, i, lo, m, h, w, limit, depth, level, nullptr, nullptr);
            int32_t peak = -1;
            for (int64_t p = 0; p < m; ++p) {
                peak = std::max(peak, level[p]);
            }
            peaks[i * segments + s] = peak;
        }
    });
    return *std::max_element(peaks.begin(), peaks.end());
}

// How the filter reads a pyramid of `chans` channels to `last`: 8-bit images of 3 or 4
// channels take the vector taps, channels-last (the pyramid's levels and a channels-last image)
// or planes (a channels-first image's level 0); `safe`: per level the last offset a 4-byte
// load of a texel may start at.
template <typename T>
struct MipReader {
    int vector = 0;
    bool planes = false;
    int64_t safe[64] = {};

    MipReader(const MipPyramid<T>& P, int64_t chans, int64_t src_chan, const Layout& L,
              int32_t last) {
#ifdef __SSE4_1__
        if constexpr (std::is_same_v<T, uint8_t>) {
            if (chans == 3 || chans == 4) {
                vector = int(chans);
                planes = !(src_chan == 1 && L.texel == chans);
                vector = planes && L.texel != 1 ? 0 : vector;
                for (int32_t m = 0; m <= last; ++m) {
                    const MipLevel<T>& M = P.levels[m];
                    safe[m] = (M.height - 1) * M.row + (M.width - 1) * M.texel + chans - 4;
                }
            }
        }
#endif
    }
};

// The pixels of the row segment [lo, lo + m) of row i of one sample's output o_b (w wide)
// that minify (level >= 0; their taps' positions X, Y: mip_footprints') filtered through the
// pyramid into o_b; the others are not written.
template <typename T, typename O, typename G>
void mip_filter(const MipPyramid<T>& P, const MipReader<T>& reader, const int32_t* level,
                const G* X, const G* Y, int64_t i, int64_t lo, int64_t m, int64_t w,
                const Planes& S, O* o_b) {
    using V = W<T>;
    const int64_t chans = S.chans;
    std::vector<V> acc;   // the sums of a number of channels other than 1, 3 and 4
    if (chans != 1 && chans != 3 && chans != 4) {
        acc.resize(chans);
    }
    for (int64_t p = 0; p < m; ++p) {
        if (level[p] < 0) {
            continue;
        }
        const MipLevel<T>& M = P.levels[level[p]];
        O* o = o_b + (i * w + lo + p) * S.out_pix;
        const V weight = V(1) / V(kMipTaps);
#ifdef __SSE4_1__
        if constexpr (std::is_same_v<T, uint8_t>) {
            if (reader.vector != 0) {
                const int64_t sm = reader.safe[level[p]];
                const bool plane = reader.planes && level[p] == 0;
                const int vector = reader.vector;
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
        // the sums of N channels known at compile time in a local array (registers: through
        // the heap vector each tap's sums went to memory and back, 1.1-1.4x the time), any
        // other number in `acc`
        const auto taps = [&](auto n_) {
            constexpr int N = decltype(n_)::value;
            V local[N > 0 ? N : 1] = {};
            V* sums = N > 0 ? local : acc.data();
            if (N == 0) {
                std::fill(acc.begin(), acc.end(), V(0));
            }
            for (int t = 0; t < kMipTaps; ++t) {
                mip_tap<N>(M, chans, V(X[t * kSegment + p]), V(Y[t * kSegment + p]), weight,
                           sums);
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
}

// The row segment [lo, lo + m) of row i of one sample's output o_b: its footprints
// (mip_footprints, levels clamped to `last`), and the pixels that minify filtered through the
// pyramid (built to `last`) into o_b (mip_filter); the others are not written.
template <typename T, typename O, typename G>
void mip_segment(const MipPyramid<T>& P, const MipReader<T>& reader, const G* us, const G* vs,
                 const uint8_t* ok, int64_t i, int64_t lo, int64_t m, int64_t h, int64_t w,
                 G limit, int32_t last, const Planes& S, O* o_b) {
    int32_t level[kSegment];
    G X[kMipTaps * kSegment], Y[kMipTaps * kSegment];
    mip_footprints<G>(us, vs, ok, i, lo, m, h, w, limit, last, level, X, Y);
    mip_filter<T, O, G>(P, reader, level, X, Y, i, lo, m, w, S, o_b);
}

// Image positions and validity of an h x w output, padded by one element at both ends (index
// -1 and h w are readable, ok 0 there), as mip_footprints reads them.
template <typename G>
struct MipPositions {
    std::unique_ptr<G[]> u_mem, v_mem;
    std::unique_ptr<uint8_t[]> ok_mem;
    G *us, *vs;
    uint8_t* ok;

    explicit MipPositions(int64_t pixels)
        : u_mem(new G[pixels + 2]), v_mem(new G[pixels + 2]), ok_mem(new uint8_t[pixels + 2]) {
        us = u_mem.get() + 1;
        vs = v_mem.get() + 1;
        ok = ok_mem.get() + 1;
        us[-1] = us[pixels] = vs[-1] = vs[pixels] = G(0);
        ok[-1] = ok[pixels] = 0;
    }
};

// sample_image's pixels of images (B, C, H, W) along rays whose footprint minifies the image,
// filtered (mip_footprints) through a mip pyramid built here, only the levels they read, per
// sample (once for an image shared by the batch); out's other pixels are left as they are.
template <typename T, typename O, typename G>
void mip_image(const T* src, int64_t src_batch, int64_t src_chan, const G* rays,
               int64_t rays_batch, const G* rot, int64_t rot_batch, const G* k, int64_t k_batch,
               const uint8_t* valid, int64_t height, int64_t width, const Layout& L, G limit,
               Planes S, O* out) {
    const int64_t h = S.pixels / S.width, w = S.width;
    const int64_t segments = (w + kSegment - 1) / kSegment;
    MipPositions<G> at(S.pixels);
    std::vector<int32_t> peaks;
    const int32_t depth = mip_depth(height, width);
    const bool whole = height * width <= 4 * S.pixels;
    MipPyramid<T> pyramid;
    for (int64_t b = 0; b < S.batch; ++b) {
        const G* ray = rays + b * rays_batch;
        const G* r = rot == nullptr ? nullptr : rot + b * rot_batch;
        const G* kb = k + b * k_batch;
        std::memcpy(at.ok, valid + b * S.pixels, S.pixels);
        const G fx = kb[0], fy = kb[1], cx = kb[2], cy = kb[3];
        // the pixels' image positions, as locate_pinhole computes them
        const auto first = [&](auto rotate_) {
            constexpr bool R = decltype(rotate_)::value;
            parallel_units(h, w, [&](int64_t i) {
                for (int64_t p = i * w; p < (i + 1) * w; ++p) {
                    G px, py, pz;
                    rotate<G, R>(r, ray[3 * p], ray[3 * p + 1], ray[3 * p + 2], px, py, pz);
                    const G z = pz > G(0) ? pz : G(1);
                    at.us[p] = fx * (px / z) + cx;
                    at.vs[p] = fy * (py / z) + cy;
                }
            });
        };
        r != nullptr ? first(std::true_type{}) : first(std::false_type{});
        const int32_t last = mip_peaks<G>(at.us, at.vs, at.ok, h, w, limit, depth, whole, peaks);
        if (last < 0) {
            continue;   // nothing minifies
        }
        pyramid.reach(src + b * src_batch, height, width, L, src_chan, S.chans, last);
        const MipReader<T> reader(pyramid, S.chans, src_chan, L, last);
        O* o_b = out + b * S.out_batch;
        parallel_units(h * segments, std::min(kSegment, w), [&](int64_t index) {
            const int64_t i = index / segments, lo = (index % segments) * kSegment;
            if (peaks[index] >= 0) {
                mip_segment<T, O, G>(pyramid, reader, at.us, at.vs, at.ok, i, lo,
                                     std::min(kSegment, w - lo), h, w, limit, last, S, o_b);
            }
        });
    }
}

}  // namespace
