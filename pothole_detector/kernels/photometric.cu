// Photometric disagreement (stages/photometric.py, whose array code is the reference).
// photometric_means: one thread per left pixel: the mean brightness of the WINDOW x WINDOW
//   square about it in the left image and about its matched pixel (column u - d rounded,
//   clipped) in the right image, border pixels repeated; the right mean NaN where the
//   disparity is.
// photometric_sums: the pixels with a right mean that agree under `state` (all of them while
//   its limit is negative, else |left - gain_before x right| <= limit), grid-stride; per block
//   the sums of left, right and |left - gain x right| and their count, into
//   partials[block][SUM_*]; the last block to arrive (arrivals: 0 at launch, left 0) adds
//   them up in block order, so the result does not vary between runs, and updates the state:
//   GAIN (mode 0): gain = sum left / max(sum right, 1), rounded to float; SPREAD (mode 1):
//   limit = trim x the mean |left - gain x right|, gain_before = gain.
// photometric_difference: |left - gain x right|, NaN where the right mean is.
// Defined by the launcher: WINDOW, SUMS (4), BATCH and the state layout (STATE_GAIN,
// STATE_GAIN_BEFORE, STATE_LIMIT).

#define SUM_LEFT 0
#define SUM_RIGHT 1
#define SUM_DIFFERENCE 2
#define SUM_COUNT 3

__device__ __forceinline__ float box_mean(const unsigned char* image, int row, int col,
                                          int height, int width) {
    const int half = WINDOW / 2;
    int total = 0;
    for (int r = row - half; r <= row + half; ++r) {
        const unsigned char* line = image + (long long)min(max(r, 0), height - 1) * width;
        for (int c = col - half; c <= col + half; ++c) total += line[min(max(c, 0), width - 1)];
    }
    return __fdiv_rn((float)total, (float)(WINDOW * WINDOW));
}

extern "C" __global__ void photometric_means(const unsigned char* left,
                                             const unsigned char* right,
                                             const float* disparity, int height, int width,
                                             float* left_mean, float* right_mean) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const long long index = (long long)row * width + col;
    const float d = disparity[index];
    left_mean[index] = box_mean(left, row, col, height, width);
    if (!isfinite(d)) {
        right_mean[index] = __int_as_float(0x7fc00000);
        return;
    }
    const float matched = fminf(fmaxf(rintf(__fsub_rn((float)col, d)), 0.0f), (float)(width - 1));
    right_mean[index] = box_mean(right, row, (int)matched, height, width);
}

__device__ __forceinline__ float difference(float left, float right, float gain) {
    return fabsf(__fsub_rn(left, __fmul_rn(gain, right)));
}

extern "C" __global__ void photometric_sums(const float* left_mean, const float* right_mean,
                                            long long size, int mode, double trim,
                                            double* state, double* partials,
                                            unsigned* arrivals) {
    const float gain = (float)state[STATE_GAIN];
    const float gain_before = (float)state[STATE_GAIN_BEFORE];
    const double limit = state[STATE_LIMIT];
    double sums[SUMS] = {0.0, 0.0, 0.0, 0.0};
    const long long stride = (long long)gridDim.x * blockDim.x;
    // BATCH strided pixels' loads in flight at once, added in the order of a plain
    // grid-stride loop
    for (long long first = blockIdx.x * (long long)blockDim.x + threadIdx.x; first < size;
         first += BATCH * stride) {
        float lefts[BATCH], rights[BATCH];
#pragma unroll
        for (int k = 0; k < BATCH; ++k) {
            const long long i = first + k * stride;
            rights[k] = i < size ? right_mean[i] : __int_as_float(0x7fc00000);
            lefts[k] = i < size ? left_mean[i] : 0.0f;
        }
#pragma unroll
        for (int k = 0; k < BATCH; ++k) {
            const float r = rights[k], l = lefts[k];
            if (!isfinite(r)) continue;
            if (limit >= 0.0 && (double)difference(l, r, gain_before) > limit) continue;
            sums[SUM_LEFT] += l;
            sums[SUM_RIGHT] += r;
            sums[SUM_DIFFERENCE] += difference(l, r, gain);
            sums[SUM_COUNT] += 1.0;
        }
    }
    __shared__ double warp_sums[32][SUMS];
    __shared__ bool last;
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int k = 0; k < SUMS; ++k) {
        for (int offset = 16; offset > 0; offset >>= 1)
            sums[k] += __shfl_down_sync(0xffffffffu, sums[k], offset);
        if (lane == 0) warp_sums[warp][k] = sums[k];
    }
    __syncthreads();
    if (threadIdx.x < SUMS) {
        double total = 0.0;
        for (int w = 0; w < (int)(blockDim.x >> 5); ++w) total += warp_sums[w][threadIdx.x];
        partials[blockIdx.x * SUMS + threadIdx.x] = total;
        __threadfence();
    }
    __syncthreads();
    if (threadIdx.x == 0) last = atomicAdd(arrivals, 1u) == gridDim.x - 1;
    __syncthreads();
    if (!last) return;
    // the last block to finish adds the partials up in a fixed order and updates the state
