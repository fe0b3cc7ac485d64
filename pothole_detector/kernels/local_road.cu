// The local road reference (stages/local_road.py) in one cooperative launch of one block per
// moment (at most MOMENTS blocks): the window of each cell of the SLIC grid from the geometry,
// then ROUNDS robust rounds of a weighted plane fitted over each cell's window through
// summed-area tables of the nine weighted moments, then the noise of the road's cells about the
// surface over each window. A block builds the summed-area tables of its moments (blockIdx.x,
// then every gridDim.x-th) in its shared memory; the cells' own steps (weights, the plane of
// each window) are shared out over the grid, grid barriers between them. Defines: ROUNDS,
// MIN_PLANE_SUPPORT, MOMENTS, THREADS (stages/local_road.py), the fit report's layout and the
// road model's (road_disparity.cuh). What other blocks wrote before a barrier is read through
// L2 (__ldcg).
#include "grid_barrier.cuh"
#include "road_disparity.cuh"

static_assert(ROUNDS >= 1, "the last round writes the squared distances the noise reads");


// Moment m of a cell at column x, row y with weight w and value v, in the order the fit reads
// them: w, w v, w x, w y, w x x, w y y, w x y, w x v, w y v (the noise uses the first two).
__device__ __forceinline__ double moment(int m, double w, double x, double y, double v) {
    switch (m) {
        case 0: return w;
        case 1: return w * v;
        case 2: return w * x;
        case 3: return w * y;
        case 4: return w * x * x;
        case 5: return w * y * y;
        case 6: return w * x * y;
        case 7: return w * x * v;
        default: return w * y * v;
    }
}

// table is (rows + 1) x pitch, its first row and column 0: the summed-area table of a moment;
// the sum of the cells top <= i < bottom, left <= j < right.
__device__ __forceinline__ double window_sum(const double* table, int pitch, int top,
                                             int bottom, int left, int right) {
    return table[bottom * pitch + right] - table[top * pitch + right]
           - table[bottom * pitch + left] + table[top * pitch + left];
}

// This block's moments m < moments (blockIdx.x, then every gridDim.x-th): sums[m * cells + k]
// = the sum of moment m of the grid's cells over cell k's window (half sizes half[k] across,
// half[cells + k] along), the cells' weights and values given, through the summed-area table
// `table` ((rows + 1) x pitch, its first row and column 0), a thread's running sum along each
// row, then each column. Synchronizes the block after each moment.
__device__ void window_moments(double* table, int moments, const double* weight,
                               const double* value, const int* half, int rows, int cols,
                               int pitch, double* sums) {
    const int cells = rows * cols;
    for (int m = blockIdx.x; m < moments; m += gridDim.x) {
        for (int k = threadIdx.x; k < cells; k += blockDim.x) {
            const int i = k / cols, j = k - i * cols;
            const double w = __ldcg(weight + k), v = __ldcg(value + k);
            table[(i + 1) * pitch + j + 1] = moment(m, w, j, i, v);
        }
        __syncthreads();
        for (int line = threadIdx.x; line < rows; line += blockDim.x) {
            double* row = table + (line + 1) * pitch + 1;
            double running = 0.0;
#pragma unroll 8
            for (int j = 0; j < cols; ++j) {
                running += row[j];
                row[j] = running;
            }
        }
        __syncthreads();
        for (int line = threadIdx.x; line < cols; line += blockDim.x) {
            double* column = table + pitch + line + 1;
            double running = 0.0;
#pragma unroll 8
            for (int i = 0; i < rows; ++i) {
                running += column[i * pitch];
                column[i * pitch] = running;
            }
        }
        __syncthreads();
        for (int k = threadIdx.x; k < cells; k += blockDim.x) {
            const int i = k / cols, j = k - i * cols;
            const int across = __ldcg(half + k), along = __ldcg(half + cells + k);
            const int top = max(i - along, 0), bottom = min(i + along + 1, rows);
            const int left = max(j - across, 0), right = min(j + across + 1, cols);
            sums[m * cells + k] = window_sum(table, pitch, top, bottom, left, right);
        }
        __syncthreads();
    }
}

