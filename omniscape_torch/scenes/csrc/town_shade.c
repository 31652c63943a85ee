/* Shading of the built-in town's ray hits: the loops of omniscape_torch/scenes/town.py's
 * Town._shade_reference (torch), one ray at a time. Built by omniscape_torch/scenes/native.py
 * with the system C compiler and loaded with ctypes (which releases the GIL during a call).
 *
 * Exactness: float32 arithmetic in the reference's order of operations, built with
 * -ffp-contract=off and without -ffast-math, so every operation rounds as torch's does and a
 * ray's result does not depend on its batch (tests/test_scenes.py compares the two).
 *
 * Layouts: rays o (n or 1, 3), d (n, 3), hits t, tri (-1: none), barycentric u, v; the
 * triangles' attributes attr (A_ROWS, T) row-major; triangle corners tris (T, 3), vertex
 * normals vn (V, 3); weather and constants w (W_COUNT), see town.py's _native_weather. */
#include <math.h>
#include <stdint.h>

enum { A_NX, A_NY, A_NZ, A_LABEL, A_KIND, A_R, A_G, A_B, A_PAINT, A_OFF, A_CX, A_CY, A_INDEX,
       A_SMOOTH, A_ROWS };
enum { W_SX, W_SY, W_SZ, W_SUN, W_AMB = W_SUN + 3, W_ZEN = W_AMB + 3, W_HOR = W_ZEN + 3,
       W_FOG = W_HOR + 3, W_FOG_C = W_FOG + 3, W_LAMPS, W_WINDOWS, W_PUDDLES, W_DARKEN,
       W_RAIN_SKY, W_HAZE, W_FAR, W_COUNT };
/* class ids (CARLA) and part kinds */
enum { BUILDING = 1, FENCE = 2, ROADLINE = 6, ROAD = 7, SIDEWALK = 8, WALL = 11, SIGN = 12 };
enum { GROUND = 0, BOX = 1 };

static const float GROUND_COLOUR[13][3] = {
    [ROAD] = {0.26f, 0.26f, 0.27f}, [ROADLINE] = {0.85f, 0.85f, 0.8f},
    [SIDEWALK] = {0.62f, 0.60f, 0.56f}, [3] = {0.42f, 0.38f, 0.28f}};

/* floorf without a libm call (baseline x86-64 has no rounding instruction): exact, as floorf,
 * for every finite float (from 2^23 on every float is an integer) */
static inline float floor_(float x) {
    if (!(fabsf(x) < 8388608.0f)) return x;
    const float i = (float)(int32_t)x;
    return i > x ? i - 1.0f : i;
}
static inline float frac_(float x) { return x - floor_(x); }
static inline int64_t cell(float x, float scale) { return (int64_t)floor_(x * scale); }
static inline float clamp0(float x) { return x < 0.0f ? 0.0f : x; }

/* town.py's _noise: a hash of a cell -> [0, 1) (int64 arithmetic wraps: done in uint64) */
static float noise(float x, float y, float z, float scale, int64_t salt) {
    uint64_t h = ((uint64_t)cell(x, scale) * 73856093u) ^ ((uint64_t)cell(y, scale) * 19349663u) ^
                 ((uint64_t)cell(z, scale) * 83492791u) ^
                 (uint64_t)(0x9E3779B9LL + salt * 0x632BE5ABLL);
    h = (h * 0x45D9F3Bu) & 0xFFFFFFFFu;
    h ^= h >> 16;
    h = (h * 0x45D9F3Bu) & 0xFFFFFFFFu;
    h ^= h >> 16;
    return (float)(h & 0xFFFF) * (1.0f / 65536.0f);
}

