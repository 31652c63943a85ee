// The cube samplers' ops (build_lut, sample_lut, sample_grid, sample_rays) and the
// library's namespace with every op's schema; the kernels are in the sample_*.h headers (their
// map in sample_base.h), the checks the ops share in op_checks.h, the image ops in
// fastimage.cpp (two translation units: the build compiles them side by side).

#include "sample_rays.h"
#include "op_checks.h"

namespace {

// What the cube samplers check first: the cube, then its points (B', ..., last), `dim`
// dimensions, named `name`; the cube's layout.
Layout check_cube_points(const char* op, const at::Tensor& cube, const char* name,
                         const at::Tensor& points, int64_t dim, int64_t last, bool bilinear,
                         int64_t pad) {
    const Layout L = check_cube(op, cube, bilinear, pad);
    check_points(op, name, points, cube, bilinear, dim, last);
    return L;
}

// What they check last: out (B, C, height, width), valid (1 or B, height, width) or none, and
// the ring.
void check_sampled(const char* op, const at::Tensor& out, const at::Tensor& cube,
                   int64_t height, int64_t width, bool bilinear,
                   const std::optional<at::Tensor>& valid, const at::Tensor& ring_src,
                   const std::optional<at::Tensor>& ring_weight, int64_t pad) {
    check_out(op, out, cube, height, width, bilinear);
    check_valid(op, valid, cube.size(0), height, width);
    check_ring(op, ring_src, ring_weight, cube, pad);
}

// build_lut: the entries (code, fraction bits) of grid (B', P, 2) into table (B', P, 3), int32
// for a float32 grid, int64 for a float64 one, for cubes of faces `face` with the strides
// (face, row, texel) of one channel.
void build_lut_op(const at::Tensor& grid, int64_t face, int64_t pad, at::IntArrayRef strides,
                  bool bilinear, const at::Tensor& table) {
    const char* op = "omniscape_torch::build_lut";
    check_contiguous(op, "grid", grid);
    TORCH_CHECK(grid.scalar_type() == at::kFloat || grid.scalar_type() == at::kDouble, op,
                ": grid: expected float32 or float64, got ", grid.scalar_type());
    TORCH_CHECK(grid.dim() == 3 && grid.size(2) == 2, op, ": grid: expected shape (B, P, 2), got ",
                grid.sizes());
    check_table(op, table, grid);
    const Layout L = check_layout(op, face, pad, strides);
    const int64_t count = grid.size(0) * grid.size(1);
    const auto run = [&](auto g) {
        using G = decltype(g);
        const G* points = elements<G>(grid);
        Entry<G>* entries = static_cast<Entry<G>*>(table.mutable_data_ptr());
        const int64_t chunks = (count + kChunk - 1) / kChunk;
        parallel_units(chunks, kChunk, [&](int64_t c) {
            const int64_t lo = c * kChunk, m = std::min(kChunk, count - lo);
            locate<G>(points + 2 * lo, m, nullptr, L, bilinear,
                      Packed<G>{entries, INT64_MAX} + lo);
        });
    };
    if (grid.scalar_type() == at::kFloat) {
        run(float{});
    } else {
        run(double{});
    }
}

// sample_lut: cube (B, 6, C, F, F) through a table (B', P, 3) of build_lut (with its grid
// (B', P, 2) for the edge pixels), built for this cube's strides, into out (B, C, H, W).
void sample_lut_op(const at::Tensor& cube, const at::Tensor& table, const at::Tensor& grid,
                   const at::Tensor& ring_src, const std::optional<at::Tensor>& ring_weight,
                   int64_t pad, at::IntArrayRef strides, bool bilinear, int64_t fill,
                   const at::Tensor& out) {
    const char* op = "omniscape_torch::sample_lut";
    const Layout L = check_cube_points(op, cube, "grid", grid, 3, 2, bilinear, pad);
    check_table(op, table, grid);
    TORCH_CHECK(strides.size() == 3 && strides[0] == L.face_stride && strides[1] == L.row &&
                    strides[2] == L.texel,
                op, ": table: built for the strides (face, row, texel) ", strides,
                ", the cube's are (", L.face_stride, ", ", L.row, ", ", L.texel, ")");
    TORCH_CHECK(out.dim() == 4 && out.size(2) * out.size(3) == grid.size(1), op,
                ": out: expected H W = ", grid.size(1), " pixels, got shape ", out.sizes());
    check_sampled(op, out, cube, out.size(2), out.size(3), bilinear, std::nullopt, ring_src,
                  ring_weight, pad);
    dispatch(cube, out, grid.scalar_type(), [&](auto t, auto o, auto g) {
        OS_DISPATCHED_TYPES;
        sample_lut<T, O, G>(elements<T>(cube),
                            static_cast<const Entry<G>*>(table.const_data_ptr()),
                            elements<G>(grid), table.size(0) == 1 ? 0 : table.size(1),
                            ring<T>(ring_src, ring_weight, L), L, bilinear, fill_value<O>(fill),
                            planes(cube, out), static_cast<O*>(out.mutable_data_ptr()));
    });
}

// sample_grid: cube (B, 6, C, F, F) at grid (B', H, W, 2) (where valid (1 or B, H, W) is
// false: fill) into out (B, C, H, W).
void sample_grid_op(const at::Tensor& cube, const at::Tensor& grid,
                    const std::optional<at::Tensor>& valid, const at::Tensor& ring_src,
                    const std::optional<at::Tensor>& ring_weight, int64_t pad, bool bilinear,
                    int64_t fill, const at::Tensor& out) {
    const char* op = "omniscape_torch::sample_grid";
    const Layout L = check_cube_points(op, cube, "grid", grid, 4, 2, bilinear, pad);
    check_sampled(op, out, cube, grid.size(1), grid.size(2), bilinear, valid, ring_src,
                  ring_weight, pad);
    dispatch(cube, out, grid.scalar_type(), [&](auto t, auto o, auto g) {
        OS_DISPATCHED_TYPES;
        sample_grid<T, O, G>(elements<T>(cube), elements<G>(grid), batch_stride(grid),
                             mask(valid), batch_stride(valid), ring<T>(ring_src, ring_weight, L),
                             L, bilinear, fill_value<O>(fill), planes(cube, out),
                             static_cast<O*>(out.mutable_data_ptr()));
    });
}

// sample_rays: cube (B, 6, C, F, F) through the grid of camera-frame rays (B', H, W, 3) rotated
// by rotation (B', 3, 3) (none: not rotated), computed in the pass in the rays' dtype (where
// valid (1 or B, H, W) is false: fill), into out (B, C, H, W).
void sample_rays_op(const at::Tensor& cube, const at::Tensor& rays,
                    const std::optional<at::Tensor>& rotation,
                    const std::optional<at::Tensor>& valid, const at::Tensor& ring_src,
                    const std::optional<at::Tensor>& ring_weight, int64_t pad, bool bilinear,
                    int64_t fill, const at::Tensor& out) {
    const char* op = "omniscape_torch::sample_rays";
    const Layout L = check_cube_points(op, cube, "rays", rays, 4, 3, bilinear, pad);
    if (rotation.has_value()) {
        check_points(op, "rotation", *rotation, cube, bilinear, 3, 3);
        TORCH_CHECK(rotation->size(1) == 3 && rotation->scalar_type() == rays.scalar_type(), op,
                    ": rotation: expected (1 or B, 3, 3) in the rays' dtype ", rays.scalar_type(),
                    ", got ", rotation->scalar_type(), " ", rotation->sizes());
    }
    check_sampled(op, out, cube, rays.size(1), rays.size(2), bilinear, valid, ring_src,
                  ring_weight, pad);
    dispatch(cube, out, rays.scalar_type(), [&](auto t, auto o, auto g) {
        OS_DISPATCHED_TYPES;
        sample_rays<T, O, G>(elements<T>(cube), elements<G>(rays), batch_stride(rays),
                             rotation.has_value() ? elements<G>(*rotation) : nullptr,
                             batch_stride(rotation), mask(valid), batch_stride(valid),
                             ring<T>(ring_src, ring_weight, L), L, bilinear, fill_value<O>(fill),
                             planes(cube, out), static_cast<O*>(out.mutable_data_ptr()));
    });
}

// cone_taps (kernels/cone.py): the texels that the bilinear taps of rays (n, 3) touch, marked
// in padded (6, m, m) bool, m = F + 2 pad + 2 (faces padded by the atlas border and one texel
// more). The same float64 operations, in the same order, as the NumPy twin's.
template <typename G>
void cone_taps(const G* rays, const uint8_t* valid, int64_t n, const double* r,
               const int64_t* faces, int64_t F, int64_t p, double margin, double near,
               uint8_t* padded) {
    const int64_t m = F + 2 * p + 2, size = 6 * m * m;
    const double f = static_cast<double>(F) / 2.0,
                 c = static_cast<double>(F - 1) / 2.0 + static_cast<double>(p) + 1.0;
    const auto mark = [&](int64_t index) {
        if (index >= 0 && index < size) padded[index] = 1;
    };
    for (int64_t i = 0; i < n; i++) {
        if (valid && !valid[i]) continue;
        double q[3] = {static_cast<double>(rays[3 * i]), static_cast<double>(rays[3 * i + 1]),
                       static_cast<double>(rays[3 * i + 2])};
        if (r) {
            const double x = q[0], y = q[1], z = q[2];
            for (int k = 0; k < 3; k++) q[k] = (r[3 * k] * x + r[3 * k + 1] * y) + r[3 * k + 2] * z;
        }
        if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) continue;
        const double top = std::max(std::max(std::abs(q[0]), std::abs(q[1])), std::abs(q[2]));
        const auto component = [&](int64_t code) {
            return code > 0 ? q[code - 1] : -q[-code - 1];
        };
        for (int64_t k = 0; k < 6; k++) {
            const double a = component(faces[3 * k]);
            if (!(a >= top * near) || !(a > 0)) continue;
            const double u = c + f * component(faces[3 * k + 2]) / a;
            const double v = c + f * component(faces[3 * k + 1]) / a;
            const double j_lo = std::floor(u - margin), i_lo = std::floor(v - margin);
            const int64_t base = (k * m + static_cast<int64_t>(i_lo)) * m +
                                 static_cast<int64_t>(j_lo);
            mark(base);
            mark(base + 1);
            mark(base + m);
            mark(base + m + 1);
            const bool wide_j = std::floor(u + margin) > j_lo,
                       wide_i = std::floor(v + margin) > i_lo;
            if (wide_j) {
                mark(base + 2);
                mark(base + m + 2);
            }
            if (wide_i) {
                mark(base + 2 * m);
                mark(base + 2 * m + 1);
            }
            if (wide_i && wide_j) mark(base + 2 * m + 2);
        }
    }
}

