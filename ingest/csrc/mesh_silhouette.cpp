// Mesh silhouette by depth buffer: the ingest mask rule "one ray through each pixel centre; the pixel is in
// when the first face the ray hits is not a neck face", evaluated per face over the pixel centres its
// projection covers instead of per ray. For a pinhole camera and faces in front of it, a ray hits a face
// exactly when the pixel centre lies in the face's projection, and the hit's distance along the ray is
// proportional to its camera depth, so the nearest face by depth is the ray's first hit. Depths come from
// each face's plane (exact, not interpolated), all in double precision. Faces are not culled by facing:
// rays see back faces too (e.g. through the open neck).

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <vector>

namespace py = pybind11;

namespace {

using DoubleArray = py::array_t<double, py::array::c_style | py::array::forcecast>;
using IndexArray = py::array_t<int64_t, py::array::c_style | py::array::forcecast>;
using FlagArray = py::array_t<uint8_t, py::array::c_style | py::array::forcecast>;

struct Pinhole {
    double fx, fy, cx, cy;
};

// Signed doubled area of (a, b, p): > 0 when p is left of a -> b in pixel coordinates.
inline double edge(double ax, double ay, double bx, double by, double px, double py) {
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax);
}

// An affine function of the pixel centre, value = du * u + dv * v + c.
struct Affine {
    double du, dv, c;
};

// The edge function of a -> b as an affine function, scaled by sign (so that inside is >= 0).
inline Affine edge_affine(double ax, double ay, double bx, double by, double sign) {
    return {-sign * (by - ay), sign * (bx - ax), sign * ((by - ay) * ax - (bx - ax) * ay)};
}

// Depth-tests one face over the pixel centres of its projection; inverse_depth and label (H*W) are updated.
//   p0..p2: the corners in camera coordinates; q0..q2: their pixels (x, y).
void draw_face(const double* p0, const double* p1, const double* p2, const double* q0, const double* q1,
               const double* q2, uint8_t face_label, const Pinhole& cam, int64_t width, int64_t height,
               double* inverse_depth, uint8_t* label) {
    const double x0 = q0[0], y0 = q0[1], x1 = q1[0], y1 = q1[1], x2 = q2[0], y2 = q2[1];
    const double area = edge(x0, y0, x1, y1, x2, y2);
    if (area == 0.0 || !std::isfinite(area)) return;  // seen edge-on: no ray hits its inside
    const double lo_x = std::max(std::ceil(std::min({x0, x1, x2})), 0.0);
    const double hi_x = std::min(std::floor(std::max({x0, x1, x2})), static_cast<double>(width - 1));
    const double lo_y = std::max(std::ceil(std::min({y0, y1, y2})), 0.0);
    const double hi_y = std::min(std::floor(std::max({y0, y1, y2})), static_cast<double>(height - 1));
    if (lo_x > hi_x || lo_y > hi_y) return;
    const double sign = area > 0.0 ? 1.0 : -1.0;
    const Affine e0 = edge_affine(x1, y1, x2, y2, sign), e1 = edge_affine(x2, y2, x0, y0, sign),
                 e2 = edge_affine(x0, y0, x1, y1, sign);
    // Plane n . P = n . p0 in camera space. The ray of pixel (u, v) is t ((u - cx) / fx, (v - cy) / fy, 1),
    // so the inverse of the hit's depth, (n_x (u - cx) / fx + n_y (v - cy) / fy + n_z) / (n . p0), is affine
    // in (u, v): the nearest hit has the largest inverse depth, found without a division per pixel.
    const double a[3] = {p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]};
    const double b[3] = {p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]};
    const double n[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
    const double offset = n[0] * p0[0] + n[1] * p0[1] + n[2] * p0[2];
    if (offset == 0.0) return;  // the plane passes through the camera centre: seen edge-on
    const Affine w = {n[0] / (cam.fx * offset), n[1] / (cam.fy * offset),
                      (n[2] - n[0] * cam.cx / cam.fx - n[1] * cam.cy / cam.fy) / offset};
    const Affine edges[3] = {e0, e1, e2};
    // -1 / du of each edge, so that a row's bounds cost no division (the exact test below has the last word).
    double step[3];
    for (int k = 0; k < 3; ++k) step[k] = edges[k].du != 0.0 ? -1.0 / edges[k].du : 0.0;
    const int64_t u_lo = static_cast<int64_t>(lo_x), u_hi = static_cast<int64_t>(hi_x);
    for (int64_t v = static_cast<int64_t>(lo_y); v <= static_cast<int64_t>(hi_y); ++v) {
        const double pv = static_cast<double>(v);
        const double row[3] = {e0.dv * pv + e0.c, e1.dv * pv + e1.c, e2.dv * pv + e2.c};
        const auto inside = [&](int64_t u) {
            const double pu = static_cast<double>(u);
            // Pixel centres on an edge count as inside, like a watertight ray test that reports the hit.
            return edges[0].du * pu + row[0] >= 0.0 && edges[1].du * pu + row[1] >= 0.0 &&
                   edges[2].du * pu + row[2] >= 0.0;
        };
        // The row's span from the three half-lines, then nudged so that its ends pass the exact test above.
        double span_lo = lo_x, span_hi = hi_x;
        for (int k = 0; k < 3; ++k) {
            if (edges[k].du > 0.0) span_lo = std::max(span_lo, std::ceil(row[k] * step[k]));
            else if (edges[k].du < 0.0) span_hi = std::min(span_hi, std::floor(row[k] * step[k]));
            else if (row[k] < 0.0) span_lo = std::numeric_limits<double>::infinity();
        }
        if (!(span_lo <= span_hi + 2.0)) continue;  // also skips NaN bounds
        int64_t first = std::max(static_cast<int64_t>(span_lo) - 1, u_lo);
        int64_t last = std::min(static_cast<int64_t>(span_hi) + 1, u_hi);
        while (first <= last && !inside(first)) ++first;
        while (last >= first && !inside(last)) --last;
        const double rw = w.dv * pv + w.c;
        double* row_depth = inverse_depth + v * width;
        uint8_t* row_label = label + v * width;
        for (int64_t u = first; u <= last; ++u) {
            const double inverse = w.du * static_cast<double>(u) + rw;
            if (inverse > row_depth[u]) {  // > 0: in front of the camera, and nearer than what is there
                row_depth[u] = inverse;
                row_label[u] = face_label;
            }
        }
    }
}

