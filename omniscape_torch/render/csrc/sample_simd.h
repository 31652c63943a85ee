#pragma once

// The vector blends of interior() on x86 (SSE4.1, AVX2, F16C where the CPU has them): 8-bit
// channels-last texels and 8-bit or half-precision planes, the same values as interior's.
// Part of the fast sampler's kernels (sample_base.h).

#include "sample_taps.h"

namespace {

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

}  // namespace
