// Tile compositing of projected 3D Gaussians on the CPU: forward and exact backward (and the module's
// Python bindings; projection and binning live in project_gaussians.cpp and bin_tiles.cpp).
//
// Semantics are gsplat 1.5.3's rasterize_to_pixels (EWA splatting): per pixel, front to back along the
// tile's depth-sorted list, alpha = min(0.999, o * exp(-sigma)), skip sigma < 0 or alpha < 1/255, stop
// before the Gaussian that would take the transmittance to <= 1e-4. Pixel centres are at integer
// coordinates (the project's convention). One OpenMP task per tile; inside a tile, each row of a Gaussian's
// screen box is narrowed to the columns its alpha >= 1/255 ellipse can reach (with a safety margin), and
// only the 8-pixel halves of the row that overlap them are evaluated, as SIMD vectors.
//
// The backward walks each pixel front to back again (recomputing the transmittance exactly instead of
// dividing it back out), gets the colour still to come from the forward output minus the running prefix,
// and writes one gradient row per intersection; rows are then summed per Gaussian, each thread owning a
// range of Gaussians and adding their rows in list order. No atomics, and the result does not depend on
// the thread count.

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <omp.h>
#include <vector>

namespace {

constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.999f;
constexpr float kTransmittanceMin = 1e-4f;
// Tiles are 16 x 16: a tile row is exactly two AVX2 vectors, so the halves of a row are processed whole,
// without scalar remainders; lanes of a half outside the Gaussian's chord are evaluated and fail the alpha
// test, like gsplat evaluates every pixel of a tile.
constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;

struct Frame {
    int64_t cameras, width, height, tile_size, tiles_x, tiles_y, channels;
};

struct Box {
    int x0, x1, y0, y1;  // pixel box [x0, x1) x [y0, y1) in image coordinates
};

// Pixels of tile `tile` (camera-local id) that lie inside the image.
Box tile_box(const Frame& f, int64_t tile) {
    const int tx = static_cast<int>(tile % f.tiles_x), ty = static_cast<int>(tile / f.tiles_x);
    return {tx * kTile, std::min<int>(tx * kTile + kTile, f.width), ty * kTile,
            std::min<int>(ty * kTile + kTile, f.height)};
}

// The rows (and columns) of `tile` a Gaussian can reach with alpha >= 1/255: its screen box (radius from the
// opacity-aware extent, plus one pixel of margin against rounding), clipped to the tile.
bool gaussian_box(float mx, float my, int rx, int ry, const Box& tile, Box& out) {
    const float x0 = std::ceil(mx - static_cast<float>(rx) - 1.0f);
    const float x1 = std::floor(mx + static_cast<float>(rx) + 1.0f) + 1.0f;
    const float y0 = std::ceil(my - static_cast<float>(ry) - 1.0f);
    const float y1 = std::floor(my + static_cast<float>(ry) + 1.0f) + 1.0f;
    out.x0 = static_cast<int>(std::max<float>(tile.x0, std::min<float>(x0, tile.x1)));
    out.x1 = static_cast<int>(std::min<float>(tile.x1, std::max<float>(x1, tile.x0)));
    out.y0 = static_cast<int>(std::max<float>(tile.y0, std::min<float>(y0, tile.y1)));
    out.y1 = static_cast<int>(std::min<float>(tile.y1, std::max<float>(y1, tile.y0)));
    return out.x0 < out.x1 && out.y0 < out.y1;
}

// exp(x) for x <= 0 (the kernel needs exp(-sigma); sigma >= 0 for a positive-definite conic, and sigma < 0
// is skipped anyway): Cody-Waite range reduction and a degree-6 polynomial, max relative error 8e-8 over
// [-87, 0]. Inline, so that the SIMD rows need no call into libm; x is clamped to [-87, 0].
inline float exp_nonpositive(float x) {
    x = std::min(std::max(x, -87.0f), 0.0f);
    const float n = std::nearbyint(x * 1.44269504088896341f);
    const float r = (x - n * 0.693359375f) + n * 2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

// Per (Gaussian, tile): what is needed to narrow each row to the columns with alpha >= 1/255.
// In exact arithmetic sigma(dx) = a/2 (dx - dx0)^2 + det/(2a) dy^2 with dx0 = -b dy / a, and alpha >= 1/255
// needs sigma <= ln(255 o). The bound is widened (relative and absolute slack on the log, one pixel on each
// side) so that float rounding of the kernel's own sigma and exp can never make a skipped pixel count. The
// constants are formed in double (det = ac - b^2 cancels for thin ellipses) and the per-row part, which only
// adds well-scaled terms, runs in float.
struct RowBound {
    float mx, b_over_a, half_det_over_a, two_over_a, log_limit;
    bool usable;  // false for a conic that is not positive definite: every row is evaluated whole
};

RowBound row_bound(float mx, float a, float b, float c, float o) {
    RowBound r{};
    r.mx = mx;
    r.usable = a > 0.0f && o > 0.0f;
    if (!r.usable) return r;
    const double da = a, db = b, dc = c;
    r.b_over_a = static_cast<float>(db / da);
    r.half_det_over_a = static_cast<float>(0.5 * (da * dc - db * db) / da);
    r.two_over_a = static_cast<float>(2.0 / da);
    const double limit = std::log(255.0 * static_cast<double>(o));
    r.log_limit = static_cast<float>(limit + 1e-3 * std::abs(limit) + 1e-2);
    return r;
}

// Columns [x0, x1) of row y (dy = my - y) that may reach alpha >= 1/255, clipped to [bx0, bx1); false when none.
inline bool row_span(const RowBound& r, float dy, int bx0, int bx1, int& x0, int& x1) {
    if (!r.usable) {
        x0 = bx0;
        x1 = bx1;
        return true;
    }
    const float room = r.log_limit - r.half_det_over_a * dy * dy;
    if (room < 0.0f) return false;
    const float half_width = std::sqrt(room * r.two_over_a);
    const float centre = r.mx + r.b_over_a * dy;  // x where sigma is smallest on this row
    const float lo = std::max(std::ceil(centre - half_width) - 1.0f, static_cast<float>(bx0));
    const float hi = std::min(std::floor(centre + half_width) + 2.0f, static_cast<float>(bx1));
    if (!(lo < hi)) return false;
    x0 = static_cast<int>(lo);
    x1 = static_cast<int>(hi);
    return true;
}

// Shape of one Gaussian on screen: mean, conic (a, b, c) and opacity.
struct Splat {
    float mx, my, a, b, c, o;
};

constexpr int kLanes = 8;  // one AVX2 vector of floats; a tile row is two of them

// Forward over 8 pixels of a tile row for one Gaussian: alpha test, early stop, transmittance update, and
// acc[k * stride + lane] += weight * colour[k] for every channel. Returns how many pixels stopped here.
// The lane helpers take restrict pointers and stay out of line: that is what lets GCC vectorise them whatever
// the calling context.
__attribute__((noinline)) int forward_lanes(const Splat& s, float dy, float x0, int32_t pos,
                                            const float* __restrict color, int64_t channels, int stride,
                                            float* __restrict done, float* __restrict T, int32_t* __restrict last,
                                            float* __restrict acc) {
    float weight[kLanes];
    int stopped = 0, used = 0;
#pragma omp simd reduction(+ : stopped, used)
    for (int lx = 0; lx < kLanes; ++lx) {
        const float dx = s.mx - (x0 + static_cast<float>(lx));
        const float sigma = 0.5f * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
        const float alpha = std::min(kAlphaMax, s.o * exp_nonpositive(-sigma));
        const bool live = (done[lx] == 0.0f) & (sigma >= 0.0f) & (alpha >= kAlphaThreshold);
        const float next_t = T[lx] * (1.0f - alpha);
        const bool stop = live & (next_t <= kTransmittanceMin);
        const bool use = live & !stop;
        stopped += stop ? 1 : 0;
        used += use ? 1 : 0;
        done[lx] = stop ? 1.0f : done[lx];
        weight[lx] = use ? alpha * T[lx] : 0.0f;
        T[lx] = use ? next_t : T[lx];
        last[lx] = use ? pos : last[lx];
    }
    if (used == 0) return stopped;
    for (int64_t k = 0; k < channels; ++k) {
        const float ck = color[k];
        float* __restrict acc_k = acc + k * stride;
#pragma omp simd
        for (int lx = 0; lx < kLanes; ++lx) acc_k[lx] += weight[lx] * ck;
    }
    return stopped;
}

struct SplatGrad {
    float mx = 0.f, my = 0.f, a = 0.f, b = 0.f, c = 0.f, o = 0.f;
};

// Pixel state of one tile for the backward, channel-major arrays with `stride` floats per channel.
struct BackwardLanes {
    const int32_t* last;      // last contributing list position
    const float* g_alpha;     // dL/dalpha
    const float* t_end;       // final transmittance
    const float* g_color;     // dL/dimage, per channel
    float* T;                 // transmittance before the current Gaussian
    float* remaining;         // colour still to come behind the current Gaussian (background included)
};

// Backward over 8 pixels of a tile row for one Gaussian: recompute alpha and the transmittance, update the
// colour still to come, and accumulate dL/dcolour (v_color) and dL/d(mean, conic, opacity) (grad) by chaining
// dL/dalpha through alpha = o exp(-sigma). The 0.999 cap has no gradient (as in gsplat).
__attribute__((noinline)) void backward_lanes(const Splat& s, float dy, float x0, int32_t pos,
                                              const float* __restrict color, int64_t channels, int stride,
                                              const BackwardLanes& px, float* __restrict v_color, SplatGrad& grad) {
    const int32_t* __restrict last = px.last;
    const float* __restrict g_a = px.g_alpha;
    const float* __restrict t_end = px.t_end;
    float* __restrict T = px.T;
    float vis[kLanes], weight[kLanes], t_before[kLanes], inv_one_minus[kLanes], v_alpha[kLanes], used[kLanes];
    int any = 0;
#pragma omp simd reduction(+ : any)
    for (int lx = 0; lx < kLanes; ++lx) {
        const float dx = s.mx - (x0 + static_cast<float>(lx));
        const float sigma = 0.5f * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
        const float e = exp_nonpositive(-sigma);
        const float alpha = std::min(kAlphaMax, s.o * e);
        const bool use = (pos <= last[lx]) & (sigma >= 0.0f) & (alpha >= kAlphaThreshold);
        const float inv = 1.0f / (1.0f - alpha);
        any += use ? 1 : 0;
        used[lx] = use ? 1.0f : 0.0f;
        vis[lx] = e;
        t_before[lx] = T[lx];
        weight[lx] = use ? alpha * T[lx] : 0.0f;
        inv_one_minus[lx] = inv;
        v_alpha[lx] = use ? g_a[lx] * t_end[lx] * inv : 0.0f;
        T[lx] = use ? T[lx] * (1.0f - alpha) : T[lx];
    }
    if (any == 0) return;  // nothing drawn here: no colour to move, no gradient
    for (int64_t k = 0; k < channels; ++k) {
        const float ck = color[k];
        const float* __restrict g_c = px.g_color + k * stride;
        float* __restrict remaining = px.remaining + k * stride;
        float vc = 0.0f;
#pragma omp simd reduction(+ : vc)
        for (int lx = 0; lx < kLanes; ++lx) {
            remaining[lx] -= weight[lx] * ck;
            const float d_alpha = g_c[lx] * (ck * t_before[lx] - remaining[lx] * inv_one_minus[lx]);
            v_alpha[lx] += used[lx] != 0.0f ? d_alpha : 0.0f;
            vc += weight[lx] * g_c[lx];
        }
        v_color[k] += vc;
    }
    float v_mx = 0.f, v_my = 0.f, v_a = 0.f, v_b = 0.f, v_c = 0.f, v_o = 0.f;
#pragma omp simd reduction(+ : v_mx, v_my, v_a, v_b, v_c, v_o)
    for (int lx = 0; lx < kLanes; ++lx) {
        const float dx = s.mx - (x0 + static_cast<float>(lx));
        const bool live = (used[lx] != 0.0f) & (s.o * vis[lx] <= kAlphaMax);
        const float v_sigma = live ? -s.o * vis[lx] * v_alpha[lx] : 0.0f;
        v_o += live ? vis[lx] * v_alpha[lx] : 0.0f;
        v_a += 0.5f * v_sigma * dx * dx;
        v_b += v_sigma * dx * dy;
        v_c += 0.5f * v_sigma * dy * dy;
        v_mx += v_sigma * (s.a * dx + s.b * dy);
        v_my += v_sigma * (s.b * dx + s.c * dy);
    }
    grad.mx += v_mx;
    grad.my += v_my;
    grad.a += v_a;
    grad.b += v_b;
    grad.c += v_c;
    grad.o += v_o;
}

void check_inputs(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opacities,
                  const torch::Tensor& colors, const torch::Tensor& radii, const torch::Tensor& background,
                  const torch::Tensor& tile_offsets, const torch::Tensor& flatten_ids) {
    for (const auto* t : {&means2d, &conics, &opacities, &colors, &background}) {
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                    "tile compositor: float inputs must be contiguous float32 CPU tensors");
    }
    TORCH_CHECK(radii.scalar_type() == torch::kInt32 && radii.is_contiguous(), "tile compositor: radii must be int32");
    TORCH_CHECK(tile_offsets.scalar_type() == torch::kInt64 && flatten_ids.scalar_type() == torch::kInt64,
                "tile compositor: tile_offsets and flatten_ids must be int64");
}

}  // namespace

