// The image ops of the library that fastsample.cpp defines: sample_image, mip_image, the
// radial cameras (camera_grid, camera_rays), the detection ops (box_pixels, outline_*)
// and the framing's (framing_reach, framing_focal); the kernels are in the sample_*.h headers
// and camera_grid.h (their map in sample_base.h), the checks the ops share in op_checks.h.

// (before the kernels' headers, whose Layout would shadow c10's in them)
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>

#include "sample_image.h"
#include "sample_mip.h"
#include "camera_grid.h"
#include "op_checks.h"

namespace {

// What sample_image_op and mip_image_op check alike: image (B, C, H, W) on the CPU within
// int32 offsets, the rays (B or 1, h, w, 3), intrinsics (B or 1, 4) and rotation (B or 1, 3, 3)
// in one floating dtype; image's layout.
Layout check_image_rays(const char* op, const at::Tensor& image, const at::Tensor& rays,
                        const std::optional<at::Tensor>& rotation,
                        const at::Tensor& intrinsics, bool bilinear) {
    const int64_t height = image.size(2), width = image.size(3);
    TORCH_CHECK(image.stride(2) >= 0 && image.stride(3) >= 0 &&
                    (height - 1) * image.stride(2) + (width - 1) * image.stride(3) < kMaxOffset,
                op, ": image: too large for int32 offsets (strides ", image.strides(), ")");
    // the image stands for the cube of check_points: a (B, 1, C, 1, 1) view
    const at::Tensor cube = image.unsqueeze(1).narrow(3, 0, 1).narrow(4, 0, 1);
    check_points(op, "rays", rays, cube, bilinear, 4, 3);
    check_points(op, "intrinsics", intrinsics, cube, bilinear, 2, 4);
    if (rotation.has_value()) {
        check_points(op, "rotation", *rotation, cube, bilinear, 3, 3);
        TORCH_CHECK(rotation->size(1) == 3, op, ": rotation: expected (1 or B, 3, 3), got ",
                    rotation->sizes());
    }
    TORCH_CHECK(intrinsics.scalar_type() == rays.scalar_type() &&
                    (!rotation.has_value() || rotation->scalar_type() == rays.scalar_type()),
                op, ": intrinsics, rotation: expected the rays' dtype ", rays.scalar_type());
    return image_layout(height, width, image.stride(2), image.stride(3));
}

// sample_image: a perspective image (B, C, H, W), any strides, along rays (1 or B, h, w, 3)
// rotated by rotation (1 or B, 3, 3, or none) into its pinhole camera, intrinsics (1 or B, 4)
// fx, fy, cx, cy, all in the dtype the image is sampled with; where valid (1 or B, h, w) is
// false, or the ray misses the image: fill; into out (B, C, h, w) and the validity into
// valid_out (B, h, w).
void sample_image_op(const at::Tensor& image, const at::Tensor& rays,
                     const std::optional<at::Tensor>& rotation, const at::Tensor& intrinsics,
                     const std::optional<at::Tensor>& valid, bool bilinear, int64_t fill,
                     const at::Tensor& out, const std::optional<at::Tensor>& valid_out) {
    const char* op = "omniscape_torch::sample_image";
    check_cpu(op, "image", image);
    TORCH_CHECK(image.dim() == 4 && image.size(2) >= 1 && image.size(3) >= 1, op,
                ": image: expected shape (B, C, H, W), got ", image.sizes());
    check_elements(op, "image", image, bilinear);
    const int64_t height = image.size(2), width = image.size(3);
    const Layout L = check_image_rays(op, image, rays, rotation, intrinsics, bilinear);
    const at::Tensor cube = image.unsqueeze(1).narrow(3, 0, 1).narrow(4, 0, 1);
    check_out(op, out, cube, rays.size(1), rays.size(2), bilinear);
    check_valid(op, valid, image.size(0), rays.size(1), rays.size(2));
    if (valid_out.has_value()) {
        check_contiguous(op, "valid_out", *valid_out);
        TORCH_CHECK(valid_out->scalar_type() == at::kBool &&
                        valid_out->sizes() ==
                            at::IntArrayRef({image.size(0), rays.size(1), rays.size(2)}),
                    op, ": valid_out: expected bool (", image.size(0), ", ", rays.size(1), ", ",
                    rays.size(2), "), got ", valid_out->scalar_type(), " ", valid_out->sizes());
    }
    dispatch(image, out, rays.scalar_type(), [&](auto t, auto o, auto g) {
        using T = decltype(t);
        using O = decltype(o);
        using G = decltype(g);
        sample_image<T, O, G>(elements<T>(image), elements<G>(rays), batch_stride(rays),
                              rotation.has_value() ? elements<G>(*rotation) : nullptr,
                              batch_stride(rotation), elements<G>(intrinsics),
                              batch_stride(intrinsics), mask(valid), batch_stride(valid),
                              height, width, L, bilinear, fill_value<O>(fill),
                              Planes{out.size(0), out.size(1), out.size(2) * out.size(3),
                                     out.size(3), image.stride(0), image.stride(1),
                                     out.stride(0), out.stride(1), out.stride(3)},
                              static_cast<O*>(out.mutable_data_ptr()),
                              valid_out.has_value()
                                  ? static_cast<uint8_t*>(valid_out->mutable_data_ptr())
                                  : nullptr);
    });
}

// mip_image: the pixels of out (B, C, h, w), sample_image's bilinear samples of image (B, C, H,
// W; uint8, float32 or float64) along the same rays, rotation and intrinsics, whose footprint
// minifies the image (a Jacobian column of the rays' image positions longer than `minifies`
// pixels, among the pixels of valid (B, h, w)), overwritten by their mip filter
// (mip_footprints); the other pixels are left as they are.
void mip_image_op(const at::Tensor& image, const at::Tensor& rays,
                  const std::optional<at::Tensor>& rotation, const at::Tensor& intrinsics,
                  const at::Tensor& valid, double minifies, const at::Tensor& out) {
    const char* op = "omniscape_torch::mip_image";
    check_cpu(op, "image", image);
    const auto s = image.scalar_type();
    TORCH_CHECK(image.dim() == 4 && image.size(2) >= 1 && image.size(3) >= 1 &&
                    (s == at::kByte || s == at::kFloat || s == at::kDouble),
                op, ": image: expected uint8, float32 or float64 (B, C, H, W), got ", s, " ",
                image.sizes());
    const int64_t height = image.size(2), width = image.size(3);
    const Layout L = check_image_rays(op, image, rays, rotation, intrinsics, true);
    const at::Tensor cube = image.unsqueeze(1).narrow(3, 0, 1).narrow(4, 0, 1);
    check_out(op, out, cube, rays.size(1), rays.size(2), true);
    TORCH_CHECK(valid.size(0) == image.size(0), op, ": valid: expected one per sample (",
                image.size(0), "), got ", valid.sizes());
    check_valid(op, valid, image.size(0), rays.size(1), rays.size(2));
    const Planes S = planes(cube, out);
    dispatch(image, out, rays.scalar_type(), [&](auto t, auto o, auto g) {
        using T = decltype(t);
        using O = decltype(o);
        using G = decltype(g);
        if constexpr (std::is_same_v<T, uint8_t> || std::is_same_v<T, float> ||
                      std::is_same_v<T, double>) {
            if constexpr (!std::is_same_v<O, int64_t>) {
                mip_image<T, O, G>(elements<T>(image), batch_stride(image), image.stride(1),
                                   elements<G>(rays), batch_stride(rays),
                                   rotation.has_value() ? elements<G>(*rotation) : nullptr,
                                   batch_stride(rotation), elements<G>(intrinsics),
                                   batch_stride(intrinsics), mask(valid), height, width, L,
                                   G(minifies * minifies), S,
                                   static_cast<O*>(out.mutable_data_ptr()));
            }
        }
    });
}

// Radially symmetric cameras (radial_rays): affine (N, 6), limits (N, 5), table (N, 2, K) or
// (1, 2, K) (shared by the cameras), K >= 2, N >= 1, contiguous, all in one floating dtype
// (returned).
at::ScalarType check_cameras(const char* op, const at::Tensor& affine, const at::Tensor& limits,
                             const at::Tensor& table) {
    const at::ScalarType dtype = affine.scalar_type();
    TORCH_CHECK(dtype == at::kFloat || dtype == at::kDouble, op,
                ": affine: expected float32 or float64, got ", dtype);
    const int64_t n = affine.dim() == 2 ? affine.size(0) : -1;
    const auto check = [&](const char* name, const at::Tensor& t, at::IntArrayRef shape) {
        check_contiguous(op, name, t);
        TORCH_CHECK(t.sizes() == shape && t.scalar_type() == dtype, op, ": ", name,
                    ": expected shape ", shape, " in ", dtype, ", got ", t.sizes(), " in ",
                    t.scalar_type());
    };
    check("affine", affine, {n, 6});
    check("limits", limits, {n, 5});
    const bool shared = table.dim() == 3 && table.size(0) == 1;
    check("table", table, {shared ? 1 : n, 2, table.dim() == 3 ? table.size(2) : -1});
    TORCH_CHECK(n >= 1 && table.size(2) >= 2 && table.size(2) < kMaxOffset / 2, op,
                ": table: expected 1 or more cameras of 2 or more entries, got ", table.sizes());
    return dtype;
}

// The elements between the tables of consecutive cameras (check_cameras): 0 for one shared.
int64_t table_batch(const at::Tensor& table) {
    return table.size(0) == 1 ? 0 : 2 * table.size(2);
}

// valid (B, H, W) bool, contiguous, of `batch` cameras.
void check_camera_valid(const char* op, const at::Tensor& valid, int64_t batch) {
    check_contiguous(op, "valid", valid);
    TORCH_CHECK(valid.scalar_type() == at::kBool && valid.dim() == 3 && valid.size(0) == batch,
                op, ": valid: expected bool (", batch, ", H, W), got ", valid.scalar_type(), " ",
                valid.sizes());
}

// points (B, H, W, last) like valid (B, H, W), contiguous, in dtype.
void check_camera_points(const char* op, const char* name, const at::Tensor& t,
                         const at::Tensor& valid, int64_t last, at::ScalarType dtype) {
    check_contiguous(op, name, t);
    TORCH_CHECK(t.scalar_type() == dtype &&
                    t.sizes() == at::IntArrayRef({valid.size(0), valid.size(1), valid.size(2),
                                                  last}),
                op, ": ", name, ": expected (", valid.size(0), ", ", valid.size(1), ", ",
                valid.size(2), ", ", last, ") in ", dtype, " like valid, got ", t.sizes(),
                " in ", t.scalar_type());
}

// camera_grid: the atlas grid (B, H, W, 2) and validity (B, H, W) of B radially symmetric
// cameras (check_cameras) rotated by rotation (B, 3, 3), for faces of `face` texels padded by
// `pad`; all in one floating dtype.
void camera_grid_op(const at::Tensor& affine, const at::Tensor& limits, const at::Tensor& table,
                    const at::Tensor& rotation, int64_t face, int64_t pad, const at::Tensor& grid,
                    const at::Tensor& valid) {
    const char* op = "omniscape_torch::camera_grid";
    const Layout L = check_layout(op, face, pad, {0, 0, 0});
    const at::ScalarType dtype = check_cameras(op, affine, limits, table);
    const int64_t batch = affine.size(0);
    check_contiguous(op, "rotation", rotation);
    TORCH_CHECK(rotation.sizes() == at::IntArrayRef({batch, 3, 3}) &&
                    rotation.scalar_type() == dtype,
                op, ": rotation: expected (", batch, ", 3, 3) in ", dtype, ", got ",
                rotation.sizes(), " in ", rotation.scalar_type());
    check_camera_valid(op, valid, batch);
    check_camera_points(op, "grid", grid, valid, 2, dtype);
    const auto run = [&](auto g) {
        using G = decltype(g);
        radial_grid<G>(affine.const_data_ptr<G>(), limits.const_data_ptr<G>(),
                       table.const_data_ptr<G>(), table.size(2), table_batch(table),
                       rotation.const_data_ptr<G>(),
                       batch, valid.size(1), valid.size(2), L, grid.mutable_data_ptr<G>(),
                       nullptr, static_cast<uint8_t*>(valid.mutable_data_ptr()));
    };
    if (dtype == at::kFloat) {
        run(float{});
    } else {
        run(double{});
    }
}

// camera_rays: the camera-frame unit rays (B, H, W, 3) and validity (B, H, W) of B radially
// symmetric cameras (check_cameras, with their cones), in the cameras' dtype.
void camera_rays_op(const at::Tensor& affine, const at::Tensor& limits, const at::Tensor& table,
                    const at::Tensor& rays, const at::Tensor& valid) {
    const char* op = "omniscape_torch::camera_rays";
    const at::ScalarType dtype = check_cameras(op, affine, limits, table);
    const int64_t batch = affine.size(0);
    check_camera_valid(op, valid, batch);
    check_camera_points(op, "rays", rays, valid, 3, dtype);
    const auto run = [&](auto g) {
        using G = decltype(g);
        radial_grid<G>(affine.const_data_ptr<G>(), limits.const_data_ptr<G>(),
                       table.const_data_ptr<G>(), table.size(2), table_batch(table), nullptr,
                       batch, valid.size(1),
                       valid.size(2), Layout{}, nullptr, rays.mutable_data_ptr<G>(),
                       static_cast<uint8_t*>(valid.mutable_data_ptr()));
    };
    if (dtype == at::kFloat) {
        run(float{});
    } else {
        run(double{});
    }
}

// reproject_image: what RandomReproject's fast path runs per chunk of samples of a pinhole
// source, in one call: the rays and validity of radially symmetric cameras from their tables
// (camera_rays), the image sampled along them into out (sample_image, `bilinear`; its validity
// into valid_out), the pixels that minify antialiased (mip_image, where minifies > 0), and the
// labels (uint8 or int64 ids, may be absent) sampled nearest into out_labels (int64, `fill`
// outside). The same kernels and results as the four ops in turn, without their calls and
// wrappers in Python; the rays live in this call only.
void reproject_image_op(const std::optional<at::Tensor>& image,
                        const std::optional<at::Tensor>& labels, const at::Tensor& affine,
                        const at::Tensor& limits, const at::Tensor& table,
                        const at::Tensor& rotation, const at::Tensor& intrinsics, bool bilinear,
                        double minifies, int64_t fill, const std::optional<at::Tensor>& out,
                        const std::optional<at::Tensor>& out_labels,
                        const at::Tensor& valid_out) {
    const char* op = "omniscape_torch::reproject_image";
    TORCH_CHECK(image.has_value() == out.has_value() &&
                    labels.has_value() == out_labels.has_value() &&
                    (image.has_value() || labels.has_value()),
                op, ": expected image with out, labels with out_labels, one of them at least");
    const at::ScalarType dtype = check_cameras(op, affine, limits, table);
    check_camera_valid(op, valid_out, affine.size(0));
    const auto options = at::TensorOptions().dtype(dtype);
    const at::Tensor rays = at::empty({valid_out.size(0), valid_out.size(1), valid_out.size(2), 3},
                                      options);
    const at::Tensor valid = at::empty_like(valid_out);
    camera_rays_op(affine, limits, table, rays, valid);
    if (image.has_value()) {
        sample_image_op(*image, rays, rotation, intrinsics, valid, bilinear, 0, *out, valid_out);
        if (minifies > 0) {
            mip_image_op(*image, rays, rotation, intrinsics, valid_out, minifies, *out);
        }
    }
    if (labels.has_value()) {
        sample_image_op(labels->unsqueeze(1), rays, rotation, intrinsics, valid, false, fill,
                        out_labels->unsqueeze(1), image.has_value()
                                                      ? std::optional<at::Tensor>()
                                                      : std::optional<at::Tensor>(valid_out));
    }
}

// ------------------------------------------------------------------------------------------
// Boxes of objects in an image sampled along rays (detection): the pixels whose rays land in a
// source rectangle
// ------------------------------------------------------------------------------------------

// Whether the pixel `p` of one sample (ray p, rotated by r into the pinhole k, as
// locate_pinhole projects it) is valid and lands in the pixel-centre rectangle u0..u1, v0..v1.
template <typename G, bool Rotate>
inline bool lands_in(const G* __restrict rays, const G* r, const G* k, const uint8_t* valid,
                     int64_t p, G u0, G v0, G u1, G v1) {
    if (valid != nullptr && !valid[p]) {
        return false;
    }
    G px, py, pz;
    rotate<G, Rotate>(r, rays[3 * p], rays[3 * p + 1], rays[3 * p + 2], px, py, pz);
    if (!(pz > G(0))) {
        return false;
    }
    const G u = k[0] * (px / pz) + k[2], v = k[1] * (py / pz) + k[3];
    return (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1);
}

// The extent (min column, min row, max column, max row; -1 where none) of the pixels of the
// window c0..c1, r0..r1 (inclusive) of one sample `width` wide that land in the rectangle:
// the rows from the top and from the bottom to the first that holds one, then per row in
// between its columns from each side up to the extent found so far (about the window's
// perimeter for a convex object, its area at most).
template <typename G, bool Rotate>
void box_extent(const G* rays, const G* rot, const G* k, const uint8_t* valid, int64_t width,
                const int64_t* window, const double* rect, int64_t* out) {
    G r[9];
    if (Rotate) {
        std::copy(rot, rot + 9, r);
    }
    const G u0 = G(rect[0]), v0 = G(rect[1]), u1 = G(rect[2]), v1 = G(rect[3]);
    const int64_t c0 = window[0], r0 = window[1], c1 = window[2], r1 = window[3];
    const auto hit = [&](int64_t row, int64_t col) {
        return lands_in<G, Rotate>(rays, r, k, valid, row * width + col, u0, v0, u1, v1);
    };
    const auto row_holds = [&](int64_t row) {
        for (int64_t col = c0; col <= c1; ++col) {
            if (hit(row, col)) {
                return true;
            }
        }
        return false;
    };
    std::fill(out, out + 4, int64_t(-1));
    int64_t top = r0;
    while (top <= r1 && !row_holds(top)) {
        ++top;
    }
    if (top > r1) {
        return;
    }
    int64_t bottom = r1;
    while (bottom > top && !row_holds(bottom)) {
        --bottom;
    }
    int64_t left = c1 + 1, right = c0 - 1;
    for (int64_t row = top; row <= bottom; ++row) {
        for (int64_t col = c0; col < left; ++col) {
            if (hit(row, col)) {
                left = col;
                break;
            }
        }
        for (int64_t col = c1; col > right; --col) {
            if (hit(row, col)) {
                right = col;
                break;
            }
        }
    }
    out[0] = left;
    out[1] = top;
    out[2] = right;
    out[3] = bottom;
}

// box_pixels: for each box m, the extent (int64 (M, 4): min column, min row, max column, max
// row, -1 where none) of the pixels of sample[m] within windows[m] (c0, r0, c1, r1, inclusive)
// whose rays (n, h, w, 3), rotated by rotation (n, 3, 3, or none) into the pinhole intrinsics
// (1 or n, 4) as sample_image projects them, are valid (n, h, w, or none) and land in the
// source pixel-centre rectangle rects[m] (float64 u0, v0, u1, v1).
void box_pixels_op(const at::Tensor& rays, const std::optional<at::Tensor>& rotation,
                   const at::Tensor& intrinsics, const std::optional<at::Tensor>& valid,
                   const at::Tensor& sample, const at::Tensor& windows, const at::Tensor& rects,
                   const at::Tensor& out) {
    const char* op = "omniscape_torch::box_pixels";
    for (const auto& [name, t] : {std::pair<const char*, const at::Tensor*>{"rays", &rays},
                                  {"intrinsics", &intrinsics}, {"sample", &sample},
                                  {"windows", &windows}, {"rects", &rects}, {"out", &out}}) {
        check_cpu(op, name, *t);
        check_contiguous(op, name, *t);
    }
    const at::ScalarType dtype = rays.scalar_type();
    TORCH_CHECK((dtype == at::kFloat || dtype == at::kDouble) && rays.dim() == 4 &&
                    rays.size(3) == 3, op, ": rays: expected float32 or float64 (n, h, w, 3), got ",
                rays.scalar_type(), " ", rays.sizes());
    const int64_t n = rays.size(0), height = rays.size(1), width = rays.size(2);
    TORCH_CHECK(intrinsics.scalar_type() == dtype && intrinsics.dim() == 2 &&
                    intrinsics.size(1) == 4 && (intrinsics.size(0) == 1 || intrinsics.size(0) == n),
                op, ": intrinsics: expected (1 or n, 4) in the rays' dtype, got ",
                intrinsics.sizes());
    if (rotation.has_value()) {
        check_cpu(op, "rotation", *rotation);
        check_contiguous(op, "rotation", *rotation);
        TORCH_CHECK(rotation->scalar_type() == dtype &&
                        rotation->sizes() == at::IntArrayRef({n, 3, 3}),
                    op, ": rotation: expected (n, 3, 3) in the rays' dtype, got ",
                    rotation->sizes());
    }
    if (valid.has_value()) {
        check_cpu(op, "valid", *valid);
        check_contiguous(op, "valid", *valid);
        TORCH_CHECK(valid->scalar_type() == at::kBool &&
                        valid->sizes() == at::IntArrayRef({n, height, width}),
                    op, ": valid: expected bool (n, h, w), got ", valid->sizes());
    }
    const int64_t boxes = sample.size(0);
    TORCH_CHECK(sample.scalar_type() == at::kLong && sample.dim() == 1 &&
                    windows.scalar_type() == at::kLong &&
                    windows.sizes() == at::IntArrayRef({boxes, 4}) &&
                    rects.scalar_type() == at::kDouble &&
                    rects.sizes() == at::IntArrayRef({boxes, 4}) &&
                    out.scalar_type() == at::kLong && out.sizes() == at::IntArrayRef({boxes, 4}),
                op, ": expected sample int64 (M,), windows int64, rects float64 and out int64 "
                "(M, 4)");
    const int64_t* s = sample.const_data_ptr<int64_t>();
    const int64_t* win = windows.const_data_ptr<int64_t>();
    for (int64_t m = 0; m < boxes; ++m) {
        const int64_t* w = win + 4 * m;
        TORCH_CHECK(s[m] >= 0 && s[m] < n && w[0] >= 0 && w[1] >= 0 && w[2] < width &&
                        w[3] < height,
                    op, ": box ", m, ": sample or window outside the rays (n, h, w) = (", n,
                    ", ", height, ", ", width, ")");
    }
    const uint8_t* ok = mask(valid);
    const auto run = [&](auto g) {
        using G = decltype(g);
        const G* ray = rays.const_data_ptr<G>();
        const G* rot = rotation.has_value() ? rotation->const_data_ptr<G>() : nullptr;
        const G* k = intrinsics.const_data_ptr<G>();
        const int64_t k_batch = intrinsics.size(0) == 1 ? 0 : 4;
        at::parallel_for(0, boxes, 1, [&](int64_t lo, int64_t hi) {
            for (int64_t m = lo; m < hi; ++m) {
                const int64_t b = s[m];
                const G* r = ray + b * height * width * 3;
                const uint8_t* v = ok == nullptr ? nullptr : ok + b * height * width;
                int64_t* o = out.mutable_data_ptr<int64_t>() + 4 * m;
                if (rot != nullptr) {
                    box_extent<G, true>(r, rot + 9 * b, k + k_batch * b, v, width, win + 4 * m,
                                        rects.const_data_ptr<double>() + 4 * m, o);
                } else {
                    box_extent<G, false>(r, nullptr, k + k_batch * b, v, width, win + 4 * m,
                                         rects.const_data_ptr<double>() + 4 * m, o);
                }
            }
        });
    };
    if (dtype == at::kFloat) {
        run(float{});
    } else {
        run(double{});
    }
}

// The outlines of boxes laid out in rows, one per sample (detection): box m (of sample
// owner[m], the owners sorted) has 4 counts[m] points, counts[m] per edge, in its sample's row
// after `offset` columns and the points of the sample's boxes before it.
void check_outlines(const char* op, const at::Tensor& counts, const at::Tensor& owner,
                    int64_t offset, int64_t rows, int64_t columns) {
    for (const auto& [name, t] : {std::pair<const char*, const at::Tensor*>{"counts", &counts},
                                  {"owner", &owner}}) {
        check_cpu(op, name, *t);
        check_contiguous(op, name, *t);
        TORCH_CHECK(t->scalar_type() == at::kLong && t->dim() == 1 &&
                        t->size(0) == counts.size(0),
                    op, ": counts, owner: expected int64 (M,)");
    }
    const int64_t* c = counts.const_data_ptr<int64_t>();
    const int64_t* o = owner.const_data_ptr<int64_t>();
    int64_t row = -1, used = 0;
    for (int64_t m = 0; m < counts.size(0); ++m) {
        TORCH_CHECK(c[m] >= 1 && o[m] >= 0 && o[m] < rows && o[m] >= row, op,
                    ": box ", m, ": counts must be positive and owners sorted within 0..",
                    rows - 1);
        used = o[m] == row ? used : offset;
        row = o[m];
        used += 4 * c[m];
        TORCH_CHECK(used <= columns, op, ": the outlines of sample ", row, " exceed ", columns,
                    " columns");
    }
}

// outline_points: the outlines of rects (M, 4) float64 (x0, y0, x1, y1), laid out as
// check_outlines says, into points (n, columns, 2) float64: edge e (top, right, bottom, left)
// from its corner to the next, point t at t / counts[m] of the way.
void outline_points_op(const at::Tensor& rects, const at::Tensor& counts,
                       const at::Tensor& owner, int64_t offset, const at::Tensor& points) {
    const char* op = "omniscape_torch::outline_points";
    check_cpu(op, "rects", rects);
    check_contiguous(op, "rects", rects);
    check_cpu(op, "points", points);
    check_contiguous(op, "points", points);
    TORCH_CHECK(rects.scalar_type() == at::kDouble &&
                    rects.sizes() == at::IntArrayRef({counts.size(0), 4}) &&
                    points.scalar_type() == at::kDouble && points.dim() == 3 &&
                    points.size(2) == 2,
                op, ": expected rects float64 (M, 4) and points float64 (n, columns, 2)");
    check_outlines(op, counts, owner, offset, points.size(0), points.size(1));
    const int64_t* c = counts.const_data_ptr<int64_t>();
    const int64_t* o = owner.const_data_ptr<int64_t>();
    const double* r = rects.const_data_ptr<double>();
    double* out = points.mutable_data_ptr<double>();
    const int64_t columns = points.size(1);
    int64_t row = -1, at = 0;
    for (int64_t m = 0; m < counts.size(0); ++m) {
        at = o[m] == row ? at : offset;
        row = o[m];
        const double x0 = r[4 * m], y0 = r[4 * m + 1], x1 = r[4 * m + 2], y1 = r[4 * m + 3];
        const double xs[5] = {x0, x1, x1, x0, x0}, ys[5] = {y0, y0, y1, y1, y0};
        double* p = out + 2 * (row * columns + at);
        for (int e = 0; e < 4; ++e) {
            for (int64_t t = 0; t < c[m]; ++t) {
                const double f = double(t) / double(c[m]);
                p[0] = xs[e] + f * (xs[e + 1] - xs[e]);
                p[1] = ys[e] + f * (ys[e + 1] - ys[e]);
                p += 2;
            }
        }
        at += 4 * c[m];
    }
}

// outline_reduce: per box m, its outline points laid out as check_outlines says (output pixels
// pix (n, columns, 2) float64, where seen `ok` and where both models map them `through`,
// (n, columns) bool) -> extents (M, 8): the extent x0, y0, x1, y1 of its seen points within
// the outer pixel centres [0, width - 1] x [0, height - 1] (inf, -inf where none), then of
// its mapped points; longest (M,): the longest step between two consecutive mapped points of
// its closed outline of which one lies within `near` pixels of those centres; flags (M,): 1
// where a point is not seen within the centres, 2 where a point is not mapped.
void outline_reduce_op(const at::Tensor& pix, const at::Tensor& ok, const at::Tensor& through,
                       const at::Tensor& counts, const at::Tensor& owner, int64_t offset,
                       int64_t width, int64_t height, double near, const at::Tensor& extents,
                       const at::Tensor& longest, const at::Tensor& flags) {
    const char* op = "omniscape_torch::outline_reduce";
    for (const auto& [name, t] : {std::pair<const char*, const at::Tensor*>{"pix", &pix},
                                  {"ok", &ok}, {"through", &through}, {"extents", &extents},
                                  {"longest", &longest}, {"flags", &flags}}) {
        check_cpu(op, name, *t);
        check_contiguous(op, name, *t);
    }
    const int64_t boxes = counts.size(0);
    TORCH_CHECK(pix.scalar_type() == at::kDouble && pix.dim() == 3 && pix.size(2) == 2 &&
                    ok.scalar_type() == at::kBool && through.scalar_type() == at::kBool &&
                    ok.sizes() == pix.sizes().slice(0, 2) &&
                    through.sizes() == pix.sizes().slice(0, 2) &&
                    extents.scalar_type() == at::kDouble &&
                    extents.sizes() == at::IntArrayRef({boxes, 8}) &&
                    longest.scalar_type() == at::kDouble &&
                    longest.sizes() == at::IntArrayRef({boxes}) &&
                    flags.scalar_type() == at::kLong && flags.sizes() == at::IntArrayRef({boxes}),
                op, ": expected pix float64 (n, columns, 2), ok and through bool (n, columns), "
                "extents float64 (M, 8), longest float64 (M,) and flags int64 (M,)");
    check_outlines(op, counts, owner, offset, pix.size(0), pix.size(1));
    const int64_t* c = counts.const_data_ptr<int64_t>();
    const int64_t* o = owner.const_data_ptr<int64_t>();
    const int64_t columns = pix.size(1);
    const double* p = pix.const_data_ptr<double>();
    const bool* seen = ok.const_data_ptr<bool>();
    const bool* mapped = through.const_data_ptr<bool>();
    double* e = extents.mutable_data_ptr<double>();
    double* l = longest.mutable_data_ptr<double>();
    int64_t* f = flags.mutable_data_ptr<int64_t>();
    const double inf = std::numeric_limits<double>::infinity();
    const double right = double(width - 1), bottom = double(height - 1);
    const auto centred = [&](int64_t i) {
        const double u = p[2 * i], v = p[2 * i + 1];
        return (u >= -1e-9) & (u <= right + 1e-9) & (v >= -1e-9) & (v <= bottom + 1e-9);
    };
    const auto close = [&](int64_t i) {
        const double u = p[2 * i], v = p[2 * i + 1];
        return (u > -near) & (u < right + near) & (v > -near) & (v < bottom + near);
    };
    int64_t row = -1, at = 0;
    for (int64_t m = 0; m < boxes; ++m) {
        at = o[m] == row ? at : offset;
        row = o[m];
        const int64_t start = row * columns + at, end = start + 4 * c[m];
        at += 4 * c[m];
        double* box = e + 8 * m;
        for (int k = 0; k < 2; ++k) {
            box[4 * k] = box[4 * k + 1] = inf;
            box[4 * k + 2] = box[4 * k + 3] = -inf;
        }
        double step = 0.0;
        int64_t flag = 0;
        for (int64_t i = start; i < end; ++i) {
            const double u = p[2 * i], v = p[2 * i + 1];
            if (seen[i] && centred(i)) {
                box[0] = std::min(box[0], u);
                box[1] = std::min(box[1], v);
                box[2] = std::max(box[2], u);
                box[3] = std::max(box[3], v);
            } else {
                flag |= 1;
            }
            if (!mapped[i]) {
                flag |= 2;
                continue;
            }
            box[4] = std::min(box[4], u);
            box[5] = std::min(box[5], v);
            box[6] = std::max(box[6], u);
            box[7] = std::max(box[7], v);
            const int64_t j = i + 1 < end ? i + 1 : start;   // the outline is closed
            if (mapped[j] && (close(i) || close(j))) {
                step = std::max(step, std::hypot(p[2 * j] - u, p[2 * j + 1] - v));
            }
        }
        l[m] = step;
        f[m] = flag;
    }
}

// ------------------------------------------------------------------------------------------
// Framing (render/framing.py, its NumPy functions reach and focal_for_coverage, per sample in
// one call: a few samples' NumPy calls cost ~10x these loops)
// ------------------------------------------------------------------------------------------

// Tensors of framing: float64, contiguous, of the given shape.
void check_framing(const char* op, const char* name, const at::Tensor& t, at::IntArrayRef shape) {
    check_contiguous(op, name, t);
    TORCH_CHECK(t.scalar_type() == at::kDouble && t.sizes() == shape, op, ": ", name,
                ": expected float64 ", shape, ", got ", t.scalar_type(), " ", t.sizes());
}

// The reach of one sample (framing_reach): theta[0, d) of the fisheye turned by r (3 x 3,
// row-major) onto the pinhole k (fx, fy, cx, cy) of height x width pixels, at most half.
void reach_one(const double* r, const double* k, double half, const double* C, const double* S,
               int64_t d, int64_t height, int64_t width, double* t) {
    const double offset[4] = {double(width) - 0.5, 0.5, double(height) - 0.5, 0.5};
    const double sign[4] = {1.0, -1.0, 1.0, -1.0};
    const double nxy[5][2] = {{1, 0}, {-1, 0}, {0, 1}, {0, -1}, {0, 0}};
    double x[5], y[5], a[5];
    bool inside = true;
    for (int j = 0; j < 5; ++j) {
        // the plane's normal (framing._normals), then in the fisheye's frame (m = n R)
        const double nz = j < 4 ? (sign[j] * k[j < 2 ? 2 : 3] - offset[j]) / k[j < 2 ? 0 : 1]
                                : -1.0;
        const double m[3] = {nxy[j][0], nxy[j][1], nz};
        double v[3];
        for (int c = 0; c < 3; ++c) {
            v[c] = m[0] * r[c] + m[1] * r[3 + c] + m[2] * r[6 + c];
        }
        x[j] = v[0];
        y[j] = v[1];
        a[j] = v[2];
        inside = inside && a[j] < 0;
    }
    if (!inside) {
        std::fill(t, t + d, std::min(0.0, half));
        return;
    }
    for (int j = 0; j < 5; ++j) {
        const double scale = -1 / a[j];
        x[j] *= scale;
        y[j] *= scale;
    }
    for (int64_t i = 0; i < d; ++i) {
        double ratio = x[0] * C[i] + y[0] * S[i];
        for (int j = 1; j < 5; ++j) {
            ratio = std::max(ratio, x[j] * C[i] + y[j] * S[i]);
        }
        t[i] = std::min(std::atan2(1.0, ratio), half);
    }
}

// The focal of one sample (framing_focal): the radius r[0, D) at focal 1 and the output's
// edge e[0, D) in each direction, the share `coverage`; its buffers kept between samples.
struct FocalSolver {
    int64_t d;
    double norm;
    std::vector<double> clipped, free;
    std::vector<std::pair<double, int64_t>> order;   // (break, direction), sorted

