// 2D-histogram threshold on the device. Algorithm and reference: stages/threshold.py
// (histogram_threshold, _tables, _search). tables: float64 [2][4][n_bins]; table 0 is over
// max(i1, i2), table 1 over min(i1, i2); rows: count, sum g1, sum g2, sum g1^2 + g2^2.
// Defined by the launcher (stages/threshold.py, _kernel): TILE_ROWS, TILE_COLUMNS, RUN,
// TABLE_THREADS, TABLE_BLOCKS, SEARCH_THREADS, the road fit report's layout (FIT_*) and the
// road parameters' (ROAD_*).

#include "block_scan.cuh"
#include "road_disparity.cuh"

#define POSITIVE_INFINITY __longlong_as_double(0x7ff0000000000000LL)

__device__ __forceinline__ bool finite(float x) {
    return (__float_as_uint(x) & 0x7f800000u) != 0x7f800000u;
}

// Sums of one table row's bin over a run of pixels, added to the table when the bin changes
// (neighbouring road pixels mostly share a bin, so a run saves most of the atomics).
struct BinRun {
    int bin = -1;
    double count = 0.0, sum_a = 0.0, sum_b = 0.0, sum_square = 0.0;

    __device__ void add(double* table, int n_bins, int next, double a, double b,
                        double square) {
        if (next != bin) {
            flush(table, n_bins);
            bin = next;
        }
        count += 1.0;
        sum_a += a;
        sum_b += b;
        sum_square += square;
    }

    __device__ void flush(double* table, int n_bins) {
        if (bin >= 0) {
            atomicAdd(&table[bin], count);
            atomicAdd(&table[n_bins + bin], sum_a);
            atomicAdd(&table[2 * n_bins + bin], sum_b);
            atomicAdd(&table[3 * n_bins + bin], sum_square);
        }
        bin = -1;
        count = sum_a = sum_b = sum_square = 0.0;
    }
};

static_assert(TILE_ROWS * (TILE_COLUMNS / RUN) == TABLE_THREADS && TILE_COLUMNS % RUN == 0,
              "a thread per run of a tile");

// A neighbour's D2 for the 8-neighbour mean: NaN outside the image, so that it is left out
// like an invalid value.
__device__ __forceinline__ float neighbour(const float* image, int height, int width, int y,
                                           int x) {
    return (y >= 0 && y < height && x >= 0 && x < width) ? image[y * width + x]
                                                         : __int_as_float(0x7fffffff);
}

// One block per TILE_ROWS x TILE_COLUMNS tile, TABLE_THREADS threads, each a run of RUN pixels
// of one row, its 3 x 3 window in registers (three loads a pixel). g2 = mean of the valid
// 8-neighbours, added in the order of threshold.neighbour_mean (float32, no FMA), so the bins
// equal the reference's.
extern "C" __global__ void __launch_bounds__(TABLE_THREADS, TABLE_BLOCKS)
threshold_tables(const float* image, double* tables, int height, int width, float lo,
                 float bin, int n_bins, int in_shared) {
    extern __shared__ double shared_tables[];
    double* target = in_shared ? shared_tables : tables;
    const int entries = 8 * n_bins;
    if (in_shared) {
        for (int i = threadIdx.x; i < entries; i += blockDim.x) shared_tables[i] = 0.0;
        __syncthreads();
    }
    const int v = blockIdx.y * TILE_ROWS + threadIdx.x / (TILE_COLUMNS / RUN);
    const int u0 = blockIdx.x * TILE_COLUMNS + (threadIdx.x % (TILE_COLUMNS / RUN)) * RUN;
    BinRun by_high, by_low;
    float left[3], middle[3], right[3];
    if (v < height && u0 < width) {
#pragma unroll
        for (int r = 0; r < 3; ++r) {
            left[r] = neighbour(image, height, width, v + r - 1, u0 - 1);
            middle[r] = neighbour(image, height, width, v + r - 1, u0);
        }
    }
    for (int k = 0; k < RUN && v < height; ++k) {
        const int u = u0 + k;
        if (u >= width) break;
#pragma unroll
        for (int r = 0; r < 3; ++r) right[r] = neighbour(image, height, width, v + r - 1, u + 1);
        const float g1 = middle[1];
        const float around[8] = {left[0], middle[0], right[0], left[1],
                                 right[1], left[2], middle[2], right[2]};
        float total = 0.0f, number = 0.0f;
#pragma unroll
        for (int i = 0; i < 8; ++i)
            if (finite(around[i])) {
                total = __fadd_rn(total, around[i]);
                number = __fadd_rn(number, 1.0f);
            }
#pragma unroll
        for (int r = 0; r < 3; ++r) {
            left[r] = middle[r];
            middle[r] = right[r];
        }
        if (number == 0.0f || !finite(g1)) continue;
        const float g2 = __fdiv_rn(total, number);
        const float f1 = floorf(__fdiv_rn(__fsub_rn(g1, lo), bin));
        const float f2 = floorf(__fdiv_rn(__fsub_rn(g2, lo), bin));
        if (!(f1 >= 0.0f && f2 >= 0.0f && f1 < (float)n_bins && f2 < (float)n_bins)) continue;
        const int i1 = (int)f1, i2 = (int)f2;
        const double a = g1, b = g2;
        const double square = __dadd_rn(__dmul_rn(a, a), __dmul_rn(b, b));
        by_high.add(target, n_bins, max(i1, i2), a, b, square);
        by_low.add(target + 4 * n_bins, n_bins, min(i1, i2), a, b, square);
    }
    by_high.flush(target, n_bins);
    by_low.flush(target + 4 * n_bins, n_bins);
    if (in_shared) {
        __syncthreads();
        for (int i = threadIdx.x; i < entries; i += blockDim.x) {
            const double value = shared_tables[i];
            if (value != 0.0) atomicAdd(&tables[i], value);
        }
    }
}

