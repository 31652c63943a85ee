// Shading of the built-in town's ray hits: the loops of omniscape_torch/render/kernels/town.py's
// torch twins (_shade_torch, ...), one ray at a time, as PyTorch custom ops
// torch.ops.omniscape_torch.{town_backfaces, town_prepare, town_shade, town_store}, built with
// the fast sampler (fastsample.cpp) by omniscape_torch/render/kernels/build.py into one library.
// A call through torch.ops releases the GIL while the op runs (torch's invokeOperatorFromPython),
// so the town's worker threads shade in parallel; each call is one serial loop over its rays
// (the town splits the work into tasks itself).
//
// Exactness: float32 arithmetic in the reference's order of operations, built with
// -ffp-contract=off and without -ffast-math, so every operation rounds as torch's does and a
// ray's result does not depend on its batch (tests/test_scenes.py compares the two). The other
// flags of the build (-O3, -march=native, -fno-trapping-math, -fno-math-errno) change no result:
// without fast-math the compiler neither reassociates nor contracts, sqrtf is the correctly
// rounded instruction, and floor_ is exact.
//
// Layouts (checked by the ops before any read): rays o (n or 1, 3), d (n, 3), hits t, tri (-1:
// none, else < T), barycentric u, v (n,); the triangles' attributes attr (A_ROWS, T) row-major;
// triangle corners tris (T, 3) int32 (< V), vertex normals vn (V, 3); weather and constants w
// (W_COUNT,), kernels/town.py's WEATHER; lamps (L, 3). All contiguous CPU tensors. Shapes,
// dtypes and the hits' and texels' indices are checked before the loop; a triangle's corners
// and a ground triangle's class id (which index vn and the ground's colours) as they are met,
// before they are read, the op raising after the loop (its outputs then not to be used): a
// pass over every triangle would cost each call about as much as shading a few thousand rays.

#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>

