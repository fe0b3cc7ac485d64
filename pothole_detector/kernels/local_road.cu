// The local road reference (stages/local_road.py) in one block: the window of each cell of the
// SLIC grid from the geometry, then ROUNDS robust rounds of a weighted plane fitted over each
// cell's window through summed-area tables of the nine weighted moments, then the noise of the
// road's cells about the surface over each window. Defines: ROUNDS, MIN_PLANE_SUPPORT
// (stages/local_road.py), the fit report's layout and the road model's (road_disparity.cuh).
#include "road_disparity.cuh"

#define MOMENTS 9

// Summed-area tables in place: each of `moments` tables (rows + 1) x (cols + 1), its first row
// and column 0 and cell (i + 1, j + 1) holding the value of cell (i, j), becomes its running sum
// along rows, then along columns. The whole block takes part; ends synchronized.
__device__ void summed_areas(double* table, int moments, int rows, int cols) {
    const int stride = (rows + 1) * (cols + 1);
    for (int e = threadIdx.x; e < moments * rows; e += blockDim.x) {
        double* line = table + (e / rows) * stride + (e % rows + 1) * (cols + 1);
        double running = line[1];
#pragma unroll 8
        for (int j = 2; j <= cols; ++j) {
            running += line[j];
            line[j] = running;
        }
    }
    __syncthreads();
    for (int e = threadIdx.x; e < moments * cols; e += blockDim.x) {
        double* column = table + (e / cols) * stride + e % cols + 1;
        double running = column[cols + 1];
#pragma unroll 8
        for (int i = 2; i <= rows; ++i) {
            running += column[i * (cols + 1)];
            column[i * (cols + 1)] = running;
        }
    }
    __syncthreads();
}

// table[m] is (rows + 1) x (cols + 1), its first row and column 0: the summed-area table of
// moment m; the sum of the cells top <= i < bottom, left <= j < right.
__device__ __forceinline__ double window_sum(const double* table, int cols, int top, int bottom,
                                             int left, int right) {
    const int stride = cols + 1;
    return table[bottom * stride + right] - table[top * stride + right]
           - table[bottom * stride + left] + table[top * stride + left];
}