void cone_taps_op(const at::Tensor& rays, const std::optional<at::Tensor>& valid,
                  const std::optional<at::Tensor>& rotation, const at::Tensor& faces,
                  int64_t face_size, int64_t pad, double tap_margin, double near,
                  const at::Tensor& padded) {
    const char* op = "omniscape_torch::cone_taps";
    check_contiguous(op, "rays", rays);
    TORCH_CHECK(rays.scalar_type() == at::kFloat || rays.scalar_type() == at::kDouble, op,
                ": rays: expected float32 or float64, got ", rays.scalar_type());
    TORCH_CHECK(rays.dim() == 2 && rays.size(1) == 3, op, ": rays: expected (n, 3), got ",
                rays.sizes());
    const int64_t n = rays.size(0);
    if (valid.has_value()) {
        check_contiguous(op, "valid", *valid);
        TORCH_CHECK(valid->scalar_type() == at::kBool && valid->dim() == 1 &&
                    valid->size(0) == n, op, ": valid: expected (", n, ") bool, got ",
                    valid->scalar_type(), " ", valid->sizes());
    }
    if (rotation.has_value()) {
        check_contiguous(op, "rotation", *rotation);
        TORCH_CHECK(rotation->scalar_type() == at::kDouble && rotation->dim() == 2 &&
                    rotation->size(0) == 3 && rotation->size(1) == 3, op,
                    ": rotation: expected (3, 3) float64, got ", rotation->scalar_type(), " ",
                    rotation->sizes());
    }
    check_contiguous(op, "faces", faces);
    TORCH_CHECK(faces.scalar_type() == at::kLong && faces.dim() == 2 && faces.size(0) == 6 &&
                faces.size(1) == 3, op, ": faces: expected (6, 3) int64, got ",
                faces.scalar_type(), " ", faces.sizes());
    const int64_t* codes = faces.const_data_ptr<int64_t>();
    for (int64_t k = 0; k < 18; k++)
        TORCH_CHECK(codes[k] != 0 && codes[k] >= -3 && codes[k] <= 3, op,
                    ": faces: expected signed axis codes in -3..-1, 1..3, got ", codes[k]);
    TORCH_CHECK(face_size >= 1 && pad >= 0, op, ": expected face_size >= 1 and pad >= 0, got ",
                face_size, " and ", pad);
    const int64_t m = face_size + 2 * pad + 2;
    check_contiguous(op, "padded", padded);
    TORCH_CHECK(padded.scalar_type() == at::kBool && padded.dim() == 3 && padded.size(0) == 6 &&
                padded.size(1) == m && padded.size(2) == m, op, ": padded: expected (6, ", m,
                ", ", m, ") bool, got ", padded.scalar_type(), " ", padded.sizes());
    const uint8_t* v = valid.has_value()
                           ? reinterpret_cast<const uint8_t*>(valid->const_data_ptr<bool>())
                           : nullptr;
    const double* r = rotation.has_value() ? rotation->const_data_ptr<double>() : nullptr;
    uint8_t* out = reinterpret_cast<uint8_t*>(padded.mutable_data_ptr<bool>());
    if (rays.scalar_type() == at::kFloat) {
        cone_taps(rays.const_data_ptr<float>(), v, n, r, codes, face_size, pad, tap_margin,
                  near, out);
    } else {
        cone_taps(rays.const_data_ptr<double>(), v, n, r, codes, face_size, pad, tap_margin,
                  near, out);
    }
}

}  // namespace