#pragma unroll
    for (int k = 0; k < SUMS; ++k) {
        sums[k] = 0.0;
        for (int b = threadIdx.x; b < (int)gridDim.x; b += blockDim.x)
            sums[k] += __ldcg(partials + b * SUMS + k);
        for (int offset = 16; offset > 0; offset >>= 1)
            sums[k] += __shfl_down_sync(0xffffffffu, sums[k], offset);
        if (lane == 0) warp_sums[warp][k] = sums[k];
    }
    __syncthreads();
    if (threadIdx.x != 0) return;
    double total[SUMS] = {0.0, 0.0, 0.0, 0.0};
    for (int w = 0; w < (int)(blockDim.x >> 5); ++w)
#pragma unroll
        for (int k = 0; k < SUMS; ++k) total[k] += warp_sums[w][k];
    if (mode == 0) {
        state[STATE_GAIN] = (double)__double2float_rn(
            total[SUM_LEFT] / fmax(total[SUM_RIGHT], 1.0));
    } else {
        state[STATE_LIMIT] = trim * (total[SUM_DIFFERENCE] / fmax(total[SUM_COUNT], 1.0));
        state[STATE_GAIN_BEFORE] = state[STATE_GAIN];
    }
    *arrivals = 0;
}

extern "C" __global__ void photometric_difference(const float* left_mean,
                                                  const float* right_mean, long long size,
                                                  const double* state, float* out) {
    const long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x;
    if (i >= size) return;
    const float r = right_mean[i];
    out[i] = isfinite(r) ? difference(left_mean[i], r, (float)state[STATE_GAIN])
                         : __int_as_float(0x7fc00000);
}

// photometric_inconsistent: one block; the mean of the finite `means` of the road's
// superpixels, then per superpixel whether its finite mean exceeds factor times that.
extern "C" __global__ void photometric_inconsistent(const float* means, const bool* road,
                                                    int count, double factor, bool* out) {
    double total = 0.0, weight = 0.0;
    for (int k = threadIdx.x; k < count; k += blockDim.x) {
        if (road[k] && isfinite(means[k])) {
            total += means[k];
            weight += 1.0;
        }
    }
    __shared__ double warp_total[32], warp_weight[32];
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
    for (int offset = 16; offset > 0; offset >>= 1) {
        total += __shfl_down_sync(0xffffffffu, total, offset);
        weight += __shfl_down_sync(0xffffffffu, weight, offset);
    }
    if (lane == 0) {
        warp_total[warp] = total;
        warp_weight[warp] = weight;
    }
    __syncthreads();
    total = 0.0;
    weight = 0.0;
    for (int w = 0; w < (int)(blockDim.x >> 5); ++w) {
        total += warp_total[w];
        weight += warp_weight[w];
    }
    const double level = total / fmax(weight, 1.0);
    for (int k = threadIdx.x; k < count; k += blockDim.x)
        out[k] = isfinite(means[k]) && (double)means[k] > factor * level;
}