namespace {

// the rows of attr and the entries of w: kernels/town.py's ATTRIBUTES and WEATHER, in order
enum { A_NX, A_NY, A_NZ, A_LABEL, A_KIND, A_R, A_G, A_B, A_PAINT, A_OFF, A_CX, A_CY, A_INDEX,
       A_SMOOTH, A_ROWS };
enum { W_SX, W_SY, W_SZ, W_SUN, W_AMB = W_SUN + 3, W_ZEN = W_AMB + 3, W_HOR = W_ZEN + 3,
       W_FOG = W_HOR + 3, W_FOG_C = W_FOG + 3, W_LAMPS, W_WINDOWS, W_PUDDLES, W_DARKEN,
       W_RAIN_SKY, W_HAZE, W_FAR, W_COUNT };
// class ids (CARLA) and part kinds
enum { BUILDING = 1, FENCE = 2, ROADLINE = 6, ROAD = 7, SIDEWALK = 8, WALL = 11, SIGN = 12 };
enum { GROUND = 0, BOX = 1 };

// the ground's colour per class (Road, RoadLine, Sidewalk, Other; the rest unused)
constexpr float GROUND_COLOUR[13][3] = {
    {0.0f, 0.0f, 0.0f},    {0.0f, 0.0f, 0.0f},   {0.0f, 0.0f, 0.0f},
    {0.42f, 0.38f, 0.28f}, {0.0f, 0.0f, 0.0f},   {0.0f, 0.0f, 0.0f},
    {0.85f, 0.85f, 0.8f},  {0.26f, 0.26f, 0.27f}, {0.62f, 0.60f, 0.56f},
    {0.0f, 0.0f, 0.0f},    {0.0f, 0.0f, 0.0f},   {0.0f, 0.0f, 0.0f},
    {0.0f, 0.0f, 0.0f}};
static_assert(ROAD == 7 && ROADLINE == 6 && SIDEWALK == 8, "GROUND_COLOUR's rows");

// floorf without a libm call: exact, as floorf, for every finite float (from 2^23 on every
// float is an integer)
inline float floor_(float x) {
    if (!(std::fabs(x) < 8388608.0f)) return x;
    const float i = static_cast<float>(static_cast<int32_t>(x));
    return i > x ? i - 1.0f : i;
}
inline float frac_(float x) { return x - floor_(x); }
inline int64_t cell(float x, float scale) { return static_cast<int64_t>(floor_(x * scale)); }
inline float clamp0(float x) { return x < 0.0f ? 0.0f : x; }

// town.py's _noise: a hash of a cell -> [0, 1) (int64 arithmetic wraps: done in uint64)
float noise(float x, float y, float z, float scale, int64_t salt) {
    uint64_t h = (static_cast<uint64_t>(cell(x, scale)) * 73856093u) ^
                 (static_cast<uint64_t>(cell(y, scale)) * 19349663u) ^
                 (static_cast<uint64_t>(cell(z, scale)) * 83492791u) ^
                 static_cast<uint64_t>(0x9E3779B9LL + salt * 0x632BE5ABLL);
    h = (h * 0x45D9F3Bu) & 0xFFFFFFFFu;
    h ^= h >> 16;
    h = (h * 0x45D9F3Bu) & 0xFFFFFFFFu;
    h ^= h >> 16;
    return static_cast<float>(h & 0xFFFF) * (1.0f / 65536.0f);
}

// town.py's _hash of three integers
float hash3(int64_t a, int64_t b, int64_t c, int64_t salt) {
    uint64_t h = static_cast<uint64_t>(0x9E3779B9LL + salt * 0x632BE5ABLL);
    const uint64_t k[3] = {73856093u, 19349663u, 83492791u};
    const int64_t v[3] = {a, b, c};
    for (int i = 0; i < 3; i++) {
        h = (h ^ (static_cast<uint64_t>(v[i]) * k[i])) & 0xFFFFFFFFu;
        h = (h * 0x45D9F3Bu) & 0xFFFFFFFFu;
        h ^= h >> 16;
    }
    return static_cast<float>(h & 0xFFFF) / 65536.0f;
}

// town.py's _smooth_noise: bilinear, smoothstep-weighted value noise over the ground
float smooth_noise(float x, float z, float scale, int64_t salt) {
    const float sx = x * scale, sz = z * scale;
    const float ixf = floor_(sx), izf = floor_(sz);
    const float fx = sx - ixf, fz = sz - izf;
    const float wx = (fx * fx) * (3.0f - 2.0f * fx), wz = (fz * fz) * (3.0f - 2.0f * fz);
    const int64_t ix = static_cast<int64_t>(ixf), iz = static_cast<int64_t>(izf);
    const float h00 = hash3(ix, 0, iz, salt), h10 = hash3(ix + 1, 0, iz, salt);
    const float h01 = hash3(ix, 0, iz + 1, salt), h11 = hash3(ix + 1, 0, iz + 1, salt);
    const float a = h00 + (h10 - h00) * wx;
    const float b = h01 + (h11 - h01) * wx;
    return a + (b - a) * wz;
}

// The rays and their hits, and the town's tables, as the loops read them.
struct Hits {
    int64_t n;
    const float* o;
    int64_t o_step;  // 3: one origin per ray, 0: one for all
    const float* d;
    const float* t;
    const int64_t* tri;
    const float* u;
    const float* v;
    const float* attr;
    int64_t T;
    const int32_t* tris;
    const float* vn;
    int64_t V;
    const float* w;
    // the first triangle met with a corner outside [0, V) (-1: none): its corners are not read
    int64_t* bad_corner;
};

struct Surface {
    bool hit;
    int64_t tri;
    float t, px, py, pz, nfx, nfy, nfz, nx, ny, nz;
};

// The hit point, the flat (face) normal and the shading normal of ray i.
Surface surface(const Hits& h, int64_t i) {
    Surface s;
    s.hit = h.tri[i] >= 0;
    s.tri = s.hit ? h.tri[i] : 0;
    s.t = s.hit ? h.t[i] : 0.0f;
    const float *oi = h.o + i * h.o_step, *di = h.d + 3 * i;
    const float* attr = h.attr;
    const int64_t T = h.T;
    s.px = oi[0] + s.t * di[0];
    s.py = oi[1] + s.t * di[1];
    s.pz = oi[2] + s.t * di[2];
    s.nfx = attr[A_NX * T + s.tri];
    s.nfy = attr[A_NY * T + s.tri];
    s.nfz = attr[A_NZ * T + s.tri];
    s.nx = s.nfx, s.ny = s.nfy, s.nz = s.nfz;
    if (s.hit && attr[A_SMOOTH * T + s.tri] > 0.0f) {
        const int32_t* c = h.tris + 3 * s.tri;
        if (!(c[0] >= 0 && c[0] < h.V && c[1] >= 0 && c[1] < h.V && c[2] >= 0 && c[2] < h.V)) {
            if (*h.bad_corner < 0) *h.bad_corner = s.tri;
            return s;
        }
        const float* vn = h.vn;
        const float us = h.u[i], vs = h.v[i], w0 = (1.0f - us) - vs;
        float n[3];
        for (int k = 0; k < 3; k++)
            n[k] = (w0 * vn[3 * c[0] + k] + us * vn[3 * c[1] + k]) + vs * vn[3 * c[2] + k];
        const float len = std::sqrt((n[0] * n[0] + n[1] * n[1]) + n[2] * n[2]);
        s.nx = n[0] / len, s.ny = n[1] / len, s.nz = n[2] / len;
    }
    return s;
}

float lambert(const Surface& s, const float* w) {
    return clamp0((s.nx * w[W_SX] + s.ny * w[W_SY]) + s.nz * w[W_SZ]);
}

// town.py's sky_of: the sky's colour in direction e
void sky(const float* w, float ex, float ey, float ez, float out[3]) {
    const float up = clamp0(-ey);
    float h = 1.0f - up;
    h = 1.0f - (h * h) * h;
    const float cs = clamp0((ex * w[W_SX] + ey * w[W_SY]) + ez * w[W_SZ]);
    float g8 = cs * cs;
    g8 = g8 * g8;
    g8 = g8 * g8;
    float g256 = g8;
    for (int k = 0; k < 5; k++) g256 = g256 * g256;
    const float glow = 0.15f * g8 + 0.8f * g256;
    const float hf = clamp0(1.0f - up * 8.0f) * w[W_HAZE];
    for (int k = 0; k < 3; k++) {
        float c = w[W_HOR + k] + (w[W_ZEN + k] - w[W_HOR + k]) * h;
        c = c + w[W_SUN + k] * glow;
        if (cs > 0.99995f) c = w[W_SUN + k] * 4.0f;
        c = c + (w[W_FOG + k] - c) * hf;
        out[k] = c * w[W_RAIN_SKY];
    }
}

// Which hits face away from their ray (out[i] = 1): the ray started inside a primitive.
void backfaces(int64_t n, const float* d, const int64_t* tri, const float* attr, int64_t T,
               uint8_t* out) {
    for (int64_t i = 0; i < n; i++) {
        const int64_t j = tri[i];
        const float* di = d + 3 * i;
        out[i] = j >= 0 && (attr[A_NX * T + j] * di[0] + attr[A_NY * T + j] * di[1]) +
                                   attr[A_NZ * T + j] * di[2] >
                               0.0f;
    }
}

// Which rays need a shadow ray (hit, lit by the shading normal, their face turned to the sun),
// its origin, and the initial shadow flag (hit and lit by the shading normal).
void prepare(const Hits& h, float bias0, float bias_per_m, uint8_t* need, float* origin,
             uint8_t* shadow) {
    const float* w = h.w;
    for (int64_t i = 0; i < h.n; i++) {
        const Surface s = surface(h, i);
        const float lam = lambert(s, w);
        shadow[i] = s.hit && lam > 0.0f;
        need[i] = shadow[i] && (s.nfx * w[W_SX] + s.nfy * w[W_SY]) + s.nfz * w[W_SZ] > 0.0f;
        const float bias = bias_per_m * s.t + bias0;
        origin[3 * i] = s.px + s.nfx * bias;
        origin[3 * i + 1] = s.py + s.nfy * bias;
        origin[3 * i + 2] = s.pz + s.nfz * bias;
    }
}

void shade(const Hits& h, const uint8_t* shadow, const float* lamps, int64_t n_lamps, float* rgb,
           float* range, int64_t* labels, float* normal, int64_t* bad_label) {
    const float* w = h.w;
    const float* attr = h.attr;
    const int64_t T = h.T;
    for (int64_t i = 0; i < h.n; i++) {
        const Surface s = surface(h, i);
        const float* di = h.d + 3 * i;
        float* out = rgb + 3 * i;
        if (!s.hit) {
            sky(w, di[0], di[1], di[2], out);
            for (int k = 0; k < 3; k++) {
                out[k] = out[k] < 0.0f ? 0.0f : (out[k] > 1.0f ? 1.0f : out[k]);
                normal[3 * i + k] = -di[k];
            }
            range[i] = w[W_FAR];
            labels[i] = 0;
            continue;
        }
        const int64_t j = s.tri;
        const float px = s.px, py = s.py, pz = s.pz;
        float label = attr[A_LABEL * T + j];
        const float kind = attr[A_KIND * T + j];
        float col[3] = {attr[A_R * T + j], attr[A_G * T + j], attr[A_B * T + j]};

        // ground: the cell's class, road markings painted on a street's road
        const bool g = kind == GROUND;
        if (g) {
            const float paint = attr[A_PAINT * T + j], off = attr[A_OFF * T + j];
            const float along = paint == 2.0f ? px : pz;
            const float across = (paint == 2.0f ? pz : px) - off;
            const float aa = std::fabs(across);
            const bool centre = aa < 0.08f && frac_(along / 6.0f) < 0.5f;
            const bool edge = std::fabs(aa - 3.5f) < 0.08f;
            const bool cross = frac_((along - 20.0f) / 60.0f) < static_cast<float>(4.0 / 60.0) &&
                               aa < 3.5f && frac_(across) < 0.5f;
            if (paint > 0.0f && (centre || edge || cross)) label = ROADLINE;
            const bool tiles = label == SIDEWALK &&
                               (frac_(px / 0.6f) < 0.06f || frac_(pz / 0.6f) < 0.06f);
            if (!(label >= 0.0f && label < 13.0f)) {   // not a class id: GROUND_COLOUR not read
                if (*bad_label < 0) *bad_label = j;
                label = 0.0f;
            }
            for (int k = 0; k < 3; k++)
                col[k] = GROUND_COLOUR[static_cast<int>(label)][k] * (tiles ? 0.75f : 1.0f);
        }

        // textures: noise everywhere, patterns per class on the boxes' faces
        const float fine = noise(px, py, pz, 6.0f, 1), coarse = noise(px, py, pz, 0.7f, 2);
        const float grain = (0.8f + 0.25f * fine) + 0.15f * coarse;
        for (int k = 0; k < 3; k++) col[k] = col[k] * grain;
        const bool b = kind == BOX;
        const float facade_u = std::fabs(s.nfx) > 0.5f ? pz : px;
        const bool side = b && s.nfy == 0.0f;
        bool win = false;
        if (side && label == BUILDING) {
            const float fu = frac_(facade_u / 2.5f), fy = frac_(py / 3.0f);
            win = fu > 0.25f && fu < 0.75f && fy > 0.3f && fy < 0.8f && py < -1.0f;
        }
        if (win) {
            const float f = 0.7f + 0.6f * fine;
            col[0] = 0.12f * f, col[1] = 0.16f * f, col[2] = 0.22f * f;
        }
        if (b && s.nfy < 0.0f && label == BUILDING)
            for (int k = 0; k < 3; k++) col[k] = col[k] * 0.45f;
        if (side && label == WALL) {
            const float row = floor_(py / 0.25f);
            const float brick_u = facade_u / 0.5f + 0.5f * (row - floor_(row / 2.0f) * 2.0f);
            if (frac_(py / 0.25f) < 0.12f || frac_(brick_u) < 0.06f)
                col[0] = 0.7f, col[1] = 0.68f, col[2] = 0.62f;
        }
        if (side && label == FENCE && frac_(facade_u / 0.15f) > 0.75f)
            for (int k = 0; k < 3; k++) col[k] = col[k] * 0.5f;
        if (b && label == SIGN) {
            const float ex = std::fabs(px - attr[A_CX * T + j]);
            const float ey = std::fabs(py - attr[A_CY * T + j]);
            if ((ex > ey ? ex : ey) > 0.27f || s.nfz > 0.0f) col[0] = col[1] = col[2] = 0.85f;
        }
        for (int k = 0; k < 3; k++) col[k] = col[k] * w[W_DARKEN];

        // light: ambient, the sun unless shadowed, street lamps
        const float lam = shadow[i] ? 0.0f : lambert(s, w);
        const float sky_light = 0.75f - 0.25f * s.ny;
        float acc = 0.0f;
        for (int64_t l = 0; l < n_lamps; l++) {
            const float vx = lamps[3 * l] - px, vy = lamps[3 * l + 1] - py,
                        vz = lamps[3 * l + 2] - pz;
            const float d2 = ((vx * vx + vy * vy) + vz * vz) + 0.25f;
            const float ndv = clamp0((s.nx * vx + s.ny * vy) + s.nz * vz);
            acc = acc + ndv / (d2 * std::sqrt(d2));
        }
        static constexpr float LAMP[3] = {1.0f, 0.8f, 0.5f}, WINDOW[3] = {1.0f, 0.82f, 0.5f};
        bool lit_win = false;
        if (w[W_WINDOWS] > 0.0f && win)
            lit_win = hash3(cell(facade_u, 0.4f), cell(py, static_cast<float>(1.0 / 3.0)),
                            static_cast<int64_t>(attr[A_INDEX * T + j]), 3) > 0.55f;
        float c[3];
        for (int k = 0; k < 3; k++) {
            float light = w[W_AMB + k] * sky_light + w[W_SUN + k] * lam;
            if (n_lamps > 0) light = light + (w[W_LAMPS] * acc) * LAMP[k];
            c[k] = col[k] * light;
            if (lit_win) c[k] = WINDOW[k] * w[W_WINDOWS];
        }
        // puddles mirror the sky
        if (w[W_PUDDLES] > 0.0f && g &&
            (label == ROAD || label == SIDEWALK || label == ROADLINE)) {
            const float blot = smooth_noise(px, pz, 0.35f, 4) * 0.65f +
                               smooth_noise(px, pz, 1.3f, 5) * 0.35f;
            if (blot < w[W_PUDDLES]) {
                float m[3];
                sky(w, di[0], -di[1], di[2], m);
                for (int k = 0; k < 3; k++) c[k] = c[k] * 0.35f + m[k] * 0.55f;
            }
        }
        // fog: exp(-x) as (1 + x / 256)^-256
        float q = 1.0f / (1.0f + w[W_FOG_C] * s.t);
        for (int k = 0; k < 8; k++) q = q * q;
        for (int k = 0; k < 3; k++) {
            const float x = c[k] * q + w[W_FOG + k] * (1.0f - q);
            out[k] = x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x);
        }
        range[i] = h.t[i];
        labels[i] = static_cast<int64_t>(label);
        normal[3 * i] = s.nx, normal[3 * i + 1] = s.ny, normal[3 * i + 2] = s.nz;
    }
}