// One block of SEARCH_THREADS threads. Table 0 becomes its prefix sums (region 1 of split t =
// index t), table 1 its suffix sums (region 2 of split t = index t + 1), in place; then the split
// with the least E2 (first on ties, like argmin). result: found, split index, road mean.
extern "C" __global__ void __launch_bounds__(SEARCH_THREADS)
threshold_search(double* tables, double* result, int n_bins) {
    __shared__ double warp_sums[32];
    __shared__ double best_value[32];
    __shared__ int best_index[32];
    for (int row = 0; row < 8; ++row) {
        double* table = tables + row * n_bins;
        const bool suffix = row >= 4;
        double carry = 0.0;
        for (int start = 0; start < n_bins; start += blockDim.x) {
            const int i = start + threadIdx.x;
            const int at = suffix ? n_bins - 1 - i : i;
            const double value = i < n_bins ? table[at] : 0.0;
            const double scanned = block_inclusive_scan(value, warp_sums) + carry;
            if (i < n_bins) table[at] = scanned;
            if (threadIdx.x == blockDim.x - 1) warp_sums[0] = scanned;
            __syncthreads();
            carry = warp_sums[0];
            __syncthreads();
        }
    }
    double least = POSITIVE_INFINITY;
    int least_index = 0x7fffffff;
    for (int t = threadIdx.x; t < n_bins - 1; t += blockDim.x) {
        const double n1 = tables[t], n2 = tables[4 * n_bins + t + 1];
        if (!(n1 > 0.0 && n2 > 0.0)) continue;
        const double s1a = tables[n_bins + t], s1b = tables[2 * n_bins + t];
        const double s2a = tables[5 * n_bins + t + 1], s2b = tables[6 * n_bins + t + 1];
        const double e2 = tables[3 * n_bins + t] + tables[7 * n_bins + t + 1]
                          - (s1a * s1a + s1b * s1b) / n1 - (s2a * s2a + s2b * s2b) / n2;
        if (e2 < least) {
            least = e2;
            least_index = t;
        }
    }
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int offset = 16; offset > 0; offset >>= 1) {
        const double other = __shfl_down_sync(0xffffffffu, least, offset);
        const int other_index = __shfl_down_sync(0xffffffffu, least_index, offset);
        if (other < least || (other == least && other_index < least_index)) {
            least = other;
            least_index = other_index;
        }
    }
    if (lane == 0) {
        best_value[warp] = least;
        best_index[warp] = least_index;
    }
    __syncthreads();
    if (threadIdx.x == 0) {
        for (int w = 1; w < (int)(blockDim.x >> 5); ++w)
            if (best_value[w] < least || (best_value[w] == least && best_index[w] < least_index)) {
                least = best_value[w];
                least_index = best_index[w];
            }
        const bool found = least_index != 0x7fffffff && least < POSITIVE_INFINITY;
        const int t = found ? least_index : 0;
        result[0] = found ? 1.0 : 0.0;
        result[1] = t;
        result[2] = found ? tables[5 * n_bins + t + 1] / tables[4 * n_bins + t + 1] : 0.0;
    }
}

// Superpixel selection (stages/threshold.select_superpixels) from the split found by
// threshold_search without reading it back: t_r = lo + (best + 1) bin_px, the reference is
// t_r or the road mean, t_s = reference - delta_pd (compared in float32 like the reference's
// Python scalar) or reference - tolerance[i] (float64 per superpixel, metric mode).
extern "C" __global__ void threshold_select(const double* result, double lo, double bin_px,
                                            int reference_kind, double road_level,
                                            double delta_pd,
                                            const double* tolerance, int per_superpixel,
                                            const float* means, const float* valid_fraction,
                                            float min_valid_fraction, int n, bool* selected) {
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n) return;
    const double split = __dadd_rn(lo, __dmul_rn(__dadd_rn(result[1], 1.0), bin_px));
    const double reference = reference_kind == 2 ? road_level
                             : reference_kind == 1 ? result[2] : split;
    const float mean = means[i];
    const bool below = per_superpixel
        ? (double)mean < __dsub_rn(reference, tolerance[i])
        : mean < (float)__dsub_rn(reference, delta_pd);
    selected[i] = (reference_kind == 2 || result[0] != 0.0) && finite(mean) && below
                  && valid_fraction[i] > min_valid_fraction;
}

