// Barrier over every thread of a cooperatively launched grid (every block resident).
// `arrivals` (global, 0 at launch) counts the blocks' arrivals; `passed`, this thread's count
// of the barriers it has passed (every thread makes the same calls, so the counts agree).
// Orders global memory accesses: released before arriving, acquired after the wait.
__device__ __forceinline__ void grid_barrier(unsigned* arrivals, unsigned& passed) {
    __syncthreads();
    passed += 1;
    if (threadIdx.x == 0) {
        const unsigned target = passed * gridDim.x;
        __threadfence();
        atomicAdd(arrivals, 1u);
        unsigned seen;
        do {
            asm volatile("ld.acquire.gpu.global.u32 %0, [%1];" : "=r"(seen) : "l"(arrivals)
                         : "memory");
        } while (seen < target);
    }
    __syncthreads();
}