// Store a batch of a cube face's rays: their colour into the face's RGB planes (3, P), range,
// labels and planar depth (range times the ray's component along the face's axis, far for the
// sky) at the texels index[i] (or start + i where index is null).
void store(int64_t n, const int64_t* index, int64_t start, const float* d, const float* rgb,
           const float* range, const int64_t* labels, const uint8_t* hit, const float* axis,
           float far, int64_t plane, float* rgb_out, float* depth_out, float* range_out,
           int64_t* labels_out) {
    for (int64_t i = 0; i < n; i++) {
        const int64_t q = index ? index[i] : start + i;
        const float* di = d + 3 * i;
        for (int k = 0; k < 3; k++) rgb_out[k * plane + q] = rgb[3 * i + k];
        range_out[q] = range[i];
        labels_out[q] = labels[i];
        depth_out[q] = hit[i] ? range[i] * ((di[0] * axis[0] + di[1] * axis[1]) + di[2] * axis[2])
                              : far;
    }
}

// ------------------------------------------------------------------------------------------
// The ops: argument checks (before any read), then the loops
// ------------------------------------------------------------------------------------------

// A contiguous CPU tensor of `dtype` and shape `shape` (-1: any size).
void check(const char* op, const char* name, const at::Tensor& t, at::ScalarType dtype,
           std::initializer_list<int64_t> shape) {
    TORCH_CHECK(t.device().is_cpu(), op, ": ", name, ": expected a CPU tensor, got one on ",
                t.device());
    bool ok = t.dim() == static_cast<int64_t>(shape.size());
    int64_t k = 0;
    for (const int64_t s : shape) {
        ok = ok && (s < 0 || t.size(k) == s);
        k++;
    }
    TORCH_CHECK(ok && t.scalar_type() == dtype, op, ": ", name, ": expected shape ",
                at::IntArrayRef(shape), " (-1: any) in ", dtype, ", got ", t.sizes(), " in ",
                t.scalar_type());
    TORCH_CHECK(t.is_contiguous(), op, ": ", name, ": expected a contiguous tensor, got strides ",
                t.strides(), " for shape ", t.sizes());
}

