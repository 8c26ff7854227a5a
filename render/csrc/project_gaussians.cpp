// EWA projection of 3D Gaussians into pinhole cameras on the CPU, forward and exact backward, one fused pass
// per Gaussian (OpenMP over Gaussians, cameras in a fixed order inside, so sums never depend on the thread
// count). Same arithmetic as project_gaussians in render/rasterize_torch.py (gsplat 1.5.3's
// fully_fused_projection with pixel centres at integer coordinates):
//
//   p = R m + t, J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] with x/z, y/z clamped to 1.3x the field of
//   view, A = J R_w Rot(q) diag(s) (2x3), cov2d = A A^T, conic = (cov2d + eps2d I)^-1, compensation
//   sqrt(det cov2d / det(cov2d + eps2d I)) in antialiased mode.
//
// The backward returns gradients for the Gaussian parameters only (means, quats, scales, opacities); the
// caller uses the PyTorch projection when the cameras need gradients.

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kExtentMax = 3.33f;
constexpr float kQuatEps = 1e-12f;  // F.normalize's eps, as kornia's quaternion_to_rotation_matrix uses

struct Camera {
    float R[3][3], t[3], fx, fy, cx, cy;
    float x_lo, x_hi, y_lo, y_hi;  // clamp range of x/z and y/z (gsplat frame: centres at +0.5)
};

Camera make_camera(const float* w2c, const float* K, int64_t width, int64_t height) {
    Camera cam{};
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) cam.R[i][j] = w2c[4 * i + j];
        cam.t[i] = w2c[4 * i + 3];
    }
    cam.fx = K[0];
    cam.fy = K[4];
    cam.cx = K[2];
    cam.cy = K[5];
    const float cxs = cam.cx + 0.5f, cys = cam.cy + 0.5f;
    const float tan_x = 0.5f * static_cast<float>(width) / cam.fx, tan_y = 0.5f * static_cast<float>(height) / cam.fy;
    cam.x_lo = -(cxs / cam.fx + 0.3f * tan_x);
    cam.x_hi = (static_cast<float>(width) - cxs) / cam.fx + 0.3f * tan_x;
    cam.y_lo = -(cys / cam.fy + 0.3f * tan_y);
    cam.y_hi = (static_cast<float>(height) - cys) / cam.fy + 0.3f * tan_y;
    return cam;
}

// Unit quaternion (w, x, y, z) and its rotation matrix.
struct Rotation {
    float q[4], norm, M[3][3];
};

Rotation rotation_from_quat(const float* quat) {
    Rotation r{};
    r.norm = std::sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
    const float inv = 1.0f / std::max(r.norm, kQuatEps);
    for (int i = 0; i < 4; ++i) r.q[i] = quat[i] * inv;
    const float w = r.q[0], x = r.q[1], y = r.q[2], z = r.q[3];
    r.M[0][0] = 1.0f - 2.0f * (y * y + z * z);
    r.M[0][1] = 2.0f * (x * y - w * z);
    r.M[0][2] = 2.0f * (x * z + w * y);
    r.M[1][0] = 2.0f * (x * y + w * z);
    r.M[1][1] = 1.0f - 2.0f * (x * x + z * z);
    r.M[1][2] = 2.0f * (y * z - w * x);
    r.M[2][0] = 2.0f * (x * z - w * y);
    r.M[2][1] = 2.0f * (y * z + w * x);
    r.M[2][2] = 1.0f - 2.0f * (x * x + y * y);
    return r;
}

// Everything the forward computes for one (camera, Gaussian) pair that the backward needs again.
struct Projected {
    float p[3], z_safe, xz, yz;
    bool depth_ok, x_free, y_free;  // x/z, y/z not clamped: their gradient flows
    float jx[3], jy[3], Bx[3], By[3], Ax[3], Ay[3];
    float cxx, cyy, cxy, det_unblurred, Cxx, Cyy, det, det_safe;
    bool det_ok;
};

