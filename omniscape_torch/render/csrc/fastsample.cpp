// The fast sampler's per-pixel loops (omniscape_torch/fastsample.py), compiled on first use by
// omniscape_torch/native.py. Plain C++ with OpenMP, no PyTorch headers: tensors come in as
// pointers, sizes and strides (in elements).
//
// The image is grid_sample(cubemap_to_atlas(cube, pad, border), grid, align_corners=False,
// padding_mode="zeros") without the atlas: a grid point becomes atlas pixels as grid_sample's
// CPU kernel computes them, x = fma(g + 1, size / 2, -0.5) (evaluated in double for a float
// grid and rounded once, which is exact); a tap on an interior texel of a face reads the cube,
// a tap on the border ("ring") texel t reads sum_m weight[t, m] * cube[src[t, m]] (the border
// plan of cubemap_to_atlas), a tap outside the atlas reads 0. Taps, codes and weights are those
// of fastsample._lut_math, _blend_math and _edge_math; built with -ffp-contract=off, so every
// sum is evaluated in the order written there.
//
// Per pixel, its "code" is the offset of the top-left tap (nearest: the texel) within one
// sample and channel of the cube when every tap is an interior texel of one face (99% of the
// pixels), -1 when every tap lies outside the atlas or the pixel is not valid (it reads `fill`:
// 0, or the ignore index of labels), -2 for an edge pixel, whose taps are read one by one
// through the border.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>