// Every entry of an integer tensor in [lo, hi).
template <typename I>
void check_range(const char* op, const char* name, const at::Tensor& t, int64_t lo, int64_t hi) {
    const I* p = t.const_data_ptr<I>();
    const int64_t n = t.numel();
    I low = 0, high = 0;
    if (n > 0) {
        low = high = p[0];
        for (int64_t i = 1; i < n; i++) {
            low = std::min(low, p[i]);
            high = std::max(high, p[i]);
        }
    }
    TORCH_CHECK(n == 0 || (low >= lo && high < hi), op, ": ", name, ": expected entries in [",
                lo, ", ", hi, "), got some in [", static_cast<int64_t>(low), ", ",
                static_cast<int64_t>(high), "]");
}

// The tables: attr (A_ROWS, T) float32, tris (T, 3) int32, vn (V, 3) float32, and the hits tri
// (n,) int64 in [-1, T). The corners in tris are checked as they are met, before they are read
// (a pass over all of them would cost each call as much as shading a few thousand rays).
void check_tables(const char* op, const at::Tensor& attr, const at::Tensor* tris,
                  const at::Tensor* vn, const at::Tensor& tri, int64_t n) {
    check(op, "attr", attr, at::kFloat, {A_ROWS, -1});
    check(op, "tri", tri, at::kLong, {n});
    check_range<int64_t>(op, "tri", tri, -1, attr.size(1));
    if (tris != nullptr) {
        check(op, "vn", *vn, at::kFloat, {-1, 3});
        check(op, "tris", *tris, at::kInt, {attr.size(1), 3});
    }
}