/* town.py's _hash of three integers */
static float hash3(int64_t a, int64_t b, int64_t c, int64_t salt) {
    uint64_t h = (uint64_t)(0x9E3779B9LL + salt * 0x632BE5ABLL);
    const uint64_t k[3] = {73856093u, 19349663u, 83492791u};
    const int64_t v[3] = {a, b, c};
    for (int i = 0; i < 3; i++) {
        h = (h ^ ((uint64_t)v[i] * k[i])) & 0xFFFFFFFFu;
        h = (h * 0x45D9F3Bu) & 0xFFFFFFFFu;
        h ^= h >> 16;
    }
    return (float)(h & 0xFFFF) / 65536.0f;
}

/* town.py's _smooth_noise: bilinear, smoothstep-weighted value noise over the ground */
static float smooth_noise(float x, float z, float scale, int64_t salt) {
    const float sx = x * scale, sz = z * scale;
    const float ixf = floor_(sx), izf = floor_(sz);
    const float fx = sx - ixf, fz = sz - izf;
    const float wx = (fx * fx) * (3.0f - 2.0f * fx), wz = (fz * fz) * (3.0f - 2.0f * fz);
    const int64_t ix = (int64_t)ixf, iz = (int64_t)izf;
    const float h00 = hash3(ix, 0, iz, salt), h10 = hash3(ix + 1, 0, iz, salt);
    const float h01 = hash3(ix, 0, iz + 1, salt), h11 = hash3(ix + 1, 0, iz + 1, salt);
    const float a = h00 + (h10 - h00) * wx;
    const float b = h01 + (h11 - h01) * wx;
    return a + (b - a) * wz;
}

typedef struct {
    int hit;
    int64_t tri;
    float t, px, py, pz, nfx, nfy, nfz, nx, ny, nz;
} Surface;

/* The hit point, the flat (face) normal and the shading normal of ray i. */
static Surface surface(int64_t i, const float *o, int64_t o_step, const float *d, const float *t,
                       const int64_t *tri, const float *u, const float *v, const float *attr,
                       int64_t T, const int32_t *tris, const float *vn) {
    Surface s;
    s.hit = tri[i] >= 0;
    s.tri = s.hit ? tri[i] : 0;
    s.t = s.hit ? t[i] : 0.0f;
    const float *oi = o + i * o_step, *di = d + 3 * i;
    s.px = oi[0] + s.t * di[0];
    s.py = oi[1] + s.t * di[1];
    s.pz = oi[2] + s.t * di[2];
    s.nfx = attr[A_NX * T + s.tri];
    s.nfy = attr[A_NY * T + s.tri];
    s.nfz = attr[A_NZ * T + s.tri];
    s.nx = s.nfx, s.ny = s.nfy, s.nz = s.nfz;
    if (s.hit && attr[A_SMOOTH * T + s.tri] > 0.0f) {
        const int32_t *c = tris + 3 * s.tri;
        const float us = u[i], vs = v[i], w0 = (1.0f - us) - vs;
        float n[3];
        for (int k = 0; k < 3; k++)
            n[k] = (w0 * vn[3 * c[0] + k] + us * vn[3 * c[1] + k]) + vs * vn[3 * c[2] + k];
        const float len = sqrtf((n[0] * n[0] + n[1] * n[1]) + n[2] * n[2]);
        s.nx = n[0] / len, s.ny = n[1] / len, s.nz = n[2] / len;
    }
    return s;
}

static float lambert(const Surface *s, const float *w) {
    return clamp0((s->nx * w[W_SX] + s->ny * w[W_SY]) + s->nz * w[W_SZ]);
}

/* Which hits face away from their ray (out[i] = 1): the ray started inside a primitive. */
void town_backfaces(int64_t n, const float *d, const int64_t *tri, const float *attr, int64_t T,
                    uint8_t *out) {
    for (int64_t i = 0; i < n; i++) {
        const int64_t j = tri[i];
        const float *di = d + 3 * i;
        out[i] = j >= 0 && (attr[A_NX * T + j] * di[0] + attr[A_NY * T + j] * di[1]) +
                               attr[A_NZ * T + j] * di[2] > 0.0f;
    }
}

