// Photometric disagreement (stages/photometric.py, whose array code is the reference).
// photometric_means: one thread per left pixel: the mean brightness of the WINDOW x WINDOW
//   square about it in the left image and about its matched pixel (column u - d rounded,
//   clipped) in the right image, border pixels repeated; the right mean NaN where the
//   disparity is.
// photometric_rounds: the gain between the views, taken again over the pixels that agree, in
//   one cooperative launch (each pass's sums added up in a fixed order, so the result does not
//   vary between runs), then the disagreement of every pixel.
// Defined by the launcher: WINDOW, SUMS (4), BATCH, THREADS, BLOCKS_PER_MULTIPROCESSOR (the
// rounds' launch holds at most this many blocks a multiprocessor), ROUNDS.

#include "grid_barrier.cuh"
#include "warp_sum.cuh"

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

// The gain and the limit between the passes (every block holds the same).
struct GainState {
    float gain, gain_before;
    double limit;
};

// One pass's sums over the grid: the pixels with a right mean that agree under `state` (all
// of them while its limit is negative, else |left - gain_before x right| <= limit),
// grid-stride; the sums of left, right and |left - gain x right| and their count. Each block's
// into partials[block][SUM_*], then, after the grid's barrier, added up by every block in the
// same fixed order (totals: valid in thread 0).
__device__ void pass_sums(const float* left_mean, const float* right_mean, long long size,
                          const GainState& state, double* partials, unsigned* arrivals,
                          unsigned& passed, double (*warp_sums)[SUMS], double (&totals)[SUMS]) {
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
            if (state.limit >= 0.0 && (double)difference(l, r, state.gain_before) > state.limit)
                continue;
            sums[SUM_LEFT] += l;
            sums[SUM_RIGHT] += r;
            sums[SUM_DIFFERENCE] += difference(l, r, state.gain);
            sums[SUM_COUNT] += 1.0;
        }
    }
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int k = 0; k < SUMS; ++k) {
        sums[k] = warp_sum(sums[k]);
        if (lane == 0) warp_sums[warp][k] = sums[k];
    }
    __syncthreads();
    if (threadIdx.x < SUMS) {
        double total = 0.0;
        for (int w = 0; w < (int)(blockDim.x >> 5); ++w) total += warp_sums[w][threadIdx.x];
        partials[blockIdx.x * SUMS + threadIdx.x] = total;
    }
    grid_barrier(arrivals, passed);
#pragma unroll
    for (int k = 0; k < SUMS; ++k) {
        sums[k] = 0.0;
        for (int b = threadIdx.x; b < (int)gridDim.x; b += blockDim.x)
            sums[k] += __ldcg(partials + b * SUMS + k);
        sums[k] = warp_sum(sums[k]);
        if (lane == 0) warp_sums[warp][k] = sums[k];
    }
    __syncthreads();
    if (threadIdx.x == 0) {
#pragma unroll
        for (int k = 0; k < SUMS; ++k) totals[k] = 0.0;
        for (int w = 0; w < (int)(blockDim.x >> 5); ++w)
#pragma unroll
            for (int k = 0; k < SUMS; ++k) totals[k] += warp_sums[w][k];
    }
}

// Every round of the gain in one cooperative launch (THREADS threads a block; partials:
// [2][gridDim.x][SUMS], arrivals: 0 at launch), then out = |left - gain x right|, NaN where the
// right mean is. The passes: GAIN, then SPREAD and GAIN again ROUNDS times. GAIN: gain = sum
// left / max(sum right, 1), rounded to float; SPREAD: limit = trim x the mean
// |left - gain x right|, gain_before = gain. Before the first pass the limit is negative (all
// pixels agree).
extern "C" __global__ void __launch_bounds__(THREADS, BLOCKS_PER_MULTIPROCESSOR)
photometric_rounds(const float* left_mean, const float* right_mean, long long size,
                   double trim, double* partials, unsigned* arrivals, float* out) {
    __shared__ double warp_sums[32][SUMS];
    __shared__ GainState shared_state;
    GainState state{-1.0f, -1.0f, -1.0};
    unsigned passed = 0;
    for (int pass = 0; pass <= 2 * ROUNDS; ++pass) {
        double totals[SUMS];
        pass_sums(left_mean, right_mean, size, state, partials + (pass & 1) * gridDim.x * SUMS,
                  arrivals, passed, warp_sums, totals);
        if (threadIdx.x == 0) {
            if (pass % 2 == 0) {
                state.gain = __double2float_rn(totals[SUM_LEFT] / fmax(totals[SUM_RIGHT], 1.0));
            } else {
                state.limit = trim * (totals[SUM_DIFFERENCE] / fmax(totals[SUM_COUNT], 1.0));
                state.gain_before = state.gain;
            }
            shared_state = state;
        }
        __syncthreads();
        state = shared_state;
        __syncthreads();
    }
    const long long stride = (long long)gridDim.x * blockDim.x;
    for (long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x; i < size; i += stride) {
        const float r = right_mean[i];
        out[i] = isfinite(r) ? difference(left_mean[i], r, state.gain)
                             : __int_as_float(0x7fc00000);
    }
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
    total = warp_sum(total);
    weight = warp_sum(weight);
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