// The rays and hits of town_prepare and town_shade: o (n or 1, 3), d (n, 3), t, u, v (n,)
// float32, and the tables; w (W_COUNT,) float32.
Hits check_hits(const char* op, const at::Tensor& o, const at::Tensor& d, const at::Tensor& t,
                const at::Tensor& tri, const at::Tensor& u, const at::Tensor& v,
                const at::Tensor& attr, const at::Tensor& tris, const at::Tensor& vn,
                const at::Tensor& w, int64_t* bad_corner) {
    check(op, "d", d, at::kFloat, {-1, 3});
    const int64_t n = d.size(0);
    check(op, "o", o, at::kFloat, {-1, 3});
    TORCH_CHECK(o.size(0) == 1 || o.size(0) == n, op, ": o: expected (1, 3) or (", n,
                ", 3) like d, got ", o.sizes());
    check(op, "t", t, at::kFloat, {n});
    check(op, "u", u, at::kFloat, {n});
    check(op, "v", v, at::kFloat, {n});
    check(op, "weather", w, at::kFloat, {W_COUNT});
    check_tables(op, attr, &tris, &vn, tri, n);
    return Hits{n,
                o.const_data_ptr<float>(),
                o.size(0) == 1 ? 0 : 3,
                d.const_data_ptr<float>(),
                t.const_data_ptr<float>(),
                tri.const_data_ptr<int64_t>(),
                u.const_data_ptr<float>(),
                v.const_data_ptr<float>(),
                attr.const_data_ptr<float>(),
                attr.size(1),
                tris.const_data_ptr<int32_t>(),
                vn.const_data_ptr<float>(),
                vn.size(0),
                w.const_data_ptr<float>(),
                bad_corner};
}