// means2d (M,2), conics (M,3), opacities (M,), colors (M,D), radii (M,2) int32, background (C,D),
// tile_offsets (C*T+1,) int64, flatten_ids (P,) int64 into M = C*N
// -> image (C,H,W,D), final transmittance (C,H,W), last contributing list position per pixel (C,H,W) int32
//    (relative to the tile's list start, -1 when none).
std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor colors, torch::Tensor radii, torch::Tensor background,
                                             torch::Tensor tile_offsets, torch::Tensor flatten_ids, int64_t width,
                                             int64_t height, int64_t tile_size, int64_t num_threads) {
    check_inputs(means2d, conics, opacities, colors, radii, background, tile_offsets, flatten_ids);
    TORCH_CHECK(tile_size == kTile, "tile compositor: the compiled kernel uses 16 x 16 tiles, got ", tile_size);
    const int64_t C = background.size(0), D = colors.size(1);
    const int64_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
    const Frame f{C, width, height, tile_size, tiles_x, tiles_y, D};
    auto image = torch::empty({C, height, width, D}, colors.options());
    auto transmittance = torch::empty({C, height, width}, colors.options());
    auto last = torch::empty({C, height, width}, radii.options());

    const float* mean = means2d.data_ptr<float>();
    const float* conic = conics.data_ptr<float>();
    const float* opacity = opacities.data_ptr<float>();
    const float* color = colors.data_ptr<float>();
    const int32_t* radius = radii.data_ptr<int32_t>();
    const float* bg = background.data_ptr<float>();
    const int64_t* offsets = tile_offsets.data_ptr<int64_t>();
    const int64_t* ids = flatten_ids.data_ptr<int64_t>();
    float* out = image.data_ptr<float>();
    float* out_t = transmittance.data_ptr<float>();
    int32_t* out_last = last.data_ptr<int32_t>();
    const int64_t tiles_per_camera = tiles_x * tiles_y;
    constexpr int ts = kTile, P = kTilePixels;

#pragma omp parallel num_threads(num_threads)
    {
        std::vector<float> T(P), done(P), acc(static_cast<size_t>(D) * P);
        std::vector<int32_t> last_local(P);
#pragma omp for schedule(dynamic, 1)
        for (int64_t tile = 0; tile < C * tiles_per_camera; ++tile) {
            const int64_t cam = tile / tiles_per_camera;
            const Box tb = tile_box(f, tile % tiles_per_camera);
            std::fill(T.begin(), T.end(), 1.0f);
            for (int p = 0; p < P; ++p) {
                const bool inside = tb.x0 + p % ts < tb.x1 && tb.y0 + p / ts < tb.y1;
                done[p] = inside ? 0.0f : 1.0f;  // pixels of a partial tile beyond the image never draw
            }
            std::fill(acc.begin(), acc.end(), 0.0f);
            std::fill(last_local.begin(), last_local.end(), -1);
            const int64_t start = offsets[tile], end = offsets[tile + 1];
            const int active = (tb.x1 - tb.x0) * (tb.y1 - tb.y0);
            int finished = 0;
            for (int64_t i = start; i < end && finished < active; ++i) {
                const int64_t g = ids[i];
                const float mx = mean[2 * g], my = mean[2 * g + 1];
                Box gb;
                if (!gaussian_box(mx, my, radius[2 * g], radius[2 * g + 1], tb, gb)) continue;
                const Splat sp{mx, my, conic[3 * g], conic[3 * g + 1], conic[3 * g + 2], opacity[g]};
                const RowBound bound = row_bound(mx, sp.a, sp.b, sp.c, sp.o);
                const int32_t pos = static_cast<int32_t>(i - start);
                const float* cg = color + g * D;
                for (int y = gb.y0; y < gb.y1; ++y) {
                    const float dy = my - static_cast<float>(y);
                    int x0, x1;
                    if (!row_span(bound, dy, gb.x0, gb.x1, x0, x1)) continue;
                    const int row = (y - tb.y0) * ts;
                    for (int half = (x0 - tb.x0) / kLanes; half * kLanes < x1 - tb.x0; ++half) {
                        const int p = row + half * kLanes;
                        finished += forward_lanes(sp, dy, static_cast<float>(tb.x0 + half * kLanes), pos, cg, D, P,
                                                  done.data() + p, T.data() + p, last_local.data() + p, acc.data() + p);
                    }
                }
            }
            const float* bgc = bg + cam * D;
            for (int y = tb.y0; y < tb.y1; ++y) {
                for (int x = tb.x0; x < tb.x1; ++x) {
                    const int p = (y - tb.y0) * ts + (x - tb.x0);
                    const int64_t pix = (cam * height + y) * width + x;
                    for (int64_t k = 0; k < D; ++k) out[pix * D + k] = acc[k * P + p] + T[p] * bgc[k];
                    out_t[pix] = T[p];
                    out_last[pix] = last_local[p];
                }
            }
        }
    }
    return {image, transmittance, last};
}