// The block's minimum or maximum of value, in every thread.
__device__ __forceinline__ double block_reduce(double value, bool minimum, double* shared) {
    for (int offset = 16; offset > 0; offset >>= 1) {
        const double other = __shfl_down_sync(0xffffffffu, value, offset);
        value = minimum ? fmin(value, other) : fmax(value, other);
    }
    const int warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
    __syncthreads();
    if ((threadIdx.x & 31) == 0) shared[warp] = value;
    __syncthreads();
    value = shared[0];
    for (int w = 1; w < warps; ++w)
        value = minimum ? fmin(value, shared[w]) : fmax(value, shared[w]);
    return value;
}

// Per superpixel the threshold as a disparity drop (drops, px) and whether the road is
// observed there (stages/threshold.observation, the reference): one block, a thread per
// superpixel in turn. Superpixel k sits at the centre of its grid cell (k / cells_x,
// k % cells_x) of `step` px on the map reduced by `downsample`. Metric mode: the threshold
// depth is depth_m or, where more, the depth whose disparity drop is noise_sigmas sigmas of
// the disparity noise, fB (1 / (d - k sigma) - 1 / d) incidence, sigma the superpixel's
// cell_noise[k] where has_cell_noise, else the fit's robust sigma; observed where the ray
// meets the road plane in front of the camera, the model is the road (road_modelled) and the
// threshold depth is at most max_depth_m. With drop_px > 0 (the pixel threshold mode) the drop is
// drop_px, observed where d > drop_px >= sigma, the ray meets the plane in front and the model
// is the road. range: nearest and farthest distance (m) ahead along the road of an observed
// superpixel, NaN where none is: from the point below the camera along the optical axis's
// direction on the road plane. road: the kernel parameters (ROAD_*); fit: the fit report
// (FIT_*).
extern "C" __global__ void __launch_bounds__(SEARCH_THREADS)
threshold_observation(const double* road, const double* fit, int count, int cells_x, int step,
                      int width, int height, int downsample, double f, double cx, double cy,
                      double fb, double depth_m, double drop_px, double noise_sigmas,
                      double max_depth_m, const double* cell_noise, int has_cell_noise,
                      bool* observed, double* drops, double* range) {
    __shared__ double partial[SEARCH_THREADS / 32];
    const double curved = road[ROAD_CURVED];
    const double* c = road + ROAD_C0;
    const double sigma = curved != 0.0 ? fit[FIT_QUADRATIC_SIGMA] : fit[FIT_PLANAR_SIGMA];
    double normal[3];
    const double height_m = fb / road_unit_normal(road, f, cx, cy, normal);
    double nearest = POSITIVE_INFINITY, farthest = -POSITIVE_INFINITY;
    for (int k = threadIdx.x; k < count; k += blockDim.x) {
        const double u = fmin((k % cells_x + 0.5) * step, width - 0.5) * downsample;
        const double v = fmin((k / cells_x + 0.5) * step, height - 0.5) * downsample;
        const double planar = road_planar(road, u, v);
        const double d = __dadd_rn(planar, __dmul_rn(curved, curvature_at(
            c, __ddiv_rn(u, (double)CURVATURE_SCALE_PX), __ddiv_rn(v, (double)CURVATURE_SCALE_PX),
            planar)));
        const double incidence = normal[0] * (u - cx) / f + normal[1] * (v - cy) / f
                                 + normal[2];
        const bool ahead = incidence > 0.0 && road_modelled(d, planar);
        bool seen;
        double safe;
        if (drop_px > 0.0) {
            const bool near_road = d > sigma && ahead;
            safe = near_road ? d : 2.0 * sigma + 1.0;
            seen = near_road && d > drop_px && drop_px >= sigma;
            drops[k] = drop_px;
        } else {
            const double noise = noise_sigmas * (has_cell_noise ? cell_noise[k] : sigma);
            const bool near_road = d > noise && ahead;
            safe = near_road ? d : 2.0 * noise + 1.0;
            const double resolvable = fb * (1.0 / (safe - noise) - 1.0 / safe) * incidence;
            const double threshold_m = fmax(resolvable, depth_m);
            seen = near_road && threshold_m <= max_depth_m;
            drops[k] = safe - fb / (fb / safe + threshold_m / (near_road ? incidence : 1.0));
        }
        observed[k] = seen;
        if (seen) {
            const double along = (fb / safe - normal[2] * height_m)
                                 / sqrt(fmax(1.0 - normal[2] * normal[2], 1e-12));
            nearest = fmin(nearest, along);
            farthest = fmax(farthest, along);
        }
    }
    nearest = block_reduce(nearest, true, partial);
    farthest = block_reduce(farthest, false, partial);
    if (threadIdx.x == 0) {
        const double nan = __longlong_as_double(0x7ff8000000000000ll);
        range[0] = nearest < POSITIVE_INFINITY ? nearest : nan;
        range[1] = farthest > -POSITIVE_INFINITY ? farthest : nan;
    }
}
