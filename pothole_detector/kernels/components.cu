// Component filters of stages/components.pothole_components on the device: which superpixels
// each component holds and which components touch a bump; the valid spans of the far corners
// (components.far_corners).

#include "block_scan.cuh"

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

// The component of full-resolution pixel (row, col) from labels on a grid reduced by
// `factor` (pixels past the enlarged grid take the last row or column).
__device__ __forceinline__ int component_at(const int* small, int row, int col, int factor,
                                            int small_height, int small_width) {
    return small[min(row / factor, small_height - 1) * small_width
                 + min(col / factor, small_width - 1)];
}

// One thread per pixel of component c > 0: bit s of present[c]
// (words_per_component words) marks superpixel s, and held[c] counts the distinct ones (the
// thread whose atomicOr sets the bit adds 1; a plain read first spares the atomic once the
// bit is set), inconsistent[c] those of them flagged in `flagged` (one byte per superpixel).
// touched[c] = 1 where a pixel of c is an 8-neighbour of a pixel off every component whose
// superpixel is flagged in `bumps` (one byte per superpixel). Components past `capacity` (the
// tables' size) set touched[0], the overflow flag; the caller then runs again with a larger
// capacity.
extern "C" __global__ void component_marks(const int* small, const int* superpixels,
                                           const bool* flagged, const bool* bumps,
                                           int height, int width, int factor,
                                           int small_height, int small_width,
                                           int words_per_component, int capacity, int* touched,
                                           int* held, int* inconsistent, unsigned* present) {
    const long long index = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= (long long)height * width) return;
    const int row = (int)(index / width), col = (int)(index % width);
    const int component = component_at(small, row, col, factor, small_height, small_width);
    if (component <= 0) return;
    if (component > capacity) {
        touched[0] = 1;
        return;
    }
    for (int dv = -1; dv <= 1; ++dv) {
        for (int du = -1; du <= 1; ++du) {
            const int v = row + dv, u = col + du;
            if ((dv == 0 && du == 0) || v < 0 || v >= height || u < 0 || u >= width) continue;
            if (component_at(small, v, u, factor, small_height, small_width) == 0
                && bumps[superpixels[(long long)v * width + u]])
                touched[component] = 1;
        }
    }
    const int superpixel = superpixels[index];
    const unsigned bit = 1u << (superpixel & 31);
    unsigned* word = present + (long long)component * words_per_component + (superpixel >> 5);
    if (!(*word & bit) && !(atomicOr(word, bit) & bit)) {
        atomicAdd(&held[component], 1);
        if (flagged[superpixel]) atomicAdd(&inconsistent[component], 1);
    }
}

// One block: component c (1..count, count = min(*components, capacity)) is kept when it
// touches no bump, holds at least min_superpixels superpixels and no more than half of them
// are inconsistent; new_id[c] (capacity + 1 entries) numbers the kept ones 1..m in order (0
// otherwise); kept[0] = m.
extern "C" __global__ void component_keep(const int* touched, const int* held,
                                          const int* inconsistent, const int* components,
                                          int capacity, int min_superpixels, int* new_id,
                                          int* kept) {
    __shared__ int warp_totals[32];
    __shared__ int carry;
    const int count = min(components[0], capacity);
    if (threadIdx.x == 0) carry = 0;
    __syncthreads();
    for (int start = 0; start <= capacity; start += blockDim.x) {
        const int component = start + threadIdx.x;
        const int flag = component > 0 && component <= count && !touched[component]
                         && held[component] >= min_superpixels
                         && 2 * inconsistent[component] <= held[component];
        const int inclusive = block_inclusive_scan(flag, warp_totals) + carry;
        if (component <= capacity) new_id[component] = flag ? inclusive : 0;
        __syncthreads();
        if (threadIdx.x == blockDim.x - 1) carry = inclusive;
        __syncthreads();
    }
    if (threadIdx.x == 0) kept[0] = carry;
}

// Final labels: new_id of each full-resolution pixel's component (0 past the capacity).
extern "C" __global__ void component_relabel(const int* small, const int* new_id, int* labels,
                                             int height, int width, int factor,
                                             int small_height, int small_width, int capacity) {
    const long long index = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= (long long)height * width) return;
    const int row = (int)(index / width), col = (int)(index % width);
    const int component = component_at(small, row, col, factor, small_height, small_width);
    labels[index] = component <= capacity ? new_id[component] : 0;
}

// Connected components (8-connectivity) by union-find on parent indices: every pixel of the
// mask links to its earlier neighbours (west, north-west, north, north-east); a root always
// links to the smaller root, so each component's root is its first pixel in raster order and
// numbering roots in index order gives scipy.ndimage.label's numbering.
__device__ __forceinline__ int find_root(const int* parent, int x) {
    while (true) {
        const int up = parent[x];
        if (up == x) return x;
        x = up;
    }
}

// find_root with path halving: each visited node is pointed at its grandparent. Only nodes
// that are no longer roots are written, and always to one of their ancestors, so concurrent
// finds and links stay correct.
__device__ __forceinline__ int find_root_halving(int* parent, int x) {
    while (true) {
        const int up = parent[x];
        if (up == x) return x;
        const int grand = parent[up];
        if (grand != up) parent[x] = grand;
        x = grand;
    }
}

