// The sum of each lane's `value` over the 32 lanes of a warp, in lane 0 (added as a tree of
// shuffles down, the same order every time, so the same values give the same bits).
__device__ __forceinline__ double warp_sum(double value) {
#pragma unroll
    for (int offset = 16; offset > 0; offset >>= 1)
        value += __shfl_down_sync(0xffffffffu, value, offset);
    return value;
}