Projected project_one(const Camera& cam, const float* mean, const Rotation& rot, const float* scale, float eps2d,
                      float near, float far) {
    Projected g{};
    for (int i = 0; i < 3; ++i)
        g.p[i] = cam.R[i][0] * mean[0] + cam.R[i][1] * mean[1] + cam.R[i][2] * mean[2] + cam.t[i];
    const float z = g.p[2];
    g.depth_ok = z >= near && z <= far;
    g.z_safe = g.depth_ok ? z : 1.0f;  // culled ones still flow through the arithmetic; keep it finite
    const float xz_raw = g.p[0] / g.z_safe, yz_raw = g.p[1] / g.z_safe;
    g.xz = std::min(std::max(xz_raw, cam.x_lo), cam.x_hi);
    g.yz = std::min(std::max(yz_raw, cam.y_lo), cam.y_hi);
    g.x_free = xz_raw > cam.x_lo && xz_raw < cam.x_hi;
    g.y_free = yz_raw > cam.y_lo && yz_raw < cam.y_hi;
    const float ux = cam.fx / g.z_safe, uy = cam.fy / g.z_safe;
    for (int i = 0; i < 3; ++i) {
        g.jx[i] = ux * (cam.R[0][i] - g.xz * cam.R[2][i]);
        g.jy[i] = uy * (cam.R[1][i] - g.yz * cam.R[2][i]);
    }
    for (int j = 0; j < 3; ++j) {
        g.Bx[j] = g.jx[0] * rot.M[0][j] + g.jx[1] * rot.M[1][j] + g.jx[2] * rot.M[2][j];
        g.By[j] = g.jy[0] * rot.M[0][j] + g.jy[1] * rot.M[1][j] + g.jy[2] * rot.M[2][j];
        g.Ax[j] = g.Bx[j] * scale[j];
        g.Ay[j] = g.By[j] * scale[j];
    }
    g.cxx = g.Ax[0] * g.Ax[0] + g.Ax[1] * g.Ax[1] + g.Ax[2] * g.Ax[2];
    g.cyy = g.Ay[0] * g.Ay[0] + g.Ay[1] * g.Ay[1] + g.Ay[2] * g.Ay[2];
    g.cxy = g.Ax[0] * g.Ay[0] + g.Ax[1] * g.Ay[1] + g.Ax[2] * g.Ay[2];
    g.det_unblurred = g.cxx * g.cyy - g.cxy * g.cxy;
    g.Cxx = g.cxx + eps2d;
    g.Cyy = g.cyy + eps2d;
    g.det = g.Cxx * g.Cyy - g.cxy * g.cxy;
    g.det_ok = g.det > 0.0f;
    g.det_safe = g.det_ok ? g.det : 1.0f;
    return g;
}

struct Inputs {
    const float *means, *quats, *scales, *opacities, *w2c, *K;
    int64_t C, N;
};

Inputs read_inputs(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
                   const torch::Tensor& opacities, const torch::Tensor& w2c, const torch::Tensor& K) {
    for (const auto* t : {&means, &quats, &scales, &opacities, &w2c, &K}) {
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                    "projection: inputs must be contiguous float32 CPU tensors");
    }
    const int64_t N = means.size(0), C = w2c.size(0);
    TORCH_CHECK(means.dim() == 2 && means.size(1) == 3 && quats.sizes() == torch::IntArrayRef({N, 4}) &&
                    scales.sizes() == torch::IntArrayRef({N, 3}) && opacities.sizes() == torch::IntArrayRef({N}),
                "projection: expected means (N,3), quats (N,4), scales (N,3), opacities (N,)");
    TORCH_CHECK(w2c.sizes() == torch::IntArrayRef({C, 4, 4}) && K.sizes() == torch::IntArrayRef({C, 3, 3}),
                "projection: expected w2c (C,4,4) and K (C,3,3)");
    return {means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(),
            opacities.data_ptr<float>(), w2c.data_ptr<float>(), K.data_ptr<float>(), C, N};
}

}  // namespace

