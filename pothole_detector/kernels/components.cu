// Component filters of stages/components.pothole_components on the device: which components
// touch a corner region (components.corner_mask) and which superpixels each one holds.

// One warp per row: first and last column with a disparity (0 and width - 1 without any).
extern "C" __global__ void row_extents(const unsigned char* valid, int height, int width,
                                       int* first, int* last) {
    const int row = blockIdx.x * (blockDim.x / 32) + threadIdx.x / 32;
    const int lane = threadIdx.x & 31;
    if (row >= height) return;
    int low = width, high = -1;
    for (int col = lane; col < width; col += 32) {
        if (valid[(long long)row * width + col]) {
            low = min(low, col);
            high = max(high, col);
        }
    }
#pragma unroll
    for (int offset = 16; offset > 0; offset >>= 1) {
        low = min(low, __shfl_down_sync(0xffffffffu, low, offset));
        high = max(high, __shfl_down_sync(0xffffffffu, high, offset));
    }
    if (lane == 0) {
        first[row] = high >= 0 ? low : 0;
        last[row] = high >= 0 ? high : width - 1;
    }
}

// One thread per pixel of component c > 0: touched[c] = 1 inside a corner region (the top and
// bottom `side` rows, within `side` columns of the row's valid span), present[c][superpixel]
// = 1. Plain stores: every writer writes the same 1.
extern "C" __global__ void component_marks(const int* components, const int* superpixels,
                                           const int* first, const int* last, int height,
                                           int width, int side, int n_superpixels,
                                           unsigned char* touched, unsigned char* present) {
    const long long index = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= (long long)height * width) return;
    const int component = components[index];
    if (component <= 0) return;
    const int row = (int)(index / width), col = (int)(index % width);
    const bool band = row < side || row >= height - side;
    if (side > 0 && band && (col < first[row] + side || col > last[row] - side))
        touched[component] = 1;
    present[(long long)component * n_superpixels + superpixels[index]] = 1;
}