// Exact vector-Jacobian product of composite_forward. image/transmittance/last are its outputs,
// grad_image (C,H,W,D), grad_alpha (C,H,W) -> per-Gaussian gradients (M, 6+D) laid out as
// [d means2d (2), d conics (3), d opacity (1), d colors (D)].
torch::Tensor composite_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                 torch::Tensor colors, torch::Tensor radii, torch::Tensor background,
                                 torch::Tensor tile_offsets, torch::Tensor flatten_ids, torch::Tensor image,
                                 torch::Tensor transmittance, torch::Tensor last, torch::Tensor grad_image,
                                 torch::Tensor grad_alpha, int64_t width, int64_t height, int64_t tile_size,
                                 int64_t num_threads) {
    check_inputs(means2d, conics, opacities, colors, radii, background, tile_offsets, flatten_ids);
    TORCH_CHECK(tile_size == kTile, "tile compositor: the compiled kernel uses 16 x 16 tiles, got ", tile_size);
    TORCH_CHECK(grad_image.is_contiguous() && grad_alpha.is_contiguous() && image.is_contiguous(),
                "tile compositor: gradients must be contiguous");
    const int64_t C = background.size(0), D = colors.size(1), M = means2d.size(0);
    const int64_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
    const Frame f{C, width, height, tile_size, tiles_x, tiles_y, D};
    const int64_t row_len = 6 + D, n_isect = flatten_ids.size(0);
    auto per_isect = torch::empty({n_isect, row_len}, colors.options());  // every row is written below

    const float* mean = means2d.data_ptr<float>();
    const float* conic = conics.data_ptr<float>();
    const float* opacity = opacities.data_ptr<float>();
    const float* color = colors.data_ptr<float>();
    const int32_t* radius = radii.data_ptr<int32_t>();
    const int64_t* offsets = tile_offsets.data_ptr<int64_t>();
    const int64_t* ids = flatten_ids.data_ptr<int64_t>();
    const float* img = image.data_ptr<float>();
    const float* t_final = transmittance.data_ptr<float>();
    const int32_t* last_pos = last.data_ptr<int32_t>();
    const float* g_img = grad_image.data_ptr<float>();
    const float* g_alpha = grad_alpha.data_ptr<float>();
    float* rows = per_isect.data_ptr<float>();
    const int64_t tiles_per_camera = tiles_x * tiles_y;
    constexpr int ts = kTile, P = kTilePixels;

#pragma omp parallel num_threads(num_threads)
    {
        std::vector<float> T(P), t_end(P), g_a(P), remaining(static_cast<size_t>(D) * P),
            g_c(static_cast<size_t>(D) * P);
        std::vector<int32_t> last_local(P);
        std::vector<float> v_color(D);
        const BackwardLanes tile_px{last_local.data(), g_a.data(), t_end.data(), g_c.data(), T.data(),
                                    remaining.data()};
#pragma omp for schedule(dynamic, 1)
        for (int64_t tile = 0; tile < C * tiles_per_camera; ++tile) {
            const int64_t cam = tile / tiles_per_camera;
            const Box tb = tile_box(f, tile % tiles_per_camera);
            const int64_t start = offsets[tile], end = offsets[tile + 1];
            if (start == end) continue;
            std::fill(rows + start * row_len, rows + end * row_len, 0.0f);  // pairs that draw nothing
            std::fill(last_local.begin(), last_local.end(), -1);
            std::fill(T.begin(), T.end(), 1.0f);
            // lanes beyond the image take part in the SIMD vectors: give them finite, inert values
            std::fill(remaining.begin(), remaining.end(), 0.0f);
            std::fill(g_c.begin(), g_c.end(), 0.0f);
            std::fill(g_a.begin(), g_a.end(), 0.0f);
            std::fill(t_end.begin(), t_end.end(), 0.0f);
            int32_t max_last = -1;
            for (int y = tb.y0; y < tb.y1; ++y) {
                for (int x = tb.x0; x < tb.x1; ++x) {
                    const int p = (y - tb.y0) * ts + (x - tb.x0);
                    const int64_t pix = (cam * height + y) * width + x;
                    last_local[p] = last_pos[pix];
                    max_last = std::max(max_last, last_pos[pix]);
                    t_end[p] = t_final[pix];
                    g_a[p] = g_alpha[pix];
                    for (int64_t k = 0; k < D; ++k) {
                        remaining[k * P + p] = img[pix * D + k];
                        g_c[k * P + p] = g_img[pix * D + k];
                    }
                }
            }
            for (int64_t i = start; i <= start + max_last; ++i) {
                const int64_t g = ids[i];
                const float mx = mean[2 * g], my = mean[2 * g + 1];
                Box gb;
                if (!gaussian_box(mx, my, radius[2 * g], radius[2 * g + 1], tb, gb)) continue;
                const Splat sp{mx, my, conic[3 * g], conic[3 * g + 1], conic[3 * g + 2], opacity[g]};
                const RowBound bound = row_bound(mx, sp.a, sp.b, sp.c, sp.o);
                const int32_t pos = static_cast<int32_t>(i - start);
                const float* cg = color + g * D;
                std::fill(v_color.begin(), v_color.end(), 0.0f);
                SplatGrad sg;
                for (int y = gb.y0; y < gb.y1; ++y) {
                    const float dy = my - static_cast<float>(y);
                    int x0, x1;
                    if (!row_span(bound, dy, gb.x0, gb.x1, x0, x1)) continue;
                    const int row = (y - tb.y0) * ts;
                    for (int half = (x0 - tb.x0) / kLanes; half * kLanes < x1 - tb.x0; ++half) {
                        const int p = row + half * kLanes;
                        const BackwardLanes lanes{tile_px.last + p, tile_px.g_alpha + p, tile_px.t_end + p,
                                                  tile_px.g_color + p, tile_px.T + p, tile_px.remaining + p};
                        backward_lanes(sp, dy, static_cast<float>(tb.x0 + half * kLanes), pos, cg, D, P, lanes,
                                       v_color.data(), sg);
                    }
                }
                float* out_row = rows + i * row_len;
                out_row[0] = sg.mx;
                out_row[1] = sg.my;
                out_row[2] = sg.a;
                out_row[3] = sg.b;
                out_row[4] = sg.c;
                out_row[5] = sg.o;
                for (int64_t k = 0; k < D; ++k) out_row[6 + k] = v_color[k];
            }
        }
    }
    // Sum the per-intersection rows per Gaussian: each thread owns a contiguous range of Gaussians and adds
    // their rows in list order, so every sum has the same order whatever the thread count.
    auto grads = torch::zeros({M, row_len}, colors.options());
    float* gout = grads.data_ptr<float>();
#pragma omp parallel num_threads(num_threads)
    {
        const int64_t parts = omp_get_num_threads(), part = omp_get_thread_num();
        const int64_t first = M * part / parts, stop = M * (part + 1) / parts;
        for (int64_t i = 0; i < n_isect; ++i) {
            const int64_t g = ids[i];
            if (g < first || g >= stop) continue;
            float* dst = gout + g * row_len;
            const float* src = rows + i * row_len;
            for (int64_t k = 0; k < row_len; ++k) dst[k] += src[k];
        }
    }
    return grads;
}

