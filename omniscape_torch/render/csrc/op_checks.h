#pragma once

// What the ops of fastsample.cpp and fastimage.cpp share: their arguments checked and read,
// and the dispatch of a call to the loops per element type. Part of the fast sampler's
// kernels (sample_base.h).

#include "sample_taps.h"

// ------------------------------------------------------------------------------------------
// The ops: tensors in, checked, then the kernels' loops per cube element (float32, float64,
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
// A lambda `[&](auto t, auto o, auto g)` names them with OS_DISPATCHED_TYPES.
#define OS_DISPATCHED_TYPES  \
    using T = decltype(t);   \
    using O = decltype(o);   \
    using G = decltype(g)
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

}  // namespace