extern "C" __global__ void label_init(const unsigned char* mask, int* parent, int size) {
    const int index = blockIdx.x * blockDim.x + threadIdx.x;
    if (index < size) parent[index] = mask[index] ? index : -1;
}

extern "C" __global__ void label_merge(int* parent, int height, int width) {
    const int index = blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= height * width || parent[index] < 0) return;
    const int row = index / width, col = index % width;
    const int neighbours[4][2] = {{0, -1}, {-1, -1}, {-1, 0}, {-1, 1}};
    for (int n = 0; n < 4; ++n) {
        const int r = row + neighbours[n][0], c = col + neighbours[n][1];
        if (r < 0 || c < 0 || c >= width) continue;
        const int other = r * width + c;
        if (parent[other] < 0) continue;
        int a = find_root_halving(parent, index), b = find_root_halving(parent, other);
        while (a != b) {
            if (a < b) {
                const int swap = a;
                a = b;
                b = swap;
            }
            const int seen = atomicCAS(&parent[a], a, b);
            if (seen == a) break;
            a = find_root_halving(parent, seen);
            b = find_root_halving(parent, b);
        }
    }
}

// parent[i] becomes the root of i; is_root[i] = 1 for roots.
extern "C" __global__ void label_flatten(int* parent, int* is_root, int size) {
    const int index = blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= size) return;
    const int up = parent[index];
    if (up < 0) {
        is_root[index] = 0;
        return;
    }
    const int root = find_root(parent, index);
    is_root[index] = root == index;
    parent[index] = root;
}

// labels[i] = number of the root of i (1-based: inclusive count of roots up to it), 0 off
// the mask.
extern "C" __global__ void label_number(const int* parent, const int* root_count, int* labels,
                                        int size) {
    const int index = blockIdx.x * blockDim.x + threadIdx.x;
    if (index >= size) return;
    const int root = parent[index];
    labels[index] = root < 0 ? 0 : root_count[root];
}

// join_pieces (stages/components.py, whose array code is the reference) on the grid reduced by
// `factor` (rows x cols cells), one thread per cell or pixel:
// join_cells: a cell is on where any pixel of its factor x factor square is labelled.
// join_rows: the cells' running maxima along the row within `reach` and `bridge_reach`.
// join_near: those along the column: a cell is near where an on cell lies within `reach`
//   (rows and columns), or where it is depressed (bridging, and inside the rows_in x cols_in
//   SLIC grid) with an on cell within `bridge_reach`.
// join_holds: holds[k] where an on cell is labelled k.
// join_labels: each labelled pixel takes its cell's joined label, through `table` where given.
extern "C" __global__ void join_cells(const int* labels, int height, int width, int factor,
                                      int rows, int cols, unsigned char* cells) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= rows * cols) return;
    const int top = (k / cols) * factor, left = (k % cols) * factor;
    unsigned char on = 0;
    for (int r = top; r < min(top + factor, height); ++r)
        for (int c = left; c < min(left + factor, width); ++c)
            on |= labels[(long long)r * width + c] > 0;
    cells[k] = on;
}

extern "C" __global__ void join_rows(const unsigned char* cells, int rows, int cols, int reach,
                                     int bridge_reach, unsigned char* near_rows,
                                     unsigned char* bridge_rows) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= rows * cols) return;
    const int j = k % cols, widest = max(reach, bridge_reach);
    const unsigned char* row = cells + (k - j);
    unsigned char near = 0, bridge = 0;
    for (int c = max(j - widest, 0); c <= min(j + widest, cols - 1); ++c) {
        const unsigned char on = row[c];
        if (abs(c - j) <= reach) near |= on;
        if (abs(c - j) <= bridge_reach) bridge |= on;
    }
    near_rows[k] = near;
    bridge_rows[k] = bridge;
}

extern "C" __global__ void join_near(const unsigned char* near_rows,
                                     const unsigned char* bridge_rows, int rows, int cols,
                                     int reach, int bridge_reach, const bool* depressed,
                                     const int* grid, int rows_in, int cols_in, int bridging,
                                     bool* near) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= rows * cols) return;
    const int i = k / cols, j = k % cols;
    bool found = false;
    for (int r = max(i - reach, 0); r <= min(i + reach, rows - 1) && !found; ++r)
        found = near_rows[r * cols + j] != 0;
    if (!found && bridging && i < rows_in && j < cols_in && depressed[grid[i * cols_in + j]]) {
        for (int r = max(i - bridge_reach, 0); r <= min(i + bridge_reach, rows - 1) && !found;
             ++r)
            found = bridge_rows[r * cols + j] != 0;
    }
    near[k] = found;
}

extern "C" __global__ void join_holds(const int* joined, const unsigned char* cells, int size,
                                      bool* holds) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k < size && cells[k] && joined[k] > 0) holds[joined[k]] = true;
}

extern "C" __global__ void join_labels(const int* labels, const int* joined, const int* table,
                                       int use_table, int height, int width, int factor,
                                       int rows, int cols, int* out) {
    const int c = blockIdx.x * blockDim.x + threadIdx.x;
    const int r = blockIdx.y * blockDim.y + threadIdx.y;
    if (c >= width || r >= height) return;
    const long long index = (long long)r * width + c;
    int label = 0;
    if (labels[index] > 0) {
        label = joined[min(r / factor, rows - 1) * cols + min(c / factor, cols - 1)];
        if (use_table) label = table[label];
    }
    out[index] = label;
}
