#pragma once

// The sampling pass: output pixels of a segment read through their taps (sample_span), the
// units of work on PyTorch's threads, and the cube sampled through a lookup table
// (sample_lut) or a grid (sample_grid). Part of the fast sampler's kernels (sample_base.h).

#include "sample_simd.h"

namespace {

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

}  // namespace
