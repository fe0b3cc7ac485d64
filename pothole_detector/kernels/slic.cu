// SLIC on the device: the assignment and the centre update of stages/superpixels.slic, whose
// NumPy loop is the reference. Distances use the reference's float32 operation order with
// rounded intrinsics (no fused multiply-add), so labels agree with the CPU.
// Defined by the launcher (stages/superpixels.py, _kernel): UPDATE_THREADS.

#include "warp_sum.cuh"

#define FAR_CENTRE 1e9f

// One thread per pixel: the nearest of the centres of its own and the eight surrounding cells.
extern "C" __global__ void slic_assign(const float* filled, const unsigned char* valid,
                                       const float* centre_v, const float* centre_u,
                                       const float* centre_d, int* labels, int height,
                                       int width, int step, int cells_y, int cells_x,
                                       float spatial_weight) {
    const int c = blockIdx.x * blockDim.x + threadIdx.x;
    const int r = blockIdx.y * blockDim.y + threadIdx.y;
    if (c >= width || r >= height) return;
    const int i = r / step, j = c / step;
    const float value = filled[r * width + c];
    const float weight = valid[r * width + c] ? 1.0f : 0.0f;
    float best = __int_as_float(0x7f800000);
    int choice = 0;
#pragma unroll
    for (int k = 0; k < 9; ++k) {
        const int ni = i + k / 3 - 1, nj = j + k % 3 - 1;
        float cv = FAR_CENTRE, cu = FAR_CENTRE, cd = 0.0f;
        if (ni >= 0 && ni < cells_y && nj >= 0 && nj < cells_x) {
            const int index = ni * cells_x + nj;
            cv = centre_v[index]; cu = centre_u[index]; cd = centre_d[index];
        }
        float dd = __fsub_rn(value, cd);
        dd = __fmul_rn(__fmul_rn(dd, dd), weight);
        const float dv = __fsub_rn((float)r, cv), du = __fsub_rn((float)c, cu);
        const float spatial = __fadd_rn(__fmul_rn(dv, dv), __fmul_rn(du, du));
        const float distance = __fadd_rn(dd, __fmul_rn(spatial_weight, spatial));
        if (distance < best) { best = distance; choice = k; }
    }
    labels[r * width + c] = (i + choice / 3 - 1) * cells_x + (j + choice % 3 - 1);
}

static_assert(UPDATE_THREADS % 32 == 0, "the centre update's block: whole warps");

// One block per centre: sums over the pixels of the 3x3 cells around it that chose it, then
// the new centre (position: mean of its pixels; value: mean of its valid pixels). Each warp
// adds its lanes' sums by shuffles, thread 0 the warps' in order.
extern "C" __global__ void __launch_bounds__(UPDATE_THREADS)
slic_update(const float* filled, const unsigned char* valid, const int* labels,
            float* centre_v, float* centre_u, float* centre_d, int height, int width, int step,
            int cells_x) {
    __shared__ double partial[5][UPDATE_THREADS / 32];
    const int label = blockIdx.x;
    const int ci = label / cells_x, cj = label % cells_x;
    const int r0 = max((ci - 1) * step, 0), r1 = min((ci + 2) * step, height);
    const int c0 = max((cj - 1) * step, 0), c1 = min((cj + 2) * step, width);
    const int span = c1 - c0;
    double sums[5] = {0.0, 0.0, 0.0, 0.0, 0.0};
    for (int p = threadIdx.x; p < (r1 - r0) * span; p += blockDim.x) {
        const int r = r0 + p / span, c = c0 + p % span;
        const int index = r * width + c;
        if (labels[index] != label) continue;
        sums[0] += 1.0;
        sums[2] += r;
        sums[3] += c;
        if (valid[index]) {
            sums[1] += 1.0;
            sums[4] += (double)filled[index];
        }
    }
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int q = 0; q < 5; ++q) {
        const double value = warp_sum(sums[q]);
        if (lane == 0) partial[q][warp] = value;
    }
    __syncthreads();
    if (threadIdx.x == 0) {
        double total[5];
#pragma unroll
        for (int q = 0; q < 5; ++q) {
            total[q] = partial[q][0];
            for (int w = 1; w < UPDATE_THREADS / 32; ++w) total[q] += partial[q][w];
        }
        if (total[0] > 0.0) {
            centre_v[label] = (float)(total[2] / total[0]);
            centre_u[label] = (float)(total[3] / total[0]);
        }
        if (total[1] > 0.0) centre_d[label] = (float)(total[4] / total[1]);
    }
}

