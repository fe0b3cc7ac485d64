// Pixel-level refinement (stages/refine.py, whose NumPy code is the reference), one thread per
// pixel.
// refine_smooth: the mean of the valid (finite) disparities of the SMOOTHING x SMOOTHING
//   square about each pixel, clipped at the image border: filled (NaN where none is valid)
//   and smoothed (NaN where the pixel itself is invalid).
// refine_grow: a labelled pixel keeps its label; an unlabelled one whose superpixel is observed
//   and whose transformed filled disparity (as kernels/transform.cu computes it) lies more
//   than fraction x its superpixel's drop below delta takes the largest label within `radius`
//   (a square, clipped); else 0.
// refine_occluded: out holds a copy of labels; the thread of the right end u of a labelled run
//   of a row (its right neighbour unlabelled) labels in out the unlabelled pixels u + k,
//   0 < k <= road disparity at u + 1 less filled at u - (SMOOTHING - 1), up to the next
//   labelled pixel, whose superpixel is observed, and sets smoothed NaN there (no other thread
//   writes those pixels).
// Defined by the launcher (stages/refine.py, _kernel): SMOOTHING and the road parameters'
// layout (ROAD_*).
#include "road_disparity.cuh"

extern "C" __global__ void refine_smooth(const float* disparity, int height, int width,
                                         float* filled, float* smoothed) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const int half = SMOOTHING / 2;
    float total = 0.0f;
    int count = 0;
    for (int r = max(row - half, 0); r <= min(row + half, height - 1); ++r)
        for (int c = max(col - half, 0); c <= min(col + half, width - 1); ++c) {
            const float value = disparity[(long long)r * width + c];
            if (isfinite(value)) {
                total += value;
                ++count;
            }
        }
    const long long index = (long long)row * width + col;
    const float mean = count > 0 ? total / count : __int_as_float(0x7fc00000);
    filled[index] = mean;
    smoothed[index] = isfinite(disparity[index]) ? mean : __int_as_float(0x7fc00000);
}

extern "C" __global__ void refine_grow(const int* labels, const float* filled,
                                       const int* superpixels, const double* drops,
                                       const bool* observed, const double* road, float delta,
                                       double fraction, int radius, int height, int width,
                                       int* out) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const long long index = (long long)row * width + col;
    if (labels[index] > 0) {
        out[index] = labels[index];
        return;
    }
    const float road_value = __double2float_rn(road_disparity(road, col, row));
    const float transformed = __fadd_rn(__fsub_rn(filled[index], road_value), delta);
    const float below = __fsub_rn(delta, transformed);
    const int superpixel = superpixels[index];
    int found = 0;
    if (observed[superpixel] && (double)below > fraction * drops[superpixel]) {
        for (int r = max(row - radius, 0); r <= min(row + radius, height - 1); ++r)
            for (int c = max(col - radius, 0); c <= min(col + radius, width - 1); ++c)
                found = max(found, labels[(long long)r * width + c]);
    }
    out[index] = found;
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
