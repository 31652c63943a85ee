#pragma once

// Rays to the atlas: the face table, a ray's rotation and cube face, the atlas grid of rays
// (ray_grid) and the cube sampled along rays without a stored grid (sample_rays). Part of
// the fast sampler's kernels (sample_base.h).

#include "sample_cube.h"

// The face table, per case 2 axis + (dominant component < 0) and then the zero ray: the face,
// then r and b as (axis, sign). Generated from cubemap/faces.py (the only face table) by
// extension.py, which passes it as -DOS_FACE_CASES=..., so a new table is a new build.
#ifndef OS_FACE_CASES
#error "OS_FACE_CASES is undefined: build this file through omniscape_torch/render/kernels/build.py"
#endif

namespace {

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

// A row-major 3 x 3 rotation copied onto the stack (its entries in registers in the loops
// over rays, apart from the arrays they read and write), none without Rotate.
template <typename G, bool Rotate>
struct LocalRotation {
    G r[9];
    explicit LocalRotation(const G* rot) {
        if (Rotate) {
            std::copy(rot, rot + 9, r);
        }
    }
};

// Ray p of rays (x, y, z at rays[3 p ..]) rotated (rotate) and the axis of its cube face
// (major_axis): how ray_grid and locate_rays start on each ray.
template <typename G, bool Rotate>
__attribute__((always_inline)) inline void rotated_ray(const G* __restrict rays, int64_t p,
                                                       const LocalRotation<G, Rotate>& R, G& px,
                                                       G& py, G& pz, bool& use_x, bool& use_y,
                                                       G& comp) {
    rotate<G, Rotate>(R.r, rays[3 * p], rays[3 * p + 1], rays[3 * p + 2], px, py, pz);
    major_axis(px, py, pz, use_x, use_y, comp);
}

// The atlas grid of `count` rays (x, y, z at rays[3 p ..]) rotated by `rot` (row-major 3 x 3,
// null: none), into grid[2 p], grid[2 p + 1]: cubemap.grid.rotated_grid_xy and grid_xy, the same
// operations in the same order (so the grid is inductor's, bit for bit).
template <typename G, bool Rotate>
void ray_grid(const G* __restrict rays, const G* __restrict rot, int64_t count,
              const Layout& L, G* __restrict grid) {
    const G f = G(L.face) / G(2), c = G(L.face - 1) / G(2), n = G(L.n), pad = G(L.pad);
    const G n6 = G(6 * L.n);
    const LocalRotation<G, Rotate> R(rot);
    for (int64_t p = 0; p < count; ++p) {
        G px, py, pz, comp;
        bool use_x, use_y;
        rotated_ray<G, Rotate>(rays, p, R, px, py, pz, use_x, use_y, comp);
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
    const LocalRotation<G, Rotate> R(rot);
    for (int64_t p = 0; p < count; ++p) {
        G px, py, pz, comp;
        bool use_x, use_y;
        rotated_ray<G, Rotate>(rays, p, R, px, py, pz, use_x, use_y, comp);
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

}  // namespace
