#pragma once

// RandomReproject's fast path, one pass per sample (the op reproject_image): the rays of
// radially symmetric cameras (camera_grid.h's radial_rays), their positions in a pinhole image
// (sample_image.h's locate_pinhole), the image sampled where a pixel does not minify and
// filtered where it does (sample_mip.h), and labels sampled nearest. Part of the fast sampler's
// kernels (sample_base.h).

#include "camera_grid.h"
#include "sample_mip.h"

namespace {

// ------------------------------------------------------------------------------------------
// Radial cameras into a pinhole image, sampled and antialiased in one pass
// ------------------------------------------------------------------------------------------

// The labels of reproject_pinhole: ids of TL (uint8 or int64), B x height x width (L, S.src_*),
// sampled nearest into `out` (int64; `fill` outside).
template <typename TL>
struct LabelImage {
    const TL* data;
    int64_t height, width;
    Layout L;
    Planes S;
    int64_t* out;
    int64_t fill;
};

// camera_rays, then sample_image of `src` along them (bilinear or nearest; validity into
// valid_out), then, where limit > 0 (the squared threshold), mip_image of the pixels that
// minify, then sample_image of the labels (nearest; if given): those ops' results in turn, bit
// for bit, with their arithmetic (the functions they run), in other order. A segment's rays
// live on the stack; each pixel's image position is computed once, and where the filter will
// overwrite a pixel its bilinear sample is not taken (the codes of the second pass read those
// pixels as outside, then the filter writes them). Per sample: the rays, positions, codes,
// point samples and labels (first pass; the positions kept where the image is filtered);
// the deepest level each segment reads (mip_peaks) and the pyramid to it; the footprints,
// point samples and filter (second pass).
template <typename T, typename O, typename G, typename TL>
void reproject_pinhole(const G* affine, const G* limits, const G* table, int64_t entries,
                       int64_t table_batch, const T* src, int64_t height, int64_t width,
                       const Layout& L, const G* rot, int64_t rot_batch, const G* k,
                       int64_t k_batch, bool bilinear, G limit, const Planes& S, O* out,
                       const LabelImage<TL>* labels, uint8_t* valid_out) {
    const int64_t h = S.pixels / S.width, w = S.width;
    const int64_t segments = (w + kSegment - 1) / kSegment;
    constexpr bool kMips =
        std::is_same_v<T, uint8_t> || std::is_same_v<T, float> || std::is_same_v<T, double>;
    const bool filter = kMips && limit > G(0);
    std::unique_ptr<MipPositions<G>> at(filter ? new MipPositions<G>(S.pixels) : nullptr);
    const int32_t depth = mip_depth(height, width);
    const bool whole = height * width <= 4 * S.pixels;
    MipPyramid<T> pyramid;
    std::vector<int32_t> peaks;
    const Ring<T> none{nullptr, nullptr, 1, 0};   // no border: the taps are clamped
    using Yes = std::true_type;
    using No = std::false_type;
    for (int64_t b = 0; b < S.batch; ++b) {
        const G* r = rot == nullptr ? nullptr : rot + b * rot_batch;
        const G* kb = k + b * k_batch;
        const RadialCamera<G> cam{affine + 6 * b, limits + 5 * b, table + table_batch * b,
                                  entries};
        const T* image = src + b * S.src_batch;
        uint8_t* seen = valid_out + b * S.pixels;
        O* o_b = out + b * S.out_batch;
        parallel_units(h * segments, std::min(kSegment, w), [&](int64_t index) {
            const int64_t x0 = (index % segments) * kSegment;
            const int64_t m = std::min(kSegment, w - x0), lo = (index / segments) * w + x0;
            G rays[3 * kSegment], xs_here[kSegment], ys_here[kSegment];
            uint8_t ok[kSegment];
            radial_rays<G>(cam, w, lo, m, rays, ok);
            SplitBuffer<G> buffer;
            G* xs = filter ? at->us + lo : xs_here;
            G* ys = filter ? at->vs + lo : ys_here;
            const auto locate = [&](auto bilinear_, auto rotate_) {
                locate_pinhole<G, decltype(bilinear_)::value, decltype(rotate_)::value>(
                    rays, r, kb, m, ok, height, width, L, buffer.taps(), xs, ys, seen + lo);
            };
            if (bilinear) {
                r != nullptr ? locate(Yes{}, Yes{}) : locate(Yes{}, No{});
            } else {
                r != nullptr ? locate(No{}, Yes{}) : locate(No{}, No{});
            }
            if (!filter) {
                sample_span<T, O, G>(image, none, buffer.taps(),
                                     ImagePoints<G>{xs, ys, height, width}, m, L, bilinear,
                                     O(0), S, o_b + lo * S.out_pix);
            }
            if (labels != nullptr) {
                const LabelImage<TL>& I = *labels;
                const Ring<TL> no_border{nullptr, nullptr, 1, 0};
                G lx[kSegment], ly[kSegment];
                uint8_t unused[kSegment];
                const auto nearest = [&](auto rotate_) {
                    locate_pinhole<G, false, decltype(rotate_)::value>(
                        rays, r, kb, m, ok, I.height, I.width, I.L, buffer.taps(), lx, ly,
                        unused);
                };
                r != nullptr ? nearest(Yes{}) : nearest(No{});
                sample_span<TL, int64_t, G>(I.data + b * I.S.src_batch, no_border,
                                            buffer.taps(),
                                            ImagePoints<G>{lx, ly, I.height, I.width}, m, I.L,
                                            false, I.fill, I.S,
                                            I.out + b * I.S.out_batch + lo * I.S.out_pix);
            }
        });
        if constexpr (kMips) {
            if (!filter) {
                continue;
            }
            std::memcpy(at->ok, seen, S.pixels);
            const G* us = at->us;
            const G* vs = at->vs;
            const uint8_t* valid = at->ok;
            const int32_t last = mip_peaks<G>(us, vs, valid, h, w, limit, depth, whole, peaks);
            if (last >= 0) {
                pyramid.reach(image, height, width, L, S.src_chan, S.chans, last);
            }
            const MipReader<T> reader(pyramid, S.chans, S.src_chan, L, last);
            parallel_units(h * segments, std::min(kSegment, w), [&](int64_t index) {
                const int64_t i = index / segments, x0 = (index % segments) * kSegment;
                const int64_t m = std::min(kSegment, w - x0), lo = i * w + x0;
                int32_t level[kSegment];
                G X[kMipTaps * kSegment], Y[kMipTaps * kSegment];
                uint8_t keep[kSegment];   // the pixels that are point-sampled
                const bool minifies = peaks[index] >= 0;
                if (minifies) {
                    mip_footprints<G>(us, vs, valid, i, x0, m, h, w, limit, last, level, X, Y);
                    for (int64_t p = 0; p < m; ++p) {
                        keep[p] = valid[lo + p] & (level[p] < 0);
                    }
                } else {
                    std::memcpy(keep, valid + lo, m);
                }
                SplitBuffer<G> buffer;
                if (bilinear) {
                    locate_positions<G, true>(us + lo, vs + lo, keep, m, height, width, L,
                                              buffer.taps());
                } else {
                    locate_positions<G, false>(us + lo, vs + lo, keep, m, height, width, L,
                                               buffer.taps());
                }
                sample_span<T, O, G>(image, none, buffer.taps(),
                                     ImagePoints<G>{us + lo, vs + lo, height, width}, m, L,
                                     bilinear, O(0), S, o_b + lo * S.out_pix);
                if (minifies) {
                    mip_filter<T, O, G>(pyramid, reader, level, X, Y, i, x0, m, w, S, o_b);
                }
            });
        }
    }
}

}  // namespace