// After a loop: no triangle met had a corner outside [0, V) (its normal was not interpolated,
// nor its vertex normals read; the outputs are not to be used).
void check_corners(const char* op, const Hits& h) {
    TORCH_CHECK(*h.bad_corner < 0, op, ": tris: expected corners in [0, ", h.V,
                "), got triangle ", *h.bad_corner, " with corners ", h.tris[3 * *h.bad_corner],
                ", ", h.tris[3 * *h.bad_corner + 1], ", ", h.tris[3 * *h.bad_corner + 2]);
}

// bool tensors as bytes (0 or 1)
const uint8_t* bytes(const at::Tensor& t) {
    return static_cast<const uint8_t*>(t.const_data_ptr());
}
uint8_t* mutable_bytes(const at::Tensor& t) { return static_cast<uint8_t*>(t.mutable_data_ptr()); }

// town_backfaces: out (n,) bool, whether hit tri of ray d meets its face from behind.
void town_backfaces_op(const at::Tensor& d, const at::Tensor& tri, const at::Tensor& attr,
                       const at::Tensor& out) {
    const char* op = "omniscape_torch::town_backfaces";
    check(op, "d", d, at::kFloat, {-1, 3});
    const int64_t n = d.size(0);
    check_tables(op, attr, nullptr, nullptr, tri, n);
    check(op, "out", out, at::kBool, {n});
    backfaces(n, d.const_data_ptr<float>(), tri.const_data_ptr<int64_t>(),
              attr.const_data_ptr<float>(), attr.size(1), mutable_bytes(out));
}

