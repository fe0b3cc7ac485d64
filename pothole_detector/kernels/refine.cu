// Pixel-level refinement (stages/refine.py, whose NumPy code is the reference), one thread per
// pixel.
// refine_smooth: the mean of the valid (finite) disparities of the SMOOTHING x SMOOTHING
//   square about each pixel, clipped at the image border: filled (NaN where none is valid)
//   and smoothed (NaN where the pixel itself is invalid), both plus offsets where shifted.
// refine_grow: a labelled pixel keeps its label; an unlabelled one whose superpixel is observed
//   and whose transformed filled disparity (as kernels/transform.cu computes it) lies more
//   than fraction x its superpixel's drop below delta takes the largest label within `radius`
//   (a square, clipped); else 0. Either is 0 where it lies less than half as deep below delta
//   as the deepest pixel within RIM_REACH (a square, clipped; NaN is none).
// refine_occluded: out holds a copy of labels; the thread of the right end u of a labelled run
//   of a row (its right neighbour unlabelled) labels in out the unlabelled pixels u + k,
//   0 < k <= road disparity at u + 1 less filled at u - (SMOOTHING - 1), up to the next
//   labelled pixel, whose superpixel is observed, and sets smoothed NaN there (no other thread
//   writes those pixels).
// Defined by the launcher (stages/refine.py, _kernel): SMOOTHING, RIM_REACH, the block's
// BLOCK_X x BLOCK_Y threads and the road parameters' layout (ROAD_*).
#include "road_disparity.cuh"

#define TILE_X (BLOCK_X + SMOOTHING - 1)
#define TILE_Y (BLOCK_Y + SMOOTHING - 1)

extern "C" __global__ void refine_smooth(const float* disparity, const float* offsets,
                                         int shifted, int height, int width, float* filled,
                                         float* smoothed) {
    // the block's squares, NaN outside the image, in the order of the clipped sums
    __shared__ float tile[TILE_Y][TILE_X];
    const int half = SMOOTHING / 2;
    const int top = blockIdx.y * BLOCK_Y - half, left = blockIdx.x * BLOCK_X - half;
    for (int e = threadIdx.y * BLOCK_X + threadIdx.x; e < TILE_X * TILE_Y;
         e += BLOCK_X * BLOCK_Y) {
        const int r = top + e / TILE_X, c = left + e % TILE_X;
        tile[e / TILE_X][e % TILE_X] = r >= 0 && r < height && c >= 0 && c < width
                                           ? disparity[(long long)r * width + c]
                                           : __int_as_float(0x7fc00000);
    }
    __syncthreads();
    const int col = blockIdx.x * BLOCK_X + threadIdx.x;
    const int row = blockIdx.y * BLOCK_Y + threadIdx.y;
    if (col >= width || row >= height) return;
    float total = 0.0f;
    int count = 0;
#pragma unroll
    for (int dy = 0; dy < SMOOTHING; ++dy)
#pragma unroll
        for (int dx = 0; dx < SMOOTHING; ++dx) {
            const float value = tile[threadIdx.y + dy][threadIdx.x + dx];
            if (isfinite(value)) {
                total += value;
                ++count;
            }
        }
    const long long index = (long long)row * width + col;
    float mean = count > 0 ? total / count : __int_as_float(0x7fc00000);
    if (shifted) mean = __fadd_rn(mean, offsets[index]);
    filled[index] = mean;
    smoothed[index] = isfinite(disparity[index]) ? mean : __int_as_float(0x7fc00000);
}

// How far below delta the transformed filled disparity of pixel (row, col) lies (px), rounded
// as stages/transform.py's host transformation.
__device__ float depth_below(const float* filled, const double* road, float delta, int row,
                             int col, int width) {
    const float road_value = __double2float_rn(road_disparity(road, col, row));
    const float transformed =
        __fadd_rn(__fsub_rn(filled[(long long)row * width + col], road_value), delta);
    return __fsub_rn(delta, transformed);
}