// (H, W) uint8: 1 where the nearest face along the pixel centre's ray is not excluded, else 0.
//   camera_points: (V, 3) vertices in camera coordinates, every z > 0 (the caller checks).
//   faces: (F, 3) vertex indices; excluded: (F,) 1 for faces whose hits leave the pixel out.
py::array_t<uint8_t> first_hit_mask(DoubleArray camera_points, IndexArray faces, FlagArray excluded, double fx,
                                    double fy, double cx, double cy, int64_t width, int64_t height) {
    if (camera_points.ndim() != 2 || camera_points.shape(1) != 3)
        throw std::invalid_argument("camera_points must be (V, 3)");
    if (faces.ndim() != 2 || faces.shape(1) != 3) throw std::invalid_argument("faces must be (F, 3)");
    if (excluded.ndim() != 1 || excluded.shape(0) != faces.shape(0))
        throw std::invalid_argument("excluded must be (F,)");
    if (width <= 0 || height <= 0) throw std::invalid_argument("width and height must be positive");
    const int64_t vertex_count = camera_points.shape(0), face_count = faces.shape(0);
    const double* points = camera_points.data();
    const int64_t* index = faces.data();
    const uint8_t* skip = excluded.data();
    for (int64_t i = 0; i < 3 * face_count; ++i)
        if (index[i] < 0 || index[i] >= vertex_count) throw std::invalid_argument("faces index missing vertices");
    py::array_t<uint8_t> mask({height, width});
    uint8_t* out = mask.mutable_data();
    {
        py::gil_scoped_release release;
        std::vector<double> inverse_depth(static_cast<size_t>(width * height), 0.0);  // 0: nothing hit
        std::vector<uint8_t> label(static_cast<size_t>(width * height), 0);  // 0 no hit, 1 kept, 2 excluded
        const Pinhole cam{fx, fy, cx, cy};
        std::vector<double> pixels(static_cast<size_t>(2 * vertex_count));  // each vertex projected once
        for (int64_t i = 0; i < vertex_count; ++i) {
            const double* p = points + 3 * i;
            pixels[2 * i] = fx * p[0] / p[2] + cx;
            pixels[2 * i + 1] = fy * p[1] / p[2] + cy;
        }
        const double* q = pixels.data();
        for (int64_t f = 0; f < face_count; ++f) {
            const int64_t* tri = index + 3 * f;
            draw_face(points + 3 * tri[0], points + 3 * tri[1], points + 3 * tri[2], q + 2 * tri[0], q + 2 * tri[1],
                      q + 2 * tri[2], skip[f] ? 2 : 1, cam, width, height, inverse_depth.data(), label.data());
        }
        for (int64_t i = 0; i < width * height; ++i) out[i] = label[i] == 1;
    }
    return mask;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "Mesh silhouettes by depth buffer (the ingest mask rule)";
    m.def("first_hit_mask", &first_hit_mask, py::arg("camera_points"), py::arg("faces"), py::arg("excluded"),
          py::arg("fx"), py::arg("fy"), py::arg("cx"), py::arg("cy"), py::arg("width"), py::arg("height"));
}