// town_prepare: need (n,) bool, origin (n, 3) float32, shadow (n,) bool.
void town_prepare_op(const at::Tensor& o, const at::Tensor& d, const at::Tensor& t,
                     const at::Tensor& tri, const at::Tensor& u, const at::Tensor& v,
                     const at::Tensor& attr, const at::Tensor& tris, const at::Tensor& vn,
                     const at::Tensor& weather, double bias0, double bias_per_m,
                     const at::Tensor& need, const at::Tensor& origin, const at::Tensor& shadow) {
    const char* op = "omniscape_torch::town_prepare";
    int64_t bad_corner = -1;
    const Hits h = check_hits(op, o, d, t, tri, u, v, attr, tris, vn, weather, &bad_corner);
    check(op, "need", need, at::kBool, {h.n});
    check(op, "origin", origin, at::kFloat, {h.n, 3});
    check(op, "shadow", shadow, at::kBool, {h.n});
    prepare(h, static_cast<float>(bias0), static_cast<float>(bias_per_m), mutable_bytes(need),
            origin.mutable_data_ptr<float>(), mutable_bytes(shadow));
    check_corners(op, h);
}

// town_shade: rgb (n, 3), range (n,) float32, labels (n,) int64, normal (n, 3) float32.
void town_shade_op(const at::Tensor& o, const at::Tensor& d, const at::Tensor& t,
                   const at::Tensor& tri, const at::Tensor& u, const at::Tensor& v,
                   const at::Tensor& attr, const at::Tensor& tris, const at::Tensor& vn,
                   const at::Tensor& weather, const at::Tensor& shadow, const at::Tensor& lamps,
                   const at::Tensor& rgb, const at::Tensor& range, const at::Tensor& labels,
                   const at::Tensor& normal) {
    const char* op = "omniscape_torch::town_shade";
    int64_t bad_corner = -1, bad_label = -1;
    const Hits h = check_hits(op, o, d, t, tri, u, v, attr, tris, vn, weather, &bad_corner);
    check(op, "shadow", shadow, at::kBool, {h.n});
    check(op, "lamps", lamps, at::kFloat, {-1, 3});
    check(op, "rgb", rgb, at::kFloat, {h.n, 3});
    check(op, "range", range, at::kFloat, {h.n});
    check(op, "labels", labels, at::kLong, {h.n});
    check(op, "normal", normal, at::kFloat, {h.n, 3});
    shade(h, bytes(shadow), lamps.const_data_ptr<float>(), lamps.size(0),
          rgb.mutable_data_ptr<float>(), range.mutable_data_ptr<float>(),
          labels.mutable_data_ptr<int64_t>(), normal.mutable_data_ptr<float>(), &bad_label);
    check_corners(op, h);
    // a ground triangle's class id indexes GROUND_COLOUR (checked as met, as the corners)
    TORCH_CHECK(bad_label < 0, op, ": attr: expected class ids (row ", static_cast<int>(A_LABEL),
                ") in [0, 13), got ", bad_label < 0 ? 0.0f : h.attr[A_LABEL * h.T + bad_label],
                " for ground triangle ", bad_label);
}