// means (N,3), quats (N,4) wxyz, scales (N,3), opacities (N,), w2c (C,4,4), K (C,3,3), all float32
// -> means2d (C,N,2), conics (C,N,3), depths (C,N), opacities per camera (C,N), radii (C,N,2) int32.
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor w2c, torch::Tensor K,
                                           int64_t width, int64_t height, double eps2d, double near, double far,
                                           bool antialiased, int64_t num_threads) {
    const Inputs in = read_inputs(means, quats, scales, opacities, w2c, K);
    const int64_t C = in.C, N = in.N;
    const auto options = means.options();
    auto means2d = torch::empty({C, N, 2}, options);
    auto conics = torch::empty({C, N, 3}, options);
    auto depths = torch::empty({C, N}, options);
    auto opacities_cam = torch::empty({C, N}, options);
    auto radii = torch::empty({C, N, 2}, options.dtype(torch::kInt32));
    float *out_m = means2d.data_ptr<float>(), *out_c = conics.data_ptr<float>(), *out_z = depths.data_ptr<float>();
    float* out_o = opacities_cam.data_ptr<float>();
    int32_t* out_r = radii.data_ptr<int32_t>();
    std::vector<Camera> cams;
    for (int64_t c = 0; c < C; ++c) cams.push_back(make_camera(in.w2c + 16 * c, in.K + 9 * c, width, height));
    const float eps = static_cast<float>(eps2d), zn = static_cast<float>(near), zf = static_cast<float>(far);
    const float w = static_cast<float>(width), h = static_cast<float>(height);

#pragma omp parallel for num_threads(num_threads) schedule(static)
    for (int64_t n = 0; n < N; ++n) {
        const Rotation rot = rotation_from_quat(in.quats + 4 * n);
        const float* s = in.scales + 3 * n;
        const bool has_extent = s[0] != 0.0f || s[1] != 0.0f || s[2] != 0.0f;
        for (int64_t c = 0; c < C; ++c) {
            const Camera& cam = cams[c];
            const Projected g = project_one(cam, in.means + 3 * n, rot, s, eps, zn, zf);
            const int64_t cn = c * N + n;
            const float mx = cam.fx * g.p[0] / g.z_safe + cam.cx, my = cam.fy * g.p[1] / g.z_safe + cam.cy;
            out_m[2 * cn] = mx;
            out_m[2 * cn + 1] = my;
            out_c[3 * cn] = g.Cyy / g.det_safe;
            out_c[3 * cn + 1] = -g.cxy / g.det_safe;
            out_c[3 * cn + 2] = g.Cxx / g.det_safe;
            out_z[cn] = g.p[2];
            float o = in.opacities[n];
            if (antialiased) o *= std::sqrt(std::max(g.det_unblurred / g.det_safe, 0.0f));
            out_o[cn] = o;
            // screen box: opacity-aware extent, as in the PyTorch projection
            const float extent = std::min(
                std::sqrt(2.0f * std::log(std::max(o, kAlphaThreshold) / kAlphaThreshold)), kExtentMax);
            const float rx = std::ceil(extent * std::sqrt(std::max(g.Cxx, 0.0f)));
            const float ry = std::ceil(extent * std::sqrt(std::max(g.Cyy, 0.0f)));
            const float px = mx + 0.5f, py = my + 0.5f;
            const bool on_screen = px + rx > 0.0f && px - rx < w && py + ry > 0.0f && py - ry < h;
            const bool visible = g.depth_ok && g.det_ok && o >= kAlphaThreshold && has_extent &&
                                 (rx > 0.0f || ry > 0.0f) && on_screen;
            out_r[2 * cn] = visible ? static_cast<int32_t>(rx) : 0;
            out_r[2 * cn + 1] = visible ? static_cast<int32_t>(ry) : 0;
        }
    }
    return {means2d, conics, depths, opacities_cam, radii};
}

