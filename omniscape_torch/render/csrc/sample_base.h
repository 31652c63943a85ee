#pragma once

// The fast sampler's per-pixel loops (omniscape_torch/render/kernels/cube.py) and the camera grid of
// render/kernels.py as PyTorch custom ops, torch.ops.omniscape_torch.{build_lut, sample_lut,
// sample_grid, sample_rays, camera_grid}, built on first use by
// omniscape_torch/render/kernels/build.py (torch.utils.cpp_extension). The ops take tensors and
// read their sizes and strides; the loops take pointers, sizes and strides (in elements).
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
//
// The kernels, one header an idea, each including those it builds on (in this order):
// sample_base.h (this one: the codes, the units of work, the elements), sample_taps.h (the
// padded cube, where a pixel's taps lie and their scalar blend), sample_simd.h (the x86
// vector blends), sample_cube.h (the sampling pass, its threads, the samplers through a
// table or a grid), sample_rays.h (rays to the atlas: the face table, sample_rays),
// sample_image.h (perspective images), sample_mip.h (their antialiasing), camera_grid.h
// (radial cameras straight to the atlas grid), sample_reproject.h (radial cameras into a
// pinhole image in one pass: reproject_image) and op_checks.h (the ops' checks and dispatch). The ops are in fastsample.cpp (the cube's) and fastimage.cpp (the image's).

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

}  // namespace