// The summed-area table is (rows + 1) x pitch doubles (pitch > cols, odd: threads running
// along consecutive rows read different shared-memory banks), in the dynamic shared memory, or
// where it does not fit (local_table 0) at table + blockIdx.x x (rows + 1) x pitch in global
// memory. arrivals: the grid barrier's counter, 0 at launch.
extern "C" __global__ void __launch_bounds__(THREADS) local_road_fit(
        const float* means, const bool* usable_in, const double* drops, const double* road,
        const double* fit, int rows, int cols, int step, int width, int height, int downsample,
        double f, double cx, double cy, double baseline, double road_level, double radius_m,
        int pitch, int local_table, int* half, double* residual, unsigned char* usable,
        double* weight, double* sums, double* table, double* reference, double* noise,
        unsigned* arrivals) {
    extern __shared__ double shared_table[];
    const int cells = rows * cols, stride = (rows + 1) * pitch;
    double* own = local_table ? shared_table : table + (long long)blockIdx.x * stride;
    unsigned passed = 0;
    for (int e = threadIdx.x; e < pitch + rows; e += blockDim.x)
        own[e < pitch ? e : (e - pitch + 1) * pitch] = 0.0;
    const int first = blockIdx.x * blockDim.x + threadIdx.x, every = gridDim.x * blockDim.x;
    for (int k = first; k < cells; k += every) {
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
        const double off = use ? road_level - (double)means[k] : 0.0;
        usable[k] = use;
        residual[k] = off;
        reference[k] = 0.0;
        weight[k] = use && fabs(off) <= drops[k] ? 1.0 : 0.0;
    }
    grid_barrier(arrivals, passed);
    // each round: the windows' moments, then each cell's plane and its weight for the next
    // round (after the last, for the noise: the inliers and their squared distances)
    for (int round = 0; round < ROUNDS; ++round) {
        window_moments(own, MOMENTS, weight, residual, half, rows, cols, pitch, sums);
        grid_barrier(arrivals, passed);
        for (int k = first; k < cells; k += every) {
            const int i = k / cols, j = k % cols;
            double moments[MOMENTS];
#pragma unroll
            for (int m = 0; m < MOMENTS; ++m) moments[m] = __ldcg(sums + m * cells + k);
            const double n = moments[0], safe = fmax(n, 1e-12);
            const double sv = moments[1], sx = moments[2], sy = moments[3];
            const double mean = sv / safe;
            const double cxx = moments[4] - sx * sx / safe;
            const double cyy = moments[5] - sy * sy / safe;
            const double cxy = moments[6] - sx * sy / safe;
            const double cxv = moments[7] - sx * sv / safe;
            const double cyv = moments[8] - sy * sv / safe;
            const double det = cxx * cyy - cxy * cxy;
            const double scale = fmax(cxx * cyy, 1e-12);
            const bool solvable = n >= MIN_PLANE_SUPPORT && det > 1e-6 * scale;
            double fitted = n > 0 ? mean : 0.0;
            if (solvable) {
                const double slope_x = (cxv * cyy - cyv * cxy) / det;
                const double slope_y = (cyv * cxx - cxv * cxy) / det;
                fitted = mean + slope_x * (j - sx / safe) + slope_y * (i - sy / safe);
            }
            reference[k] = fitted;
            const double off = residual[k] - fitted;
            weight[k] = usable[k] && fabs(off) <= drops[k] ? 1.0 : 0.0;
            if (round == ROUNDS - 1) residual[cells + k] = off * off;
        }
        grid_barrier(arrivals, passed);
    }
    window_moments(own, 2, weight, residual + cells, half, rows, cols, pitch, sums);
    grid_barrier(arrivals, passed);
    const double sigma = road[ROAD_CURVED] != 0.0 ? fit[FIT_QUADRATIC_SIGMA]
                                                  : fit[FIT_PLANAR_SIGMA];
    for (int k = first; k < cells; k += every) {
        const double support = __ldcg(sums + k), spread = fmax(__ldcg(sums + cells + k), 0.0);
        noise[k] = support >= MIN_PLANE_SUPPORT ? sqrt(spread / fmax(support - 3.0, 1.0))
                                                : sigma;
    }
}

// local_tests (stages/local_road.py, whose array code is the reference), one thread per
// superpixel k: drop[k] + reference[k] into total; flags[0], [1], [2] (count each): depressed,
// significant, bumps. Rounded as NumPy does, without fused multiply-adds.
extern "C" __global__ void local_tests(const float* means, const double* reference,
                                       const double* noise, const double* drop,
                                       const bool* searched, int count, double road_level,
                                       double refine_fraction, double corner_significance,
                                       double noise_sigmas, double* total, bool* flags) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= count) return;
    const double mean = means[k], offset = reference[k], threshold = drop[k];
    const double level = __dsub_rn((double)(float)road_level, offset);
    const bool search = searched[k];
    total[k] = __dadd_rn(threshold, offset);
    flags[k] = search && mean < __dsub_rn(level, __dmul_rn(refine_fraction, threshold));
    flags[count + k] = search && mean < __dsub_rn(level, __dmul_rn(corner_significance,
                                                                   threshold));
    const double below = __dsub_rn(__dsub_rn(road_level, mean), offset);
    flags[2 * count + k] = search && isfinite(below)
                           && below < __dmul_rn(-noise_sigmas, noise[k]);
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