// bin_tiles.cpp
std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor radii, torch::Tensor depths, int64_t width,
                                     int64_t height, int64_t tile_size, int64_t num_threads);

// project_gaussians.cpp
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                           torch::Tensor opacities, torch::Tensor w2c, torch::Tensor K,
                                           int64_t width, int64_t height, double eps2d, double near, double far,
                                           bool antialiased, int64_t num_threads);
std::vector<torch::Tensor> project_backward(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                            torch::Tensor opacities, torch::Tensor w2c, torch::Tensor K,
                                            torch::Tensor v_means2d, torch::Tensor v_conics, torch::Tensor v_depths,
                                            torch::Tensor v_opacities, int64_t width, int64_t height, double eps2d,
                                            double near, double far, bool antialiased, int64_t num_threads);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.def("project_forward", &project_forward, "EWA projection of 3D Gaussians, forward (CPU, OpenMP)");
    m.def("project_backward", &project_backward, "EWA projection, gradients of the Gaussian parameters (CPU)");
    m.def("composite_forward", &composite_forward, "Gaussian tile compositing, forward (CPU, OpenMP)");
    m.def("composite_backward", &composite_backward, "Gaussian tile compositing, exact backward (CPU, OpenMP)");
    m.def("bin_tiles", &bin_tiles, "Gaussian-tile intersections sorted by camera, tile and depth (CPU)");
}