TORCH_LIBRARY(omniscape_torch, m) {
    // the fake (meta) implementations, for torch.compile, are registered there
    m.set_python_module("omniscape_torch.render.kernels.build");
    m.def("build_lut(Tensor grid, int face, int pad, int[] strides, bool bilinear, "
          "Tensor(a!) table) -> ()");
    m.def("sample_lut(Tensor cube, Tensor table, Tensor grid, Tensor ring_src, "
          "Tensor? ring_weight, int pad, int[] strides, bool bilinear, int fill, "
          "Tensor(a!) out) -> ()");
    m.def("sample_grid(Tensor cube, Tensor grid, Tensor? valid, Tensor ring_src, "
          "Tensor? ring_weight, int pad, bool bilinear, int fill, Tensor(a!) out) -> ()");
    m.def("sample_rays(Tensor cube, Tensor rays, Tensor? rotation, Tensor? valid, "
          "Tensor ring_src, Tensor? ring_weight, int pad, bool bilinear, int fill, "
          "Tensor(a!) out) -> ()");
    m.def("camera_grid(Tensor affine, Tensor limits, Tensor table, Tensor rotation, int face, "
          "int pad, Tensor(a!) grid, Tensor(b!) valid) -> ()");
    m.def("camera_rays(Tensor affine, Tensor limits, Tensor table, Tensor(a!) rays, "
          "Tensor(b!) valid) -> ()");
    m.def("sample_image(Tensor image, Tensor rays, Tensor? rotation, Tensor intrinsics, "
          "Tensor? valid, bool bilinear, int fill, Tensor(a!) out, Tensor(b!)? valid_out) -> ()");
    m.def("box_pixels(Tensor rays, Tensor? rotation, Tensor intrinsics, Tensor? valid, "
          "Tensor sample, Tensor windows, Tensor rects, Tensor(a!) out) -> ()");
    m.def("outline_points(Tensor rects, Tensor counts, Tensor owner, int offset, "
          "Tensor(a!) points) -> ()");
    m.def("outline_reduce(Tensor pix, Tensor ok, Tensor through, Tensor counts, Tensor owner, "
          "int offset, int width, int height, float near, Tensor(a!) extents, "
          "Tensor(b!) longest, Tensor(c!) flags) -> ()");
    m.def("mip_image(Tensor image, Tensor rays, Tensor? rotation, Tensor intrinsics, "
          "Tensor valid, float minifies, Tensor(a!) out) -> ()");
    m.def("reproject_image(Tensor? image, Tensor? labels, Tensor affine, Tensor limits, "
          "Tensor table, Tensor rotation, Tensor intrinsics, bool bilinear, float minifies, "
          "int fill, Tensor(a!)? out, Tensor(b!)? out_labels, Tensor(c!) valid_out) -> ()");
    m.def("framing_reach(Tensor rotation, Tensor intrinsics, Tensor half, Tensor cos, "
          "Tensor sin, int height, int width, Tensor(a!) theta) -> ()");
    m.def("framing_focal(Tensor radius, Tensor to_edge, Tensor coverage, int height, "
          "int width, Tensor(a!) focal) -> ()");
    m.def("frame_lens(Tensor u, Tensor spec, Tensor intrinsics, Tensor centre, Tensor cos, "
          "Tensor sin, int src_height, int src_width, Tensor radius, Tensor slope, "
          "float per_angle, Tensor to_edge, int height, int width, Tensor(a!) params, "
          "Tensor(b!) fov, Tensor(c!) attitude, Tensor(d!) applied, Tensor(e!) rotation, "
          "Tensor(f!) coverage) -> ()");
}

TORCH_LIBRARY_IMPL(omniscape_torch, CPU, m) {
    m.impl("build_lut", &build_lut_op);
    m.impl("sample_lut", &sample_lut_op);
    m.impl("sample_grid", &sample_grid_op);
    m.impl("sample_rays", &sample_rays_op);
    m.impl("cone_taps", &cone_taps_op);
}
