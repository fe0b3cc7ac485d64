// Census semi-global matching on the device. Algorithm and reference:
// pothole_detector/stages/census_sgm.py. Compile-time: LEVELS (multiple of LANES), LANES (16 or
// 32 threads per path line / per pixel), CENSUS_RY, CENSUS_RX, INVALID_COST, BORDER_Y,
// BORDER_X. Path costs: uint8 [8][H][W][LEVELS]; thread `sub` of a group holds levels
// sub * PER_LANE .. sub * PER_LANE + PER_LANE - 1.

#define PER_LANE (LEVELS / LANES)
#define OUTSIDE_COST (1 << 20)

// (dx, dy) of the eight path directions: census_sgm.DIRECTIONS.
__constant__ int DIRECTION_DX[8] = {1, -1, 0, 0, 1, -1, 1, -1};
__constant__ int DIRECTION_DY[8] = {0, 0, 1, -1, 1, 1, -1, -1};

__device__ __forceinline__ unsigned group_mask() {
    return LANES == 32 ? 0xffffffffu : (0xffffu << (threadIdx.x & 16));
}

__device__ __forceinline__ int group_min(int value, unsigned mask) {
#pragma unroll
    for (int offset = LANES / 2; offset > 0; offset >>= 1)
        value = min(value, __shfl_xor_sync(mask, value, offset, LANES));
    return value;
}

__device__ __forceinline__ unsigned group_min_u(unsigned value, unsigned mask) {
#pragma unroll
    for (int offset = LANES / 2; offset > 0; offset >>= 1)
        value = min(value, __shfl_xor_sync(mask, value, offset, LANES));
    return value;
}

__device__ __forceinline__ int clamp_index(int i, int n) { return min(max(i, 0), n - 1); }

// blockIdx.z: 0 = left, 1 = right. One thread per pixel.
extern "C" __global__ void census_pair(const unsigned char* left, const unsigned char* right,
                                       unsigned* census_left, unsigned* census_right,
                                       int height, int width) {
    const int u = blockIdx.x * blockDim.x + threadIdx.x;
    const int v = blockIdx.y * blockDim.y + threadIdx.y;
    if (u >= width || v >= height) return;
    const unsigned char* image = blockIdx.z == 0 ? left : right;
    unsigned* out = blockIdx.z == 0 ? census_left : census_right;
    unsigned bits = 0;
    int bit = 0;
#pragma unroll
    for (int dy = 0; dy <= CENSUS_RY; ++dy) {
        const int ahead_row = clamp_index(v + dy, height) * width;
        const int behind_row = clamp_index(v - dy, height) * width;
#pragma unroll
        for (int dx = -CENSUS_RX; dx <= CENSUS_RX; ++dx) {
            if (dy == 0 && dx <= 0) continue;
            const int ahead = image[ahead_row + clamp_index(u + dx, width)];
            const int behind = image[behind_row + clamp_index(u - dx, width)];
            bits |= (unsigned)(ahead > behind) << bit;
            ++bit;
        }
    }
    out[v * width + u] = bits;
}

// blockIdx.y: direction (dx, dy) in the order of census_sgm.DIRECTIONS; each group of LANES
// threads walks one line of that direction from where it enters the image.
extern "C" __global__ void __launch_bounds__(256)
sgm_paths(const unsigned* census_left, const unsigned* census_right, const int* kappa,
          unsigned char* paths, int height, int width, int p1, int p2) {
    const int direction = blockIdx.y;
    const int dx = DIRECTION_DX[direction], dy = DIRECTION_DY[direction];
    const int sub = threadIdx.x % LANES;
    const int line = blockIdx.x * (blockDim.x / LANES) + threadIdx.x / LANES;
    int u, v, lines;
    if (dy == 0) {
        lines = height; v = line; u = dx > 0 ? 0 : width - 1;
    } else if (dx == 0) {
        lines = width; u = line; v = dy > 0 ? 0 : height - 1;
    } else {
        lines = width + height - 1;
        if (line < width) {
            u = line; v = dy > 0 ? 0 : height - 1;
        } else {
            const int along = line - width + 1;
            u = dx > 0 ? 0 : width - 1; v = dy > 0 ? along : height - 1 - along;
        }
    }
    if (line >= lines) return;
    const unsigned mask = group_mask();
    unsigned char* out = paths + (size_t)direction * height * width * LEVELS;
    int previous[PER_LANE];
    int previous_min = 0;
    bool first = true;
    while (u >= 0 && u < width && v >= 0 && v < height) {
        const unsigned left_bits = census_left[v * width + u];
        const unsigned* right_row = census_right + (size_t)v * width;
        const int start = u - kappa[v] - sub * PER_LANE;
        int current[PER_LANE];
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) {
            const int x = start - k;
            current[k] = x >= 0 ? __popc(left_bits ^ right_row[x]) : INVALID_COST;
        }
        if (!first) {
            int below = __shfl_up_sync(mask, previous[PER_LANE - 1], 1, LANES);
            int above = __shfl_down_sync(mask, previous[0], 1, LANES);
            if (sub == 0) below = OUTSIDE_COST;
            if (sub == LANES - 1) above = OUTSIDE_COST;
            const int jump = previous_min + p2;
#pragma unroll
            for (int k = 0; k < PER_LANE; ++k) {
                const int lower = k == 0 ? below : previous[k - 1];
                const int upper = k == PER_LANE - 1 ? above : previous[k + 1];
                const int best = min(min(previous[k], min(lower, upper) + p1), jump);
                current[k] += best - previous_min;
            }
        }
        int local = current[0];
#pragma unroll
        for (int k = 1; k < PER_LANE; ++k) local = min(local, current[k]);
        previous_min = group_min(local, mask);
        unsigned char* cell = out + ((size_t)v * width + u) * LEVELS + sub * PER_LANE;
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) {
            cell[k] = (unsigned char)current[k];
            previous[k] = current[k];
        }
        first = false;
        u += dx;
        v += dy;
    }
}