// town_store: n rays d (n, 3) with rgb (n, 3), range (n,), labels (n,), hit (n,) into a face's
// rgb_out (3, P), depth_out, range_out (P,) float32 and labels_out (P,) int64, at the texels
// index (n,) in [0, P), or start .. start + n - 1 where index is None.
void town_store_op(const at::Tensor& d, const std::optional<at::Tensor>& index, int64_t start,
                   const at::Tensor& rgb, const at::Tensor& range, const at::Tensor& labels,
                   const at::Tensor& hit, const at::Tensor& axis, double far,
                   const at::Tensor& rgb_out, const at::Tensor& depth_out,
                   const at::Tensor& range_out, const at::Tensor& labels_out) {
    const char* op = "omniscape_torch::town_store";
    check(op, "d", d, at::kFloat, {-1, 3});
    const int64_t n = d.size(0);
    check(op, "rgb", rgb, at::kFloat, {n, 3});
    check(op, "range", range, at::kFloat, {n});
    check(op, "labels", labels, at::kLong, {n});
    check(op, "hit", hit, at::kBool, {n});
    check(op, "axis", axis, at::kFloat, {3});
    check(op, "rgb_out", rgb_out, at::kFloat, {3, -1});
    const int64_t plane = rgb_out.size(1);
    check(op, "depth_out", depth_out, at::kFloat, {plane});
    check(op, "range_out", range_out, at::kFloat, {plane});
    check(op, "labels_out", labels_out, at::kLong, {plane});
    if (index.has_value()) {
        check(op, "index", *index, at::kLong, {n});
        check_range<int64_t>(op, "index", *index, 0, plane);
    } else {
        TORCH_CHECK(start >= 0 && start <= plane - n, op, ": start: expected 0 <= start <= ",
                    plane - n, " (", n, " rays into ", plane, " texels), got ", start);
    }
    store(n, index.has_value() ? index->const_data_ptr<int64_t>() : nullptr, start,
          d.const_data_ptr<float>(), rgb.const_data_ptr<float>(), range.const_data_ptr<float>(),
          labels.const_data_ptr<int64_t>(), bytes(hit), axis.const_data_ptr<float>(),
          static_cast<float>(far), plane, rgb_out.mutable_data_ptr<float>(),
          depth_out.mutable_data_ptr<float>(), range_out.mutable_data_ptr<float>(),
          labels_out.mutable_data_ptr<int64_t>());
}

}  // namespace

// The ops' schemas (and their fakes) are defined in Python, beside their wrappers and torch
// twins: omniscape_torch/render/kernels/town.py (OPS). Here only their CPU kernels.
TORCH_LIBRARY_IMPL(omniscape_torch, CPU, m) {
    m.impl("town_backfaces", &town_backfaces_op);
    m.impl("town_prepare", &town_prepare_op);
    m.impl("town_shade", &town_shade_op);
    m.impl("town_store", &town_store_op);
}