// Vector-Jacobian product of project_forward for the Gaussian parameters. v_means2d (C,N,2), v_conics (C,N,3),
// v_depths (C,N), v_opacities (C,N) -> d means (N,3), d quats (N,4), d scales (N,3), d opacities (N,).
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor opacities, torch::Tensor w2c, torch::Tensor K,
                                            torch::Tensor v_means2d, torch::Tensor v_conics, torch::Tensor v_depths,
                                            torch::Tensor v_opacities, int64_t width, int64_t height, double eps2d,
                                            double near, double far, bool antialiased, int64_t num_threads) {
    const Inputs in = read_inputs(means, quats, scales, opacities, w2c, K);
    const int64_t C = in.C, N = in.N;
    for (const auto* t : {&v_means2d, &v_conics, &v_depths, &v_opacities}) {
        TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->is_contiguous() && t->size(0) == C &&
                        t->size(1) == N,
                    "projection backward: gradients must be contiguous float32 (C,N,...) tensors");
    }
    auto d_means = torch::zeros({N, 3}, means.options());
    auto d_quats = torch::zeros({N, 4}, means.options());
    auto d_scales = torch::zeros({N, 3}, means.options());
    auto d_opacities = torch::zeros({N}, means.options());
    const float *vm = v_means2d.data_ptr<float>(), *vc = v_conics.data_ptr<float>();
    const float *vz = v_depths.data_ptr<float>(), *vo = v_opacities.data_ptr<float>();
    float *dm = d_means.data_ptr<float>(), *dq = d_quats.data_ptr<float>(), *ds = d_scales.data_ptr<float>();
    float* dop = d_opacities.data_ptr<float>();
    std::vector<Camera> cams;
    for (int64_t c = 0; c < C; ++c) cams.push_back(make_camera(in.w2c + 16 * c, in.K + 9 * c, width, height));
    const float eps = static_cast<float>(eps2d), zn = static_cast<float>(near), zf = static_cast<float>(far);