// One block per row. Winner, uniqueness, subpixel, the right view's winners (shared-memory
// atomicMin of cost << 16 | d per right column) and the left-right check. raw: D0, -1 invalid.
extern "C" __global__ void __launch_bounds__(256)
sgm_select(const unsigned char* paths, float* raw, int height, int width, int uniqueness,
           int lr_max_diff) {
    extern __shared__ unsigned shared[];
    unsigned* right_best = shared;
    int* left_best = (int*)(shared + width);
    const int groups = blockDim.x / LANES;
    const int group = threadIdx.x / LANES;
    const int sub = threadIdx.x % LANES;
    unsigned* totals = shared + 2 * width + group * LEVELS;
    const int v = blockIdx.x;
    const unsigned mask = group_mask();
    const size_t plane = (size_t)height * width * LEVELS;
    for (int x = threadIdx.x; x < width; x += blockDim.x) right_best[x] = 0xffffffffu;
    __syncthreads();
    for (int u = group; u < width; u += groups) {
        const size_t cell = ((size_t)v * width + u) * LEVELS + sub * PER_LANE;
        unsigned total[PER_LANE];
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) total[k] = 0;
#pragma unroll
        for (int direction = 0; direction < 8; ++direction) {
#pragma unroll
            for (int k = 0; k < PER_LANE; ++k) total[k] += paths[direction * plane + cell + k];
        }
        unsigned packed = 0xffffffffu;
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k)
            packed = min(packed, (total[k] << 16) | (unsigned)(sub * PER_LANE + k));
        packed = group_min_u(packed, mask);
        const int best = packed & 0xffff;
        const unsigned least = packed >> 16;
        unsigned second = 0xffffffffu;
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) {
            const int d = sub * PER_LANE + k;
            if (abs(d - best) > 1) second = min(second, total[k]);
            totals[d] = total[k];
            if (u - d >= 0) atomicMin(&right_best[u - d], (total[k] << 16) | (unsigned)d);
        }
        second = group_min_u(second, mask);
        __syncwarp(mask);
        if (sub == 0) {
            bool valid = u - best >= 0;
            if (uniqueness > 0 && second != 0xffffffffu
                && !(100u * least < (unsigned)(100 - uniqueness) * second))
                valid = false;
            float value = (float)best;
            if (best > 0 && best < LEVELS - 1) {
                const int below = (int)totals[best - 1];
                const int above = (int)totals[best + 1];
                const int denominator = max(below + above - 2 * (int)least, 1);
                value = value + __fdiv_rn((float)(below - above), 2.0f * (float)denominator);
            }
            left_best[u] = valid ? best : -1;
            raw[(size_t)v * width + u] = value;
        }
        __syncwarp(mask);
    }
    __syncthreads();
    for (int u = threadIdx.x; u < width; u += blockDim.x) {
        const int best = left_best[u];
        bool valid = best >= 0;
        if (valid && lr_max_diff >= 0)
            valid = abs((int)(right_best[u - best] & 0xffff) - best) <= lr_max_diff;
        if (!valid) raw[(size_t)v * width + u] = -1.0f;
    }
}

// 3x3 median (edge-replicated; -1 = invalid takes part), census border, kappa added back,
// matches left of the image dropped. out: D1, NaN invalid.
extern "C" __global__ void sgm_finish(const float* raw, const int* kappa, float* out,
                                      int height, int width, int median) {
    const int u = blockIdx.x * blockDim.x + threadIdx.x;
    const int v = blockIdx.y * blockDim.y + threadIdx.y;
    if (u >= width || v >= height) return;
    float value;
    if (median) {
        float w[9];
#pragma unroll
        for (int a = 0; a < 3; ++a)
#pragma unroll
            for (int b = 0; b < 3; ++b)
                w[a * 3 + b] = raw[clamp_index(v + a - 1, height) * width
                                   + clamp_index(u + b - 1, width)];
#pragma unroll
        for (int i = 0; i < 5; ++i)
#pragma unroll
            for (int j = i + 1; j < 9; ++j) {
                const float low = fminf(w[i], w[j]);
                w[j] = fmaxf(w[i], w[j]);
                w[i] = low;
            }
        value = w[4];
    } else {
        value = raw[v * width + u];
    }
    const float disparity = value + (float)kappa[v];
    const bool border = v < BORDER_Y || v >= height - BORDER_Y || u < BORDER_X
                        || u >= width - BORDER_X;
    const bool invalid = value < 0.0f || (float)u - disparity < 0.0f || border;
    out[v * width + u] = invalid ? __int_as_float(0x7fc00000) : disparity;
}