extern "C" __global__ void local_road_fit(
        const float* means, const bool* usable_in, const double* drops, const double* road,
        const double* fit, int rows, int cols, int step, int width, int height, int downsample,
        double f, double cx, double cy, double baseline, double road_level, double radius_m,
        int* half, double* residual, unsigned char* usable, double* table, double* reference,
        double* noise) {
    const int cells = rows * cols;
    const int stride = (rows + 1) * (cols + 1);
    for (int k = threadIdx.x; k < cells; k += blockDim.x) {
        const int i = k / cols, j = k % cols;
        const double u = fmin((j + 0.5) * step, width - 0.5) * downsample;
        const double v = fmin((i + 0.5) * step, height - 0.5) * downsample;
        const double d = road_disparity(road, u, v);
        double normal[3];
        road_unit_normal(road, f, cx, cy, normal);
        const double ray_x = (u - cx) / f, ray_y = (v - cy) / f;
        const double cosine = (normal[0] * ray_x + normal[1] * ray_y + normal[2])
                              / sqrt(ray_x * ray_x + ray_y * ray_y + 1.0);
        const bool ahead = d > 0 && cosine > 0;
        const double cell_m = baseline * step * downsample / (ahead ? d : 1.0);
        const double across = ahead ? ceil(radius_m / cell_m) : 1.0;
        const double along = ahead ? ceil(radius_m * cosine / cell_m) : 1.0;
        half[k] = (int)fmin(fmax(across, 1.0), (double)cols);
        half[cells + k] = (int)fmin(fmax(along, 1.0), (double)rows);
        const bool use = usable_in[k] && isfinite(means[k]);
        usable[k] = use;
        residual[k] = use ? road_level - (double)means[k] : 0.0;
        reference[k] = 0.0;
    }
    for (int e = threadIdx.x; e < MOMENTS * (rows + 1); e += blockDim.x)
        table[(e / (rows + 1)) * stride + (e % (rows + 1)) * (cols + 1)] = 0.0;
    for (int e = threadIdx.x; e < MOMENTS * cols; e += blockDim.x)
        table[(e / cols) * stride + 1 + e % cols] = 0.0;
    __syncthreads();
    for (int round = 0; round < ROUNDS; ++round) {
        for (int k = threadIdx.x; k < cells; k += blockDim.x) {
            const int i = k / cols, j = k % cols;
            const double w = usable[k] && fabs(residual[k] - reference[k]) <= drops[k] ? 1.0
                                                                                     : 0.0;
            const double x = j, y = i, value = residual[k];
            const double moment[MOMENTS] = {w, w * x, w * y, w * x * x, w * y * y, w * x * y,
                                            w * value, w * x * value, w * y * value};
            const int at = (i + 1) * (cols + 1) + j + 1;
            for (int m = 0; m < MOMENTS; ++m) table[m * stride + at] = moment[m];
        }
        __syncthreads();
        summed_areas(table, MOMENTS, rows, cols);
        for (int k = threadIdx.x; k < cells; k += blockDim.x) {
            const int i = k / cols, j = k % cols;
            const int along = half[cells + k];
            const int top = max(i - along, 0), bottom = min(i + along + 1, rows);
            const int left = max(j - half[k], 0), right = min(j + half[k] + 1, cols);
            double sums[MOMENTS];
            for (int m = 0; m < MOMENTS; ++m)
                sums[m] = window_sum(table + m * stride, cols, top, bottom, left, right);
            const double n = sums[0], safe = fmax(n, 1e-12);
            const double mean = sums[6] / safe;
            const double cxx = sums[3] - sums[1] * sums[1] / safe;
            const double cyy = sums[4] - sums[2] * sums[2] / safe;
            const double cxy = sums[5] - sums[1] * sums[2] / safe;
            const double cxv = sums[7] - sums[1] * sums[6] / safe;
            const double cyv = sums[8] - sums[2] * sums[6] / safe;
            const double det = cxx * cyy - cxy * cxy;
            const double scale = fmax(cxx * cyy, 1e-12);
            const bool solvable = n >= MIN_PLANE_SUPPORT && det > 1e-6 * scale;
            double fitted = n > 0 ? mean : 0.0;
            if (solvable) {
                const double slope_x = (cxv * cyy - cyv * cxy) / det;
                const double slope_y = (cyv * cxx - cxv * cxy) / det;
                fitted = mean + slope_x * (j - sums[1] / safe) + slope_y * (i - sums[2] / safe);
            }
            residual[cells + k] = fitted;
        }
        __syncthreads();
        for (int k = threadIdx.x; k < cells; k += blockDim.x) reference[k] = residual[cells + k];
        __syncthreads();
    }
    const double sigma = road[ROAD_CURVED] != 0.0 ? fit[FIT_QUADRATIC_SIGMA]
                                                  : fit[FIT_PLANAR_SIGMA];
    for (int k = threadIdx.x; k < cells; k += blockDim.x) {
        const int at = (k / cols + 1) * (cols + 1) + k % cols + 1;
        const double off = residual[k] - reference[k];
        const double w = usable[k] && fabs(off) <= drops[k] ? 1.0 : 0.0;
        table[at] = w;
        table[stride + at] = w * off * off;
    }
    __syncthreads();
    summed_areas(table, 2, rows, cols);
    for (int k = threadIdx.x; k < cells; k += blockDim.x) {
        const int i = k / cols, j = k % cols;
        const int along = half[cells + k];
        const int top = max(i - along, 0), bottom = min(i + along + 1, rows);
        const int left = max(j - half[k], 0), right = min(j + half[k] + 1, cols);
        const double support = window_sum(table, cols, top, bottom, left, right);
        const double spread = fmax(window_sum(table + stride, cols, top, bottom, left, right),
                                   0.0);
        noise[k] = support >= MIN_PLANE_SUPPORT ? sqrt(spread / fmax(support - 3.0, 1.0))
                                                : sigma;
    }
}

// local_pixel_offsets (stages/local_road.py, pixel_offsets, whose array code is the reference):
// one thread per full-resolution pixel, the cells' offsets bilinear between the cells' centres
// (cell_px apart, centres at (k + 0.5) cell_px), constant past the outer centres, in float.
__device__ __forceinline__ void cell_weights(int pixel, int cells, float cell_px, int* low,
                                             int* high, float* weight) {
    float position = __fsub_rn(__fdiv_rn(__fadd_rn((float)pixel, 0.5f), cell_px), 0.5f);
    position = fminf(fmaxf(position, 0.0f), (float)(cells - 1));
    *low = (int)floorf(position);
    *high = min(*low + 1, cells - 1);
    *weight = __fsub_rn(position, (float)*low);
}

extern "C" __global__ void local_pixel_offsets(const double* cell_offsets, int cells_y,
                                               int cells_x, float cell_px, int height, int width,
                                               float* out) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    int left, right, top, bottom;
    float across_weight, down_weight;
    cell_weights(col, cells_x, cell_px, &left, &right, &across_weight);
    cell_weights(row, cells_y, cell_px, &top, &bottom, &down_weight);
    const float keep_across = __fsub_rn(1.0f, across_weight);
    const float keep_down = __fsub_rn(1.0f, down_weight);
    const double* upper = cell_offsets + (long long)top * cells_x;
    const double* lower = cell_offsets + (long long)bottom * cells_x;
    const float at_top = __fadd_rn(__fmul_rn(__double2float_rn(upper[left]), keep_across),
                                   __fmul_rn(__double2float_rn(upper[right]), across_weight));
    const float at_bottom = __fadd_rn(__fmul_rn(__double2float_rn(lower[left]), keep_across),
                                      __fmul_rn(__double2float_rn(lower[right]), across_weight));
    out[(long long)row * width + col] = __fadd_rn(__fmul_rn(at_top, keep_down),
                                                  __fmul_rn(at_bottom, down_weight));
}