    FocalSolver(int64_t d, int64_t height, int64_t width)
        : d(d), norm(M_PI / (double(d) * double(height) * double(width))), clipped(d + 1),
          free(d + 1), order(d) {}

    double operator()(const double* r, const double* e, double coverage) {
        const double inf = std::numeric_limits<double>::infinity();
        for (int64_t i = 0; i < d; ++i) {
            order[i] = {r[i] > 0 ? e[i] / r[i] : inf, i};
        }
        std::sort(order.begin(), order.end());
        clipped[0] = 0.0;
        for (int64_t i = 0; i < d; ++i) {
            const double ei = e[order[i].second];
            clipped[i + 1] = clipped[i] + ei * ei;
        }
        free[d] = 0.0;
        for (int64_t i = d - 1; i >= 0; --i) {
            const double ri = r[order[i].second];
            free[i] = free[i + 1] + ri * ri;
        }
        int64_t piece = 0;
        double widest = 0.0;
        for (int64_t i = 0; i < d; ++i) {
            const bool finite = r[order[i].second] > 0;
            const double end = finite ? order[i].first : 0.0;
            widest = std::max(widest, end);
            const double at_break = finite ? norm * (clipped[i] + end * end * free[i]) : inf;
            piece += at_break < coverage;
        }
        const double c = clipped[piece], u = free[piece];
        const double f = std::sqrt(std::max((coverage / norm - c) / std::max(u, 1e-300), 0.0));
        return u > 0 ? f : widest;
    }
};

// framing_reach: theta (n, D), along each direction (cos, sin (D,)) about the fisheye's centre
// the angle from its axis out to which its rays (ray_src = R ray, rotation (n, 3, 3)) reach the
// pinhole image (intrinsics (n, 4) fx, fy, cx, cy; height x width pixels, edges at -0.5 and
// W - 0.5), at most half (n,); 0 where the axis misses the image. framing.reach's arithmetic.
void framing_reach_op(const at::Tensor& rotation, const at::Tensor& intrinsics,
                      const at::Tensor& half, const at::Tensor& cos, const at::Tensor& sin,
                      int64_t height, int64_t width, const at::Tensor& theta) {
    const char* op = "omniscape_torch::framing_reach";
    const int64_t n = half.dim() == 1 ? half.size(0) : -1, d = cos.numel();
    check_framing(op, "half", half, {n});
    check_framing(op, "rotation", rotation, {n, 3, 3});
    check_framing(op, "intrinsics", intrinsics, {n, 4});
    check_framing(op, "cos", cos, {d});
    check_framing(op, "sin", sin, {d});
    check_framing(op, "theta", theta, {n, d});
    for (int64_t b = 0; b < n; ++b) {
        reach_one(rotation.const_data_ptr<double>() + 9 * b,
                  intrinsics.const_data_ptr<double>() + 4 * b, half.const_data_ptr<double>()[b],
                  cos.const_data_ptr<double>(), sin.const_data_ptr<double>(), d, height, width,
                  theta.mutable_data_ptr<double>() + d * b);
    }
}

// framing_focal: focal (n,) at which sum_d min(f radius, to_edge)^2 pi / (D H W) (the valid
// share) equals coverage (n,): radius (n, D), to_edge (n or 1, D). framing.focal_for_coverage's
// arithmetic (the pieces between the sorted focals where a direction reaches the edge).
void framing_focal_op(const at::Tensor& radius, const at::Tensor& to_edge,
                      const at::Tensor& coverage, int64_t height, int64_t width,
                      const at::Tensor& focal) {
    const char* op = "omniscape_torch::framing_focal";
    const int64_t n = coverage.dim() == 1 ? coverage.size(0) : -1;
    const int64_t d = radius.dim() == 2 ? radius.size(1) : -1;
    check_framing(op, "coverage", coverage, {n});
    check_framing(op, "radius", radius, {n, d});
    check_framing(op, "to_edge", to_edge, {to_edge.dim() == 2 && to_edge.size(0) == 1 ? 1 : n, d});
    check_framing(op, "focal", focal, {n});
    TORCH_CHECK(d >= 1 && height >= 1 && width >= 1, op, ": expected D >= 1 directions and an "
                "output of 1 pixel or more, got ", d, " and ", height, " x ", width);
    const int64_t edge_batch = to_edge.size(0) == 1 ? 0 : d;
    FocalSolver solve(d, height, width);
    for (int64_t b = 0; b < n; ++b) {
        focal.mutable_data_ptr<double>()[b] =
            solve(radius.const_data_ptr<double>() + d * b,
                  to_edge.const_data_ptr<double>() + edge_batch * b,
                  coverage.const_data_ptr<double>()[b]);
    }
}

// frame_lens: RandomReproject's draw of n fisheyes of one lens with a radius table, framed to
// pinhole sources, in one call (RandomReproject._draw_params' arithmetic, per sample): from the
// uniforms u (16 n: the families of _draw_params, in its order) and spec (11,) = the ranges
// (lo, hi) of fov, yaw, pitch, roll and coverage, then p: fov (n,), attitude (3, n) (yaw, pitch,
// roll; 0 where applied (n,) is false: u >= p), coverage (n,), the rotations (n, 3, 3)
// (presets.rotation_rows' entries, in its order of operations), then framing_reach onto
// intrinsics (n, 4) of src_height x src_width pixels, the lens radius at focal 1 at those angles
// (radius (A,) at j / per_angle, slope (A,) to the next: _UnitLens.radius_at's interpolation)
// and framing_focal against to_edge (1 or n, D): params (n, P) rows (f, f, centre (1 or n, 2)),
// the rest left as they are.
void frame_lens_op(const at::Tensor& u, const at::Tensor& spec, const at::Tensor& intrinsics,
                   const at::Tensor& centre, const at::Tensor& cos, const at::Tensor& sin,
                   int64_t src_height, int64_t src_width, const at::Tensor& radius,
                   const at::Tensor& slope, double per_angle, const at::Tensor& to_edge,
                   int64_t height, int64_t width, const at::Tensor& params,
                   const at::Tensor& fov, const at::Tensor& attitude, const at::Tensor& applied,
                   const at::Tensor& rotation, const at::Tensor& coverage) {
    const char* op = "omniscape_torch::frame_lens";
    const int64_t n = fov.dim() == 1 ? fov.size(0) : -1, d = cos.numel();
    const int64_t entries = radius.numel();
    check_framing(op, "u", u, {16 * n});
    check_framing(op, "spec", spec, {11});
    check_framing(op, "intrinsics", intrinsics, {n, 4});
    check_framing(op, "centre", centre, {centre.dim() == 2 && centre.size(0) == 1 ? 1 : n, 2});
    check_framing(op, "cos", cos, {d});
    check_framing(op, "sin", sin, {d});
    check_framing(op, "radius", radius, {entries});
    check_framing(op, "slope", slope, {entries});
    check_framing(op, "to_edge", to_edge, {to_edge.dim() == 2 && to_edge.size(0) == 1 ? 1 : n, d});
    check_framing(op, "params", params, {n, params.dim() == 2 ? params.size(1) : -1});
    check_framing(op, "fov", fov, {n});
    check_framing(op, "attitude", attitude, {3, n});
    check_framing(op, "rotation", rotation, {n, 3, 3});
    check_framing(op, "coverage", coverage, {n});
    check_contiguous(op, "applied", applied);
    TORCH_CHECK(applied.scalar_type() == at::kBool && applied.sizes() == at::IntArrayRef({n}),
                op, ": applied: expected bool (", n, "), got ", applied.scalar_type(), " ",
                applied.sizes());
    TORCH_CHECK(d >= 1 && entries >= 2 && params.size(1) >= 4 && height >= 1 && width >= 1, op,
                ": expected D >= 1 directions, a table of 2 entries or more, params of 4 or "
                "more and an output of 1 pixel or more, got ", d, ", ", entries, ", ",
                params.size(1), " and ", height, " x ", width);
    const double* U = u.const_data_ptr<double>();
    const double* sp_ = spec.const_data_ptr<double>();
    const double* tab = radius.const_data_ptr<double>();
    const double* step = slope.const_data_ptr<double>();
    const int64_t edge_batch = to_edge.size(0) == 1 ? 0 : d;
    const int64_t centre_batch = centre.size(0) == 1 ? 0 : 2;
    const auto scaled = [&](int range, double value) {   // _scaled: lo + (hi - lo) u
        return sp_[2 * range] + (sp_[2 * range + 1] - sp_[2 * range]) * value;
    };
    std::vector<double> r(d);
    FocalSolver solve(d, height, width);
    for (int64_t b = 0; b < n; ++b) {
        const double f = scaled(0, U[n + b]);
        const bool on = U[14 * n + b] < sp_[10];
        double angle[3], c[3], s[3];
        for (int k = 0; k < 3; ++k) {
            angle[k] = on ? scaled(1 + k, U[11 * n + k * n + b]) : 0.0;
            c[k] = std::cos(angle[k]);
            s[k] = std::sin(angle[k]);
            attitude.mutable_data_ptr<double>()[k * n + b] = angle[k];
        }
        const double cov = scaled(4, U[15 * n + b]);
        fov.mutable_data_ptr<double>()[b] = f;
        applied.mutable_data_ptr<bool>()[b] = on;
        coverage.mutable_data_ptr<double>()[b] = cov;
        const double cy = c[0], sy = s[0], cp = c[1], sp = s[1], cr = c[2], sr = s[2];
        double* R = rotation.mutable_data_ptr<double>() + 9 * b;
        const double entries_[9] = {cy * cr + sy * sp * sr, sy * sp * cr - cy * sr, sy * cp,
                                    cp * sr, cp * cr, -sp,
                                    cy * sp * sr - sy * cr, sy * sr + cy * sp * cr, cy * cp};
        std::copy(entries_, entries_ + 9, R);
        reach_one(R, intrinsics.const_data_ptr<double>() + 4 * b, 0.5 * f,
                  cos.const_data_ptr<double>(), sin.const_data_ptr<double>(), d, src_height,
                  src_width, r.data());
        for (int64_t i = 0; i < d; ++i) {   // the angle -> the radius at focal 1
            const double at = r[i] * per_angle;
            const int64_t j = std::min(static_cast<int64_t>(at), entries - 2);
            r[i] = tab[j] + (at - double(j)) * step[j];
        }
        const double focal = solve(r.data(), to_edge.const_data_ptr<double>() + edge_batch * b,
                                   cov);
        double* row = params.mutable_data_ptr<double>() + params.size(1) * b;
        const double* ctr = centre.const_data_ptr<double>() + centre_batch * b;
        row[0] = row[1] = focal;
        row[2] = ctr[0];
        row[3] = ctr[1];
    }
}

}  // namespace

TORCH_LIBRARY_IMPL(omniscape_torch, CPU, m) {
    m.impl("camera_grid", &camera_grid_op);
    m.impl("camera_rays", &camera_rays_op);
    m.impl("sample_image", &sample_image_op);
    m.impl("box_pixels", &box_pixels_op);
    m.impl("outline_points", &outline_points_op);
    m.impl("outline_reduce", &outline_reduce_op);
    m.impl("mip_image", &mip_image_op);
    m.impl("reproject_image", &reproject_image_op);
    m.impl("framing_reach", &framing_reach_op);
    m.impl("framing_focal", &framing_focal_op);
    m.impl("frame_lens", &frame_lens_op);
}