// One thread per cell: the cell-middle centre (clamped to the image) moved to the lowest
// gradient (dv^2 + du^2 of central differences, edge-replicated; invalid pixels never win) of
// its 3x3 neighbourhood, first in raster order on ties; its value is filled at the new centre.
extern "C" __global__ void slic_start(const float* filled, const unsigned char* valid,
                                      float* centre_v, float* centre_u, float* centre_d,
                                      int height, int width, int step, int cells_y,
                                      int cells_x) {
    const int cell = blockIdx.x * blockDim.x + threadIdx.x;
    if (cell >= cells_y * cells_x) return;
    const int v0 = min((cell / cells_x) * step + step / 2, height - 1);
    const int u0 = min((cell % cells_x) * step + step / 2, width - 1);
    float best = 0.0f;
    int best_v = 0, best_u = 0;
    for (int k = 0; k < 9; ++k) {
        const int v = min(max(v0 + k / 3 - 1, 0), height - 1);
        const int u = min(max(u0 + k % 3 - 1, 0), width - 1);
        float gradient = __int_as_float(0x7f800000);
        if (valid[v * width + u]) {
            const float du = __fsub_rn(filled[v * width + min(u + 1, width - 1)],
                                       filled[v * width + max(u - 1, 0)]);
            const float dv = __fsub_rn(filled[min(v + 1, height - 1) * width + u],
                                       filled[max(v - 1, 0) * width + u]);
            gradient = __fadd_rn(__fmul_rn(du, du), __fmul_rn(dv, dv));
        }
        if (k == 0 || gradient < best) {
            best = gradient;
            best_v = v;
            best_u = u;
        }
    }
    centre_v[cell] = (float)best_v;
    centre_u[cell] = (float)best_u;
    centre_d[cell] = filled[best_v * width + best_u];
}

// Per-superpixel count, valid count and sum of valid values of an HxW float32 map (NaN
// invalid), float64 sums[n][3]; each warp adds once per distinct label among its pixels (the
// counts from its ballots, the sum by shuffles).
extern "C" __global__ void superpixel_sums(const float* image, const int* labels, long long size,
                                           double* sums) {
    const long long index = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const bool inside = index < size;
    const int label = inside ? labels[index] : -1;
    const float value = inside ? image[index] : 0.0f;
    const bool valid = inside && (__float_as_uint(value) & 0x7f800000u) != 0x7f800000u;
    const int lane = threadIdx.x & 31;
    unsigned remaining = __ballot_sync(0xffffffffu, inside);
    while (remaining) {
        const int leader = __ffs(remaining) - 1;
        const int target = __shfl_sync(0xffffffffu, label, leader);
        const bool mine = inside && label == target;
        const unsigned group = __ballot_sync(0xffffffffu, mine);
        const unsigned group_valid = __ballot_sync(0xffffffffu, mine && valid);
        remaining &= ~group;
        double total = mine && valid ? (double)value : 0.0;
#pragma unroll
        for (int offset = 16; offset > 0; offset >>= 1)
            total += __shfl_down_sync(0xffffffffu, total, offset);
        const double group_total = __shfl_sync(0xffffffffu, total, 0);
        if (lane == leader) {
            atomicAdd(&sums[target * 3], (double)__popc(group));
            atomicAdd(&sums[target * 3 + 1], (double)__popc(group_valid));
            atomicAdd(&sums[target * 3 + 2], group_total);
        }
    }
}

// Mean of the valid values (NaN where none) and valid fraction per superpixel, float32.
extern "C" __global__ void superpixel_finish(const double* sums, float* mean, float* fraction,
                                             int n) {
    const int label = blockIdx.x * blockDim.x + threadIdx.x;
    if (label >= n) return;
    const double count = sums[label * 3], count_valid = sums[label * 3 + 1];
    mean[label] = count_valid > 0.0 ? (float)(sums[label * 3 + 2] / count_valid)
                                    : __int_as_float(0x7fc00000);
    fraction[label] = (float)(count_valid / fmax(count, 1.0));
}

// The SLIC input of stages/superpixels.superpixel_grid in one pass over D2: the mean of the
// finite values of each factor x factor block (float32, 0 where the block is not at least
// half valid) and the block's validity (at least half of its values finite).
extern "C" __global__ void slic_block_mean(const float* image, int width, int factor,
                                           int small_height, int small_width, float* filled,
                                           unsigned char* valid) {
    const int c = blockIdx.x * blockDim.x + threadIdx.x;
    const int r = blockIdx.y * blockDim.y + threadIdx.y;
    if (c >= small_width || r >= small_height) return;
    float total = 0.0f;
    int count = 0;
    for (int dr = 0; dr < factor; ++dr)
        for (int dc = 0; dc < factor; ++dc) {
            const float value = image[(long long)(r * factor + dr) * width + c * factor + dc];
            if ((__float_as_uint(value) & 0x7f800000u) != 0x7f800000u) {
                total = __fadd_rn(total, value);
                ++count;
            }
        }
    const bool enough = count * 2 >= factor * factor;
    const long long index = (long long)r * small_width + c;
    filled[index] = enough ? (float)((double)total / (double)count) : 0.0f;
    valid[index] = enough;
}

// Nearest-neighbour enlargement (stages/superpixels.upsample_labels): pixel (r, c) takes
// label (min(r / factor, small_height - 1), min(c / factor, small_width - 1)).
extern "C" __global__ void upsample_labels(const int* small, int small_height, int small_width,
                                           int factor, int height, int width, int* labels) {
    const int c = blockIdx.x * blockDim.x + threadIdx.x;
    const int r = blockIdx.y * blockDim.y + threadIdx.y;
    if (c >= width || r >= height) return;
    labels[(long long)r * width + c] =
        small[min(r / factor, small_height - 1) * small_width + min(c / factor, small_width - 1)];
}
