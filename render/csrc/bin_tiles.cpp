// Tile binning of projected Gaussians on the CPU: every (Gaussian, tile) pair whose screen box touches the
// tile, sorted by camera, tile and depth, exactly as bin_gaussians_to_tiles in render/rasterize_torch.py
// computes it (same rectangle arithmetic in the same precision; ties in depth keep the Gaussian order).
// Counting, prefix sum and fill are serial passes (one step per intersection); the per-tile depth sorts run
// in parallel, so the result does not depend on the thread count.

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

// Tile rectangle [x0, x1) x [y0, y1) (in tiles) of each Gaussian's screen box, exactly as the PyTorch binning
// computes it (same arithmetic in the same precision); an empty rectangle for culled Gaussians.
template <typename scalar_t>
void tile_rects(const scalar_t* mean, const int32_t* radius, int64_t M, int64_t tile_size, int64_t tiles_x,
                int64_t tiles_y, int32_t* rect, int64_t num_threads) {
    const scalar_t ts = static_cast<scalar_t>(tile_size);
#pragma omp parallel for num_threads(num_threads) schedule(static)
    for (int64_t g = 0; g < M; ++g) {
        int32_t* r = rect + 4 * g;
        const int32_t rx = radius[2 * g], ry = radius[2 * g + 1];
        if (rx <= 0 && ry <= 0) {
            r[0] = r[1] = r[2] = r[3] = 0;
            continue;
        }
        const scalar_t cx = (mean[2 * g] + static_cast<scalar_t>(0.5)) / ts;
        const scalar_t cy = (mean[2 * g + 1] + static_cast<scalar_t>(0.5)) / ts;
        const scalar_t hx = static_cast<scalar_t>(rx) / ts, hy = static_cast<scalar_t>(ry) / ts;
        const auto clamp = [](scalar_t v, int64_t hi) {
            return static_cast<int32_t>(std::min<scalar_t>(std::max<scalar_t>(v, 0), static_cast<scalar_t>(hi)));
        };
        r[0] = clamp(std::floor(cx - hx), tiles_x);
        r[1] = std::max(r[0], clamp(std::ceil(cx + hx), tiles_x));
        r[2] = clamp(std::floor(cy - hy), tiles_y);
        r[3] = std::max(r[2], clamp(std::ceil(cy + hy), tiles_y));
    }
}

template <typename scalar_t>
std::vector<torch::Tensor> bin_tiles_typed(const torch::Tensor& means2d, const torch::Tensor& radii,
                                           const torch::Tensor& depths, int64_t width, int64_t height,
                                           int64_t tile_size, int64_t num_threads) {
    const int64_t C = depths.size(0), N = depths.size(1), M = C * N;
    const int64_t tiles_x = (width + tile_size - 1) / tile_size, tiles_y = (height + tile_size - 1) / tile_size;
    const int64_t tiles_per_camera = tiles_x * tiles_y, tiles = C * tiles_per_camera;
    std::vector<int32_t> rect(static_cast<size_t>(4 * M));
    tile_rects<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), M, tile_size, tiles_x, tiles_y,
                         rect.data(), num_threads);

    auto tile_offsets = torch::zeros({tiles + 1}, torch::dtype(torch::kInt64));
    int64_t* offsets = tile_offsets.data_ptr<int64_t>();
    for (int64_t g = 0; g < M; ++g) {  // count per tile (serial: one increment per intersection)
        const int32_t* r = rect.data() + 4 * g;
        const int64_t base = (g / N) * tiles_per_camera;
        for (int32_t ty = r[2]; ty < r[3]; ++ty)
            for (int32_t tx = r[0]; tx < r[1]; ++tx) ++offsets[base + ty * tiles_x + tx + 1];
    }
    for (int64_t t = 0; t < tiles; ++t) offsets[t + 1] += offsets[t];
    auto flatten_ids = torch::empty({offsets[tiles]}, torch::dtype(torch::kInt64));
    int64_t* ids = flatten_ids.data_ptr<int64_t>();
    std::vector<int64_t> cursor(offsets, offsets + tiles);
    for (int64_t g = 0; g < M; ++g) {  // fill in Gaussian order, so that equal depths keep that order below
        const int32_t* r = rect.data() + 4 * g;
        const int64_t base = (g / N) * tiles_per_camera;
        for (int32_t ty = r[2]; ty < r[3]; ++ty)
            for (int32_t tx = r[0]; tx < r[1]; ++tx) ids[cursor[base + ty * tiles_x + tx]++] = g;
    }
    const scalar_t* depth = depths.data_ptr<scalar_t>();
#pragma omp parallel for num_threads(num_threads) schedule(dynamic, 4)
    for (int64_t t = 0; t < tiles; ++t) {
        std::stable_sort(ids + offsets[t], ids + offsets[t + 1],
                         [depth](int64_t i, int64_t j) { return depth[i] < depth[j]; });
    }
    return {flatten_ids, tile_offsets};
}

}  // namespace

// Gaussian-tile intersections sorted by (camera, tile, depth), ties in Gaussian order.
// means2d (C,N,2), radii (C,N,2) int32 (0 = culled), depths (C,N), float32 or float64
// -> flatten_ids (P,) int64 into the flattened C*N Gaussians, tile_offsets (C*T+1,) int64.
std::vector<torch::Tensor> bin_tiles(torch::Tensor means2d, torch::Tensor radii, torch::Tensor depths, int64_t width,
                                     int64_t height, int64_t tile_size, int64_t num_threads) {
    TORCH_CHECK(depths.dim() == 2 && means2d.dim() == 3 && means2d.size(2) == 2 && radii.dim() == 3,
                "tile binning: expected means2d (C,N,2), radii (C,N,2), depths (C,N)");
    TORCH_CHECK(means2d.size(0) == depths.size(0) && means2d.size(1) == depths.size(1) &&
                    radii.size(0) == depths.size(0) && radii.size(1) == depths.size(1) && radii.size(2) == 2,
                "tile binning: means2d, radii and depths disagree on (C, N)");
    TORCH_CHECK(means2d.is_contiguous() && depths.is_contiguous() && radii.is_contiguous() &&
                    means2d.device().is_cpu() && means2d.scalar_type() == depths.scalar_type() &&
                    radii.scalar_type() == torch::kInt32,
                "tile binning: needs contiguous CPU tensors, means2d and depths of one float dtype, int32 radii");
    TORCH_CHECK(tile_size > 0 && width > 0 && height > 0, "tile binning: sizes must be positive");
    if (means2d.scalar_type() == torch::kFloat64)
        return bin_tiles_typed<double>(means2d, radii, depths, width, height, tile_size, num_threads);
    TORCH_CHECK(means2d.scalar_type() == torch::kFloat32, "tile binning: means2d must be float32 or float64");
    return bin_tiles_typed<float>(means2d, radii, depths, width, height, tile_size, num_threads);
}