extern "C" __global__ void refine_grow(const int* labels, const float* filled,
                                       const int* superpixels, const double* drops,
                                       const bool* observed, const double* road, float delta,
                                       double fraction, int radius, int height, int width,
                                       int* out) {
    // the depths of the block's pixels and of those within RIM_REACH of them (-inf outside)
    __shared__ float depths[BLOCK_Y + 2 * RIM_REACH][BLOCK_X + 2 * RIM_REACH];
    const int col = blockIdx.x * BLOCK_X + threadIdx.x;
    const int row = blockIdx.y * BLOCK_Y + threadIdx.y;
    const bool inside = col < width && row < height;
    const long long index = (long long)row * width + col;
    const int given = inside ? labels[index] : 0;
    float below = 0.0f;
    bool candidate = false;
    if (inside) {
        below = depth_below(filled, road, delta, row, col, width);
        const int superpixel = superpixels[index];
        candidate = given > 0
                    || (observed[superpixel] && (double)below > fraction * drops[superpixel]);
    }
    bool off_step = false;
    if (__syncthreads_or(candidate)) {
        const int top = blockIdx.y * BLOCK_Y - RIM_REACH, left = blockIdx.x * BLOCK_X - RIM_REACH;
        const int tile_width = BLOCK_X + 2 * RIM_REACH;
        for (int e = threadIdx.y * BLOCK_X + threadIdx.x;
             e < (BLOCK_Y + 2 * RIM_REACH) * tile_width; e += BLOCK_X * BLOCK_Y) {
            const int r = top + e / tile_width, c = left + e % tile_width;
            depths[e / tile_width][e % tile_width] =
                r >= 0 && r < height && c >= 0 && c < width
                    ? depth_below(filled, road, delta, r, c, width)
                    : __int_as_float(0xff800000);
        }
        __syncthreads();
        if (candidate) {
            float deepest = __int_as_float(0xff800000);
            for (int dy = 0; dy <= 2 * RIM_REACH; ++dy)
                for (int dx = 0; dx <= 2 * RIM_REACH; ++dx)
                    deepest = fmaxf(deepest, depths[threadIdx.y + dy][threadIdx.x + dx]);
            off_step = below < 0.5f * deepest;
        }
    }
    const bool deep = candidate && given <= 0 && !off_step;
    // most blocks have no deep pixel, or no label within reach of any of their pixels
    int found = 0;
    if (__syncthreads_or(deep)) {
        const int top = max((int)(blockIdx.y * BLOCK_Y) - radius, 0);
        const int bottom = min((int)((blockIdx.y + 1) * BLOCK_Y) - 1 + radius, height - 1);
        const int first = max((int)(blockIdx.x * BLOCK_X) - radius, 0);
        const int span = min((int)((blockIdx.x + 1) * BLOCK_X) - 1 + radius, width - 1)
                         - first + 1;
        const int reach = (bottom - top + 1) * span;
        bool labelled = false;
        for (int e = threadIdx.y * BLOCK_X + threadIdx.x; e < reach && !labelled;
             e += BLOCK_X * BLOCK_Y)
            labelled = labels[(long long)(top + e / span) * width + first + e % span] > 0;
        if (__syncthreads_or(labelled) && deep) {
            for (int r = max(row - radius, 0); r <= min(row + radius, height - 1); ++r)
                for (int c = max(col - radius, 0); c <= min(col + radius, width - 1); ++c)
                    found = max(found, labels[(long long)r * width + c]);
        }
    }
    if (inside) out[index] = given > 0 ? (off_step ? 0 : given) : found;
}

extern "C" __global__ void refine_occluded(const int* labels, const float* filled,
                                           float* smoothed, const int* superpixels,
                                           const bool* observed, const double* road,
                                           int height, int width, int* out) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width - 1 || row >= height) return;
    const long long index = (long long)row * width + col;
    const int label = labels[index];
    const int inside = col - (SMOOTHING - 1);
    if (label <= 0 || labels[index + 1] != 0 || inside < 0) return;
    const double step = road_disparity(road, (double)(col + 1), (double)row)
                        - (double)filled[(long long)row * width + inside];
    for (int k = 1; col + k < width && k <= step; ++k) {
        const long long at = index + k;
        if (labels[at] != 0) break;
        if (!observed[superpixels[at]]) continue;
        out[at] = label;
        smoothed[at] = __int_as_float(0x7fc00000);
    }
}