#pragma omp parallel for num_threads(num_threads) schedule(static)
    for (int64_t n = 0; n < N; ++n) {
        const Rotation rot = rotation_from_quat(in.quats + 4 * n);
        const float* s = in.scales + 3 * n;
        float v_rot[3][3] = {}, v_mean[3] = {}, v_scale[3] = {}, v_opacity = 0.0f;
        for (int64_t c = 0; c < C; ++c) {
            const Camera& cam = cams[c];
            const Projected g = project_one(cam, in.means + 3 * n, rot, s, eps, zn, zf);
            const int64_t cn = c * N + n;
            const float zs = g.z_safe, zs2 = zs * zs;
            float v_p[3] = {0.0f, 0.0f, vz[cn]}, v_zs = 0.0f;
            // means2d = (fx x/z + cx, fy y/z + cy)
            v_p[0] += cam.fx / zs * vm[2 * cn];
            v_p[1] += cam.fy / zs * vm[2 * cn + 1];
            v_zs -= (cam.fx * g.p[0] * vm[2 * cn] + cam.fy * g.p[1] * vm[2 * cn + 1]) / zs2;
            // conic = (Cyy, -cxy, Cxx) / det
            const float v_c0 = vc[3 * cn], v_c1 = vc[3 * cn + 1], v_c2 = vc[3 * cn + 2], dsafe = g.det_safe;
            float v_Cxx = v_c2 / dsafe, v_Cyy = v_c0 / dsafe, v_cxy = -v_c1 / dsafe;
            float v_det = g.det_ok ? -(v_c0 * g.Cyy - v_c1 * g.cxy + v_c2 * g.Cxx) / (dsafe * dsafe) : 0.0f;
            float v_cxx = 0.0f, v_cyy = 0.0f;
            const float o = in.opacities[n];
            if (antialiased) {
                const float ratio = g.det_unblurred / dsafe, comp = std::sqrt(std::max(ratio, 0.0f));
                v_opacity += vo[cn] * comp;
                const float v_ratio = (ratio > 0.0f && comp > 0.0f) ? vo[cn] * o * 0.5f / comp : 0.0f;
                const float v_det_unblurred = v_ratio / dsafe;
                if (g.det_ok) v_det -= v_ratio * g.det_unblurred / (dsafe * dsafe);
                v_cxx += v_det_unblurred * g.cyy;
                v_cyy += v_det_unblurred * g.cxx;
                v_cxy -= 2.0f * g.cxy * v_det_unblurred;
            } else {
                v_opacity += vo[cn];
            }
            // det = Cxx Cyy - cxy^2, C = cov2d + eps2d I
            v_Cxx += v_det * g.Cyy;
            v_Cyy += v_det * g.Cxx;
            v_cxy -= 2.0f * g.cxy * v_det;
            v_cxx += v_Cxx;
            v_cyy += v_Cyy;
            // cov2d = A A^T, A = B diag(s), B = J R_w Rot
            float v_Bx[3], v_By[3];
            for (int j = 0; j < 3; ++j) {
                const float v_Ax = 2.0f * v_cxx * g.Ax[j] + v_cxy * g.Ay[j];
                const float v_Ay = 2.0f * v_cyy * g.Ay[j] + v_cxy * g.Ax[j];
                v_scale[j] += v_Ax * g.Bx[j] + v_Ay * g.By[j];
                v_Bx[j] = v_Ax * s[j];
                v_By[j] = v_Ay * s[j];
            }
            float v_jx[3], v_jy[3];
            for (int i = 0; i < 3; ++i) {
                v_jx[i] = v_Bx[0] * rot.M[i][0] + v_Bx[1] * rot.M[i][1] + v_Bx[2] * rot.M[i][2];
                v_jy[i] = v_By[0] * rot.M[i][0] + v_By[1] * rot.M[i][1] + v_By[2] * rot.M[i][2];
                for (int j = 0; j < 3; ++j) v_rot[i][j] += g.jx[i] * v_Bx[j] + g.jy[i] * v_By[j];
            }
            // jx = fx/z (R_0 - xz R_2), jy = fy/z (R_1 - yz R_2)
            float v_ux = 0.0f, v_uy = 0.0f, v_xz = 0.0f, v_yz = 0.0f;
            for (int i = 0; i < 3; ++i) {
                v_ux += v_jx[i] * (cam.R[0][i] - g.xz * cam.R[2][i]);
                v_uy += v_jy[i] * (cam.R[1][i] - g.yz * cam.R[2][i]);
                v_xz -= v_jx[i] * cam.R[2][i];
                v_yz -= v_jy[i] * cam.R[2][i];
            }
            v_xz *= cam.fx / zs;
            v_yz *= cam.fy / zs;
            v_zs -= (cam.fx * v_ux + cam.fy * v_uy) / zs2;
            if (g.x_free) {
                v_p[0] += v_xz / zs;
                v_zs -= g.p[0] * v_xz / zs2;
            }
            if (g.y_free) {
                v_p[1] += v_yz / zs;
                v_zs -= g.p[1] * v_yz / zs2;
            }
            if (g.depth_ok) v_p[2] += v_zs;
            // p = R m + t
            for (int j = 0; j < 3; ++j) v_mean[j] += cam.R[0][j] * v_p[0] + cam.R[1][j] * v_p[1] + cam.R[2][j] * v_p[2];
        }
        // rotation matrix of the unit quaternion (w, x, y, z), then the normalisation
        const float w = rot.q[0], x = rot.q[1], y = rot.q[2], z = rot.q[3];
        const float(*v)[3] = v_rot;
        float v_q[4];
        v_q[0] = 2.0f * (-z * v[0][1] + y * v[0][2] + z * v[1][0] - x * v[1][2] - y * v[2][0] + x * v[2][1]);
        v_q[1] = 2.0f * (y * v[0][1] + z * v[0][2] + y * v[1][0] - 2.0f * x * v[1][1] - w * v[1][2] + z * v[2][0] +
                         w * v[2][1] - 2.0f * x * v[2][2]);
        v_q[2] = 2.0f * (-2.0f * y * v[0][0] + x * v[0][1] + w * v[0][2] + x * v[1][0] + z * v[1][2] - w * v[2][0] +
                         z * v[2][1] - 2.0f * y * v[2][2]);
        v_q[3] = 2.0f * (-2.0f * z * v[0][0] - w * v[0][1] + x * v[0][2] + w * v[1][0] - 2.0f * z * v[1][1] +
                         y * v[1][2] + x * v[2][0] + y * v[2][1]);
        if (rot.norm > kQuatEps) {
            const float dot = rot.q[0] * v_q[0] + rot.q[1] * v_q[1] + rot.q[2] * v_q[2] + rot.q[3] * v_q[3];
            for (int i = 0; i < 4; ++i) dq[4 * n + i] = (v_q[i] - rot.q[i] * dot) / rot.norm;
        } else {
            for (int i = 0; i < 4; ++i) dq[4 * n + i] = v_q[i] / kQuatEps;
        }
        for (int j = 0; j < 3; ++j) {
            dm[3 * n + j] = v_mean[j];
            ds[3 * n + j] = v_scale[j];
        }
        dop[n] = v_opacity;
    }
    return {d_means, d_quats, d_scales, d_opacities};
}
