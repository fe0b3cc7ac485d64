// Block-wide inclusive prefix sum of one value per thread (blockDim.x a multiple of 32, at
// most 1024): the thread's value plus those of every thread before it. `warp_sums` is shared
// scratch of 32 values. Every thread of the block must call it; it ends with a barrier, after
// which warp_sums may be reused.
template <typename T>
__device__ T block_inclusive_scan(T value, T* warp_sums) {
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int offset = 1; offset < 32; offset <<= 1) {
        const T other = __shfl_up_sync(0xffffffffu, value, offset);
        if (lane >= offset) value += other;
    }
    if (lane == 31) warp_sums[warp] = value;
    __syncthreads();
    if (warp == 0) {
        T sum = lane < (int)(blockDim.x >> 5) ? warp_sums[lane] : T(0);
#pragma unroll
        for (int offset = 1; offset < 32; offset <<= 1) {
            const T other = __shfl_up_sync(0xffffffffu, sum, offset);
            if (lane >= offset) sum += other;
        }
        warp_sums[lane] = sum;
    }
    __syncthreads();
    const T before = warp > 0 ? warp_sums[warp - 1] : T(0);
    __syncthreads();
    return value + before;
}