namespace {

constexpr int32_t kOutside = -1;
constexpr int32_t kEdge = -2;
constexpr int64_t kTileW = 64, kTileH = 16;  // pixels per unit of work of the samplers
constexpr int64_t kChunk = 4096;  // grid points per unit of work of the table

// The padded cube: faces of `face` texels with a border of `pad`, `n = face + 2 pad` per
// padded side; `face_stride` elements between faces of one channel in the cube.
struct Layout {
    int64_t face, pad, n, face_stride;
    double half_x, half_y;  // n / 2 and 6 n / 2: the unnormalisation of grid_sample
};

Layout layout(int64_t face, int64_t pad, int64_t face_stride) {
    const int64_t n = face + 2 * pad;
    return Layout{face, pad, n, face_stride, 0.5 * n, 3.0 * n};
}

// The border texels (row-major over the padded faces, interior skipped): texel t reads the
// cube (one sample and channel) at src[t k .. t k + k) with weight[...], or at src[t k] alone
// when weight is null (a copy: exact for any dtype).
template <typename T>
struct Ring {
    const int64_t* src;
    const T* weight;
    int64_t k;
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

template <typename G>
struct Packed {
    Entry<G>* e;
    int64_t code(int64_t p) const { return e[p].code; }
    G fx(int64_t p) const { return e[p].fx; }
    G fy(int64_t p) const { return e[p].fy; }
    void set(int64_t p, int32_t code, G fx, G fy) const { e[p] = Entry<G>{code, fx, fy}; }
    void set_code(int64_t p, int32_t code) const { e[p].code = code; }
    Packed operator+(int64_t d) const { return Packed{e + d}; }
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
};

// The three arrays of a segment of pixels, on the stack.
template <typename G>
struct SplitBuffer {
    int32_t code[kTileW];
    G fx[kTileW], fy[kTileW];
    Split<G> taps() { return Split<G>{code, fx, fy}; }
};

// The samples and channels of the cube and of the output image.
struct Planes {
    int64_t batch, chans, pixels, width;
    int64_t src_batch, src_chan;  // strides of the cube
    int64_t out_batch, out_chan;  // strides of the output (its pixels are contiguous)
};

inline float unnormalize(float g, double half) {
    return static_cast<float>(static_cast<double>(g + 1.0f) * half - 0.5);
}

inline double unnormalize(double g, double half) {
    return (g + 1.0) * half - 0.5;
}

// Codes and bilinear fractions of `count` grid points; `valid` (bool, may be null) false ->
// outside. Branch-free int32 arithmetic (`&` for `&&`) that the compiler vectorises; the
// offsets fit in int32 (fastsample._check_offsets).
template <typename G, bool Bilinear, typename Taps>
void locate(const G* __restrict grid, int64_t count, const uint8_t* __restrict valid,
            const Layout& L, Taps out) {
    const int32_t n = static_cast<int32_t>(L.n), f = static_cast<int32_t>(L.face);
    const int32_t pad = static_cast<int32_t>(L.pad), stride = static_cast<int32_t>(L.face_stride);
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
        out.set(p, interior ? k * stride + (i - pad) * f + (j - pad)
                            : (touches ? kEdge : kOutside),
                x - x0, y - y0);
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
template <typename T>
inline T blend(T nw, T ne, T sw, T se, T fx, T fy) {
    const T e = 1 - fx, s = 1 - fy;
    T acc = nw * (s * e);
    acc = acc + ne * (s * fx);
    acc = acc + sw * (fy * e);
    acc = acc + se * (fy * fx);
    return acc;
}

// Where texel (column j, row r) of the virtual atlas of one sample and channel is read: `at`
// in the cube (kCube), ring texel `at` (kRing: fastsample._ring_position), or nowhere (kZero:
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
        return Tap{k * L.face_stride + (i - p) * f + (j - p), kCube};
    }
    // index among the ring texels (fastsample._ring_position)
    const int64_t pos = i < p       ? i * n + j
                        : i < p + f ? p * n + (i - p) * 2 * p + (j < p ? j : j - f)
                                    : p * n + f * 2 * p + (i - p - f) * n + j;
    return Tap{k * (n * n - f * f) + pos, kRing};
}

template <typename T>
inline T read(const T* cube, const Ring<T>& R, const Tap& t) {
    if (t.kind != kRing) {
        return t.kind == kCube ? cube[t.at] : T(0);
    }
    const int64_t* src = R.src + t.at * R.k;
    if (R.weight == nullptr) {
        return cube[src[0]];
    }
    // summed in the plan's order up to the row's first zero weight: the rows list their
    // nonzero weights first (fastsample._ring_offsets), then zeros, which would add nothing
    const T* w = R.weight + t.at * R.k;
    T acc = cube[src[0]] * w[0];
    for (int64_t m = 1; m < R.k && w[m] != T(0); ++m) {
        acc = acc + cube[src[m]] * w[m];
    }
    return acc;
}

// An edge pixel at grid point (gx, gy) of one sample: its taps located once, then read through
// the virtual atlas for every channel into out[c out_chan]. Not inlined: rare, and inlined into
// sample_span it slowed the whole pass by 10% (1M pixels, 0.2% of them edge pixels).
template <typename T, typename G>
__attribute__((noinline)) void edge_pixel(const T* cube, const Ring<T>& R, G gx, G gy,
                                          const Layout& L, bool bilinear, const Planes& S,
                                          T* out) {
    const G x = unnormalize(gx, L.half_x), y = unnormalize(gy, L.half_y);
    if (!bilinear) {
        const Tap t = atlas_tap(static_cast<int64_t>(std::nearbyint(x)),
                                static_cast<int64_t>(std::nearbyint(y)), L);
        for (int64_t c = 0; c < S.chans; ++c) {
            out[c * S.out_chan] = read(cube + c * S.src_chan, R, t);
        }
        return;
    }
    if constexpr (std::is_floating_point_v<T>) {   // integer cubes are sampled nearest
        const G x0 = std::floor(x), y0 = std::floor(y);
        const int64_t j = static_cast<int64_t>(x0), r = static_cast<int64_t>(y0);
        const Tap nw = atlas_tap(j, r, L), ne = atlas_tap(j + 1, r, L);
        const Tap sw = atlas_tap(j, r + 1, L), se = atlas_tap(j + 1, r + 1, L);
        for (int64_t c = 0; c < S.chans; ++c) {
            const T* q = cube + c * S.src_chan;
            out[c * S.out_chan] = blend<T>(read(q, R, nw), read(q, R, ne), read(q, R, sw),
                                           read(q, R, se), T(x - x0), T(y - y0));
        }
    }
}

// N channels of pixels [0, m) as if every pixel were interior (the outside ones read `fill`):
// per pixel the tap offset and weights once, then the N channels' taps. Scalar: gathers
// vectorised by the compiler were slower (AVX-512 on AMD EPYC: 36 -> 47 ms for 8 x 1M pixels),
// so was a channel at a time (36 against 30 ms).
template <typename T, typename G, int N, typename Taps>
__attribute__((optimize("no-tree-vectorize")))
void interior(const T* __restrict cube, int64_t src_chan, Taps t, int64_t m, int64_t f,
              bool bilinear, T fill, T* __restrict out, int64_t out_chan) {
    if (std::is_floating_point_v<T> && bilinear) {
        for (int64_t p = 0; p < m; ++p) {
            const int64_t k = std::max<int64_t>(t.code(p), 0);
            const bool inside = t.code(p) >= 0;
            const T x = T(t.fx(p)), y = T(t.fy(p)), e = 1 - x, s = 1 - y;
            const T w0 = s * e, w1 = s * x, w2 = y * e, w3 = y * x;  // blend()'s order
            for (int n = 0; n < N; ++n) {
                const T* q = cube + n * src_chan + k;
                T acc = q[0] * w0;
                acc = acc + q[1] * w1;
                acc = acc + q[f] * w2;
                acc = acc + q[f + 1] * w3;
                out[n * out_chan + p] = inside ? acc : fill;
            }
        }
    } else {
        for (int64_t p = 0; p < m; ++p) {
            const int64_t k = std::max<int64_t>(t.code(p), 0);
            const bool inside = t.code(p) >= 0;
            for (int n = 0; n < N; ++n) {
                const T v = cube[n * src_chan + k];
                out[n * out_chan + p] = inside ? v : fill;
            }
        }
    }
}

// Output pixels [lo, lo + m) of sample b: the entries `t` and `grid` (the pixels' grid
// points, for the edge pixels) start at the first of them; the pixels outside read `fill`.
// Up to 4 channels per pass over the pixels (interior), then the edge pixels again.
template <typename T, typename G, typename Taps>
void sample_span(const T* cube, const Ring<T>& R, Taps t, const G* grid, int64_t m,
                 const Layout& L, bool bilinear, T fill, const Planes& S, T* out) {
    for (int64_t c = 0; c < S.chans; c += 4) {
        const T* q = cube + c * S.src_chan;
        T* o = out + c * S.out_chan;
        switch (std::min<int64_t>(S.chans - c, 4)) {
            case 1:
                interior<T, G, 1, Taps>(q, S.src_chan, t, m, L.face, bilinear, fill, o,
                                        S.out_chan);
                break;
            case 2:
                interior<T, G, 2, Taps>(q, S.src_chan, t, m, L.face, bilinear, fill, o,
                                        S.out_chan);
                break;
            case 3:
                interior<T, G, 3, Taps>(q, S.src_chan, t, m, L.face, bilinear, fill, o,
                                        S.out_chan);
                break;
            default:
                interior<T, G, 4, Taps>(q, S.src_chan, t, m, L.face, bilinear, fill, o,
                                        S.out_chan);
        }
    }
    for (int64_t p = 0; p < m; ++p) {
        if (t.code(p) == kEdge) {
            edge_pixel<T, G>(cube, R, grid[2 * p], grid[2 * p + 1], L, bilinear, S, out + p);
        }
    }
}

// fn(b, lo, m) for the row segments [lo, lo + m) of every tile of kTileW x kTileH pixels of
// every sample, the tiles spread over the threads. A tile, not a row: the taps of a rotated
// camera's row can run down a face's columns, a new cache line each; those of a tile stay in a
// small patch of the cube.
template <typename Fn>
void for_tiles(const Planes& S, int threads, Fn fn) {
    const int64_t height = S.pixels / S.width;
    const int64_t nx = (S.width + kTileW - 1) / kTileW, ny = (height + kTileH - 1) / kTileH;
#pragma omp parallel for collapse(2) num_threads(threads) schedule(static)
    for (int64_t b = 0; b < S.batch; ++b) {
        for (int64_t t = 0; t < nx * ny; ++t) {
            const int64_t x0 = (t % nx) * kTileW, y0 = (t / nx) * kTileH;
            const int64_t m = std::min(kTileW, S.width - x0);
            for (int64_t y = y0; y < std::min(y0 + kTileH, height); ++y) {
                fn(b, y * S.width + x0, m);
            }
        }
    }
}

// Sampling through a lookup table (the entries of a grid; fractions unused for nearest),
// shared by the batch (lut_batch = 0) or one per sample (lut_batch = P).
template <typename T, typename G>
void sample_lut(const T* src, const Entry<G>* table, const G* grid, int64_t lut_batch,
                const Ring<T>& R, const Layout& L, bool bilinear, T fill, Planes S, T* out,
                int threads) {
    for_tiles(S, threads, [&](int64_t b, int64_t lo, int64_t m) {
        const int64_t at = b * lut_batch + lo;
        const Packed<G> taps{const_cast<Entry<G>*>(table) + at};   // read only
        sample_span<T, G>(src + b * S.src_batch, R, taps, grid + 2 * at, m, L, bilinear, fill,
                          S, out + b * S.out_batch + lo);
    });
}

// Output pixels [lo, lo + m) of one sample at grid points `g` (their `valid`, may be null):
// their taps computed into the stack, then sampled.
template <typename T, typename G>
void sample_points(const T* cube, const G* g, const uint8_t* valid, int64_t m, const Ring<T>& R,
                   const Layout& L, bool bilinear, T fill, const Planes& S, T* out) {
    SplitBuffer<G> buffer;
    locate<G>(g, m, valid, L, bilinear, buffer.taps());
    sample_span<T, G>(cube, R, buffer.taps(), g, m, L, bilinear, fill, S, out);
}

// A grid used once (grid_batch = 0: one grid for the batch, else 2 P): the codes computed in
// the sampling pass, a segment at a time. Pixels where `valid` (bool, valid_batch = 0 or P;
// null: all valid) is false read `fill`, as if outside the atlas.
template <typename T, typename G>
void sample_grid(const T* src, const G* grid, int64_t grid_batch, const uint8_t* valid,
                 int64_t valid_batch, const Ring<T>& R, const Layout& L, bool bilinear, T fill,
                 Planes S, T* out, int threads) {
    for_tiles(S, threads, [&](int64_t b, int64_t lo, int64_t m) {
        sample_points<T, G>(src + b * S.src_batch, grid + b * grid_batch + 2 * lo,
                            valid == nullptr ? nullptr : valid + b * valid_batch + lo, m, R, L,
                            bilinear, fill, S, out + b * S.out_batch + lo);
    });
}

// The faces of the cube as omniscape_torch.fastgrid._CASES (from cubemap.faces): per case
// 2 axis + (dominant component < 0), the face, then r and b as (axis, sign). fastsample checks
// this copy against cubemap.faces before the first use (os_face_cases).
constexpr int32_t kCases[6][5] = {{3, 2, -1, 1, 1}, {2, 2, 1, 1, 1}, {5, 0, 1, 2, -1},
                                  {4, 0, 1, 2, 1},  {0, 0, 1, 1, 1}, {1, 0, -1, 1, 1}};
constexpr int32_t kZeroCase[5] = {0, 0, 1, 1, 1};

template <int K, int Col>
constexpr int32_t case_entry() {
    return K < 6 ? kCases[K][Col] : kZeroCase[Col];
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

// fastgrid._grid_xy's pick: the value of case 2 axis + neg, or of the zero case.
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

// The atlas grid of `count` rays (x, y, z at rays[3 p ..]) rotated by `rot` (row-major 3 x 3,
// null: none), into grid[2 p], grid[2 p + 1]: fastgrid._rotated_grid_xy and _grid_xy, the same
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
        G px = x, py = y, pz = z;
        if (Rotate) {
            px = r[0] * x + r[1] * y;
            px = px + r[2] * z;
            py = r[3] * x + r[4] * y;
            py = py + r[5] * z;
            pz = r[6] * x + r[7] * y;
            pz = pz + r[8] * z;
        }
        const G ax = std::fabs(px), ay = std::fabs(py), az = std::fabs(pz);
        const bool use_x = (ax >= ay) & (ax >= az);
        const bool use_y = !use_x & (ay >= az);
        const G comp = use_x ? px : (use_y ? py : pz);
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

// sample_grid of the grid of rays (rays_batch = 0: one set for the batch, else 3 P) rotated
// per sample (rot_batch = 0 or 9; rot null: not rotated), computed a segment at a time into
// the stack and sampled at once: the grid never goes to memory.
template <typename T, typename G>
void sample_rays(const T* src, const G* rays, int64_t rays_batch, const G* rot,
                 int64_t rot_batch, const uint8_t* valid, int64_t valid_batch, const Ring<T>& R,
                 const Layout& L, bool bilinear, T fill, Planes S, T* out, int threads) {
    for_tiles(S, threads, [&](int64_t b, int64_t lo, int64_t m) {
        G g[2 * kTileW];
        ray_grid<G>(rays + b * rays_batch + 3 * lo, rot == nullptr ? nullptr : rot + b * rot_batch,
                    m, L, g);
        sample_points<T, G>(src + b * S.src_batch, g,
                            valid == nullptr ? nullptr : valid + b * valid_batch + lo, m, R, L,
                            bilinear, fill, S, out + b * S.out_batch + lo);
    });
}

}  // namespace

// ------------------------------------------------------------------------------------------
// The C entry points (ctypes): per cube dtype (f32, f64; or the element size 1, 2, 4, 8 bytes
// of a cube sampled nearest, whose elements are copied: any dtype, exact) and grid dtype.
// `fill`: the value of the pixels outside (an integer: the ignore index of labels), given as
// int64 and converted to the element type (two's complement for unsigned elements).
// ------------------------------------------------------------------------------------------

#define PLANE_ARGS int64_t batch, int64_t chans, int64_t pixels, int64_t width, \
    int64_t src_batch, int64_t src_chan, int64_t out_batch, int64_t out_chan
#define PLANES Planes{batch, chans, pixels, width, src_batch, src_chan, out_batch, out_chan}
#define RING_ARGS(T) const int64_t *ring_src, const T *ring_weight, int64_t ring_k
#define RING(T) Ring<T>{ring_src, ring_weight, ring_k}

extern "C" {

#define LUT(NAME, G)                                                                          \
    void NAME(const G* grid, int64_t count, int64_t face, int64_t pad, int64_t face_stride,  \
              int bilinear, Entry<G>* table, int threads) {                                  \
        const Layout L = layout(face, pad, face_stride);                                      \
        const int64_t tiles = (count + kChunk - 1) / kChunk;                                  \
        _Pragma("omp parallel for num_threads(threads) schedule(static)")                     \
        for (int64_t tile = 0; tile < tiles; ++tile) {                                        \
            const int64_t lo = tile * kChunk, m = std::min(kChunk, count - lo);               \
            locate<G>(grid + 2 * lo, m, nullptr, L, bilinear != 0, Packed<G>{table} + lo);    \
        }                                                                                     \
    }
LUT(os_lut_f32, float)
LUT(os_lut_f64, double)

#define SAMPLE(SUFFIX, T, G)                                                                  \
    void os_sample_lut_##SUFFIX(const T* src, const Entry<G>* table, const G* grid,           \
                                int64_t lut_batch, RING_ARGS(T), int64_t face, int64_t pad,   \
                                int64_t face_stride, int bilinear, int64_t fill, PLANE_ARGS,  \
                                T* out, int threads) {                                        \
        sample_lut<T, G>(src, table, grid, lut_batch, RING(T),                                \
                         layout(face, pad, face_stride), bilinear != 0, T(fill), PLANES, out, \
                         threads);                                                            \
    }                                                                                         \
    void os_sample_grid_##SUFFIX(const T* src, const G* grid, int64_t grid_batch,             \
                                 const uint8_t* valid, int64_t valid_batch, RING_ARGS(T),     \
                                 int64_t face, int64_t pad, int64_t face_stride,              \
                                 int bilinear, int64_t fill, PLANE_ARGS, T* out,              \
                                 int threads) {                                               \
        sample_grid<T, G>(src, grid, grid_batch, valid, valid_batch, RING(T),                 \
                          layout(face, pad, face_stride), bilinear != 0, T(fill), PLANES,     \
                          out, threads);                                                      \
    }                                                                                         \
    void os_sample_rays_##SUFFIX(const T* src, const G* rays, int64_t rays_batch,             \
                                 const G* rot, int64_t rot_batch, const uint8_t* valid,       \
                                 int64_t valid_batch, RING_ARGS(T), int64_t face,             \
                                 int64_t pad, int64_t face_stride, int bilinear,              \
                                 int64_t fill, PLANE_ARGS, T* out, int threads) {             \
        sample_rays<T, G>(src, rays, rays_batch, rot, rot_batch, valid, valid_batch, RING(T), \
                          layout(face, pad, face_stride), bilinear != 0, T(fill), PLANES,     \
                          out, threads);                                                      \
    }
SAMPLE(f32, float, float)
SAMPLE(f64, double, double)
SAMPLE(1_f32, uint8_t, float)
SAMPLE(2_f32, uint16_t, float)
SAMPLE(4_f32, uint32_t, float)
SAMPLE(8_f32, uint64_t, float)
SAMPLE(1_f64, uint8_t, double)
SAMPLE(2_f64, uint16_t, double)
SAMPLE(4_f64, uint32_t, double)
SAMPLE(8_f64, uint64_t, double)

void os_face_cases(int32_t* out) {
    std::copy(&kCases[0][0], &kCases[0][0] + 30, out);
    std::copy(kZeroCase, kZeroCase + 5, out + 30);
}

}  // extern "C"