/* Which rays need a shadow ray (hit, lit by the shading normal, their face turned to the sun),
 * its origin, and the initial shadow flag (hit and lit by the shading normal). */
void town_prepare(int64_t n, const float *o, int64_t o_step, const float *d, const float *t,
                  const int64_t *tri, const float *u, const float *v, const float *attr,
                  int64_t T, const int32_t *tris, const float *vn, const float *w,
                  float bias0, float bias_per_m, uint8_t *need, float *origin,
                  uint8_t *shadow) {
    for (int64_t i = 0; i < n; i++) {
        Surface s = surface(i, o, o_step, d, t, tri, u, v, attr, T, tris, vn);
        const float lam = lambert(&s, w);
        shadow[i] = s.hit && lam > 0.0f;
        need[i] = shadow[i] && (s.nfx * w[W_SX] + s.nfy * w[W_SY]) + s.nfz * w[W_SZ] > 0.0f;
        const float bias = bias_per_m * s.t + bias0;
        origin[3 * i] = s.px + s.nfx * bias;
        origin[3 * i + 1] = s.py + s.nfy * bias;
        origin[3 * i + 2] = s.pz + s.nfz * bias;
    }
}

/* town.py's sky_of: the sky's colour in direction e */
static void sky(const float *w, float ex, float ey, float ez, float out[3]) {
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

void town_shade(int64_t n, const float *o, int64_t o_step, const float *d, const float *t,
                const int64_t *tri, const float *u, const float *v, const float *attr, int64_t T,
                const int32_t *tris, const float *vn, const float *w, const uint8_t *shadow,
                const float *lamps, int64_t n_lamps, float *rgb, float *range, int64_t *labels,
                float *normal) {
    for (int64_t i = 0; i < n; i++) {
        Surface s = surface(i, o, o_step, d, t, tri, u, v, attr, T, tris, vn);
        const float *di = d + 3 * i;
        float *out = rgb + 3 * i;
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

        /* ground: the cell's class, road markings painted on a street's road */
        const int g = kind == GROUND;
        if (g) {
            const float paint = attr[A_PAINT * T + j], off = attr[A_OFF * T + j];
            const float along = paint == 2.0f ? px : pz;
            const float across = (paint == 2.0f ? pz : px) - off;
            const float aa = fabsf(across);
            const int centre = aa < 0.08f && frac_(along / 6.0f) < 0.5f;
            const int edge = fabsf(aa - 3.5f) < 0.08f;
            const int cross = frac_((along - 20.0f) / 60.0f) < (float)(4.0 / 60.0) && aa < 3.5f &&
                              frac_(across) < 0.5f;
            if (paint > 0.0f && (centre || edge || cross)) label = ROADLINE;
            const int tiles = label == SIDEWALK &&
                              (frac_(px / 0.6f) < 0.06f || frac_(pz / 0.6f) < 0.06f);
            for (int k = 0; k < 3; k++)
                col[k] = GROUND_COLOUR[(int)label][k] * (tiles ? 0.75f : 1.0f);
        }

        /* textures: noise everywhere, patterns per class on the boxes' faces */
        const float fine = noise(px, py, pz, 6.0f, 1), coarse = noise(px, py, pz, 0.7f, 2);
        const float grain = (0.8f + 0.25f * fine) + 0.15f * coarse;
        for (int k = 0; k < 3; k++) col[k] = col[k] * grain;
        const int b = kind == BOX;
        const float facade_u = fabsf(s.nfx) > 0.5f ? pz : px;
        const int side = b && s.nfy == 0.0f;
        int win = 0;
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
            const float ex = fabsf(px - attr[A_CX * T + j]), ey = fabsf(py - attr[A_CY * T + j]);
            if ((ex > ey ? ex : ey) > 0.27f || s.nfz > 0.0f) col[0] = col[1] = col[2] = 0.85f;
        }
        for (int k = 0; k < 3; k++) col[k] = col[k] * w[W_DARKEN];

        /* light: ambient, the sun unless shadowed, street lamps */
        const float lam = shadow[i] ? 0.0f : lambert(&s, w);
        const float sky_light = 0.75f - 0.25f * s.ny;
        float acc = 0.0f;
        for (int64_t l = 0; l < n_lamps; l++) {
            const float vx = lamps[3 * l] - px, vy = lamps[3 * l + 1] - py,
                        vz = lamps[3 * l + 2] - pz;
            const float d2 = ((vx * vx + vy * vy) + vz * vz) + 0.25f;
            const float ndv = clamp0((s.nx * vx + s.ny * vy) + s.nz * vz);
            acc = acc + ndv / (d2 * sqrtf(d2));
        }
        static const float LAMP[3] = {1.0f, 0.8f, 0.5f}, WINDOW[3] = {1.0f, 0.82f, 0.5f};
        int lit_win = 0;
        if (w[W_WINDOWS] > 0.0f && win)
            lit_win = hash3(cell(facade_u, 0.4f), cell(py, (float)(1.0 / 3.0)),
                            (int64_t)attr[A_INDEX * T + j], 3) > 0.55f;
        float c[3];
        for (int k = 0; k < 3; k++) {
            float light = w[W_AMB + k] * sky_light + w[W_SUN + k] * lam;
            if (n_lamps > 0) light = light + (w[W_LAMPS] * acc) * LAMP[k];
            c[k] = col[k] * light;
            if (lit_win) c[k] = WINDOW[k] * w[W_WINDOWS];
        }
        /* puddles mirror the sky */
        if (w[W_PUDDLES] > 0.0f && g && (label == ROAD || label == SIDEWALK || label == ROADLINE)) {
            const float blot = smooth_noise(px, pz, 0.35f, 4) * 0.65f +
                               smooth_noise(px, pz, 1.3f, 5) * 0.35f;
            if (blot < w[W_PUDDLES]) {
                float m[3];
                sky(w, di[0], -di[1], di[2], m);
                for (int k = 0; k < 3; k++) c[k] = c[k] * 0.35f + m[k] * 0.55f;
            }
        }
        /* fog: exp(-x) as (1 + x / 256)^-256 */
        float q = 1.0f / (1.0f + w[W_FOG_C] * s.t);
        for (int k = 0; k < 8; k++) q = q * q;
        for (int k = 0; k < 3; k++) {
            const float x = c[k] * q + w[W_FOG + k] * (1.0f - q);
            out[k] = x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x);
        }
        range[i] = t[i];
        labels[i] = (int64_t)label;
        normal[3 * i] = s.nx, normal[3 * i + 1] = s.ny, normal[3 * i + 2] = s.nz;
    }
}

/* Store a batch of a cube face's rays: their colour into the face's RGB planes (3, F * F),
 * range, labels and planar depth (range times the ray's component along the face's axis,
 * far for the sky) at the texels index[i] (or start + i where index is NULL). */
void town_store(int64_t n, const int64_t *index, int64_t start, const float *d,
                const float *rgb, const float *range, const int64_t *labels,
                const uint8_t *hit, const float *axis, float far, int64_t plane,
                float *rgb_out, float *depth_out, float *range_out, int64_t *labels_out) {
    for (int64_t i = 0; i < n; i++) {
        const int64_t q = index ? index[i] : start + i;
        const float *di = d + 3 * i;
        for (int k = 0; k < 3; k++) rgb_out[k * plane + q] = rgb[3 * i + k];
        range_out[q] = range[i];
        labels_out[q] = labels[i];
        depth_out[q] = hit[i] ? range[i] * ((di[0] * axis[0] + di[1] * axis[1]) + di[2] * axis[2])
                              : far;
    }
}
