// Probe of row sweeps (docs/gpu-notes.md, thirteenth and fourteenth sessions; not used by the
// package): one launch walks the image's rows down (kind 2) and up (kind 3), three directions
// at once (the vertical and both diagonals of that sense), each pixel's matching cost once, and
// writes the three path costs' sum as one byte per level (uint8 HxWxLEVELS per sense); kinds 0
// and 1 walk the rows left to right and right to left, a group a row, each direction's path
// costs into a volume of its own (out_right, out_left), so that one launch (kinds 0 to 3) holds
// all eight directions in four volumes with no read-modify-write. A block holds COLS columns
// (rows for kinds 0 and 1) of 16 lanes (6 levels each at LEVELS 96); the diagonals' states of
// the row above lie in shared memory. Block-edge columns: EXCHANGE 0 and CLUSTER 0 leave them
// stale (timing only); EXCHANGE 2 hands edge states to the neighbouring blocks every row
// through global memory as 64-bit words that carry their row and the launch's epoch (edges:
// uint64 2 x blocks x 2 x 4 x LEVELS / 2; no fence, no flag; *failed set where a wait gave
// up); CLUSTER n reads them from the neighbouring block's shared memory in clusters of n
// blocks (exact within a cluster). Census words ROWS_AHEAD rows (steps) ahead. (EXCHANGE 1,
// edge states and a row flag per block through global memory with fences and atomics, is in
// this file at commit 423382f; docs/gpu-notes.md has its times.)
// Built on sgm.cu (LEVELS, LANES 16 and the census defines given; its PER_LANE, PAIRS,
// FAR_HALF, pack_costs, group_minimum and invalid_word used as they are; nvcc: -I its
// folder, probe_row_sweeps.py inlines it).
#include "sgm.cu"
static_assert(LANES == 16 && PACKED, "the probe: 16 lanes of packed level pairs");
#ifndef EXCHANGE
#define EXCHANGE 0
#endif
#ifndef COLS
#define COLS 32
#endif
#ifndef ROWS_AHEAD
#define ROWS_AHEAD 1
#endif
#define WORDS (LEVELS / 2)

// One packed path step of one direction, as sgm.cu's walk_paths takes it (there inside the
// walk's step): prev the source pixel's pairs, below / above the levels beside the lane's.
__device__ __forceinline__ unsigned step_dir(const unsigned (&prev)[PAIRS], unsigned below,
                                             unsigned above, unsigned minimum,
                                             const unsigned (&cost)[PAIRS], unsigned p1_pair,
                                             unsigned p2_pair, unsigned (&out)[PAIRS]) {
    unsigned shifted[PAIRS + 1];
    shifted[0] = __funnelshift_l(below, prev[0], 16);
#pragma unroll
    for (int p = 1; p < PAIRS; ++p) shifted[p] = __funnelshift_l(prev[p - 1], prev[p], 16);
    shifted[PAIRS] = __funnelshift_l(prev[PAIRS - 1], above, 16);
    const unsigned jump = minimum + p2_pair - p1_pair;
#pragma unroll
    for (int p = 0; p < PAIRS; ++p) {
        const unsigned neighbours = __vimin3_u16x2(shifted[p], shifted[p + 1], jump);
        const unsigned best = __viaddmin_u16x2(neighbours, p1_pair, prev[p]);
        out[p] = cost[p] + best - minimum;
    }
    unsigned least = out[0];
#pragma unroll
    for (int p = 1; p < PAIRS; ++p) least = __vminu2(least, out[p]);
    return __vminu2(least, __byte_perm(least, 0u, 0x1032));
}


// One step's census words: the left word at `u` of its row and the right words of the lane's
// levels, `base` - k for level first + k (invalid_word(left) left of the row's start).
__device__ __forceinline__ void load_words(const unsigned* row_left, const unsigned* row_right,
                                           int u, int base, unsigned& left,
                                           unsigned (&right)[PER_LANE]) {
    left = row_left[u];
    const unsigned outside = invalid_word(left);
#pragma unroll
    for (int k = 0; k < PER_LANE; ++k) right[k] = base - k >= 0 ? row_right[base - k] : outside;
}

// The lane's matching costs as level pairs (levels first + 2p and first + 2p + 1).
__device__ __forceinline__ void pair_costs(unsigned left, const unsigned (&right)[PER_LANE],
                                           unsigned (&cost)[PAIRS]) {
#pragma unroll
    for (int p = 0; p < PAIRS; ++p)
        cost[p] = pack_costs(__popc(left ^ right[2 * p]), __popc(left ^ right[2 * p + 1]));
}

// One horizontal walk a group (rows blockIdx.x * COLS + group), its direction's path costs
// as one byte per level (uint8 HxWxLEVELS); census ROWS_AHEAD steps ahead.
__device__ __forceinline__ void horizontal_walk(const unsigned* __restrict__ census_left,
                                                const unsigned* __restrict__ census_right,
                                                const int* __restrict__ kappa,
                                                unsigned char* out, int height, int width,
                                                int p1, int p2, bool leftward) {
    const int group = threadIdx.x / LANES, sub = threadIdx.x % LANES;
    if ((int)blockIdx.x * COLS >= height) return;
    const int v = blockIdx.x * COLS + group;
    const int vc = min(v, height - 1);
    const int first = sub * PER_LANE;
    const int shift = kappa[vc];
    const unsigned* row_left = census_left + (size_t)vc * width;
    const unsigned* row_right = census_right + (size_t)vc * width;
    unsigned char* row_out = out + (size_t)vc * width * LEVELS + first;
    const unsigned p1_pair = (unsigned)p1 * 0x10001u, p2_pair = (unsigned)p2 * 0x10001u;
    unsigned previous[PAIRS];
#pragma unroll
    for (int p = 0; p < PAIRS; ++p) previous[p] = 0u;
    unsigned minimum = 0u;
    const int du = leftward ? -1 : 1;
    unsigned set_left[ROWS_AHEAD], set_right[ROWS_AHEAD][PER_LANE];
    auto load = [&](int u, unsigned& left, unsigned (&right)[PER_LANE]) {
        load_words(row_left, row_right, u, u - first - shift, left, right);
    };
    int u = leftward ? width - 1 : 0;
#pragma unroll
    for (int j = 0; j < ROWS_AHEAD; ++j)
        if (j < width) load(u + j * du, set_left[j], set_right[j]);
#pragma unroll 1
    for (int s0 = 0; s0 < width; s0 += ROWS_AHEAD) {
#pragma unroll
        for (int j = 0; j < ROWS_AHEAD; ++j) {
            if (s0 + j >= width) break;
            unsigned cost[PAIRS];
            pair_costs(set_left[j], set_right[j], cost);
            if (s0 + j + ROWS_AHEAD < width) load(u + ROWS_AHEAD * du, set_left[j], set_right[j]);
            unsigned below = __shfl_up_sync(0xffffffffu, previous[PAIRS - 1], 1, LANES);
            unsigned above = __shfl_down_sync(0xffffffffu, previous[0], 1, LANES);
            if (sub == 0) below = FAR_HALF << 16;
            if (sub == LANES - 1) above = FAR_HALF;
            unsigned next[PAIRS];
            const unsigned least = step_dir(previous, below, above, minimum, cost, p1_pair,
                                            p2_pair, next);
            if (v < height) {
#pragma unroll
                for (int p = 0; p < PAIRS; ++p)
                    __stcs(reinterpret_cast<unsigned short*>(row_out + (size_t)u * LEVELS) + p,
                           (unsigned short)__byte_perm(next[p], 0u, 0x3320));
            }
#pragma unroll
            for (int p = 0; p < PAIRS; ++p) previous[p] = next[p];
            minimum = group_minimum<LANES>(least);
            u += du;
        }
    }
}

// EXCHANGE 2: edge states handed over through L2 as 64-bit words {state pair, tag}, the tag
// (high 16 bits) the launch's epoch and the row, the path minimum's half beside it, so that
// no fence or flag is needed: a consumer polls its words until all carry the row's tag.
__device__ __forceinline__ void publish(unsigned long long* at, unsigned pair, unsigned tag) {
    asm volatile("st.relaxed.gpu.global.u64 [%0], %1;"
                 : : "l"(at), "l"(((unsigned long long)tag << 32) | pair) : "memory");
}
__device__ __forceinline__ unsigned long long peek(const unsigned long long* at) {
    unsigned long long x;
    asm volatile("ld.relaxed.gpu.global.u64 %0, [%1];" : "=l"(x) : "l"(at) : "memory");
    return x;
}
// the PAIRS words at `at` once every one carries `tag` (high 16 bits of the high word);
// gives up after a bounded wait (a probe must not hang), flagging *failed
__device__ __forceinline__ unsigned receive(const unsigned long long* at, unsigned tag,
                                            unsigned (&pairs)[PAIRS], unsigned* failed) {
    unsigned long long w[PAIRS];
    bool ready;
    int tries = 0;
    do {
#pragma unroll
        for (int p = 0; p < PAIRS; ++p) w[p] = peek(at + p);
        ready = true;
#pragma unroll
        for (int p = 0; p < PAIRS; ++p) ready = ready && (unsigned)(w[p] >> 48) == tag;
    } while (!ready && ++tries < (1 << 22));
    if (!ready) atomicExch(failed, 1u);
#pragma unroll
    for (int p = 0; p < PAIRS; ++p) pairs[p] = (unsigned)w[p];
    return ((unsigned)(w[0] >> 32) & 0xffffu) * 0x10001u;
}

#ifndef CLUSTER
#define CLUSTER 0
#endif
__device__ __forceinline__ void cluster_barrier() {
    asm volatile("barrier.cluster.arrive.release.aligned;\n\t"
                 "barrier.cluster.wait.acquire.aligned;" ::: "memory");
}
template <typename T>
__device__ __forceinline__ T* cluster_map(T* pointer, unsigned rank) {
    T* out;
    asm volatile("mapa.u64 %0, %1, %2;" : "=l"(out) : "l"(pointer), "r"(rank));
    return out;
}
__device__ __forceinline__ unsigned cluster_rank() {
    unsigned r;
    asm volatile("mov.u32 %0, %%cluster_ctarank;" : "=r"(r));
    return r;
}
extern "C" __global__ void __launch_bounds__(COLS * LANES)
#if CLUSTER
__cluster_dims__(CLUSTER, 1, 1)
#endif
sweep_probe(const unsigned* __restrict__ census_left, const unsigned* __restrict__ census_right,
            const int* __restrict__ kappa, unsigned char* out_down, unsigned char* out_up,
            int height, int width, int p1, int p2, unsigned* edges, unsigned* failed,
            unsigned char* out_right, unsigned char* out_left, unsigned epoch, int first_kind) {
    // kind (blockIdx.y + first_kind): 0 / 1 the horizontal walks (left to right, right to
    // left), 2 / 3 the downward / upward sweeps
    const int kind = blockIdx.y + first_kind;
    if (kind < 2) {
        horizontal_walk(census_left, census_right, kappa, kind ? out_left : out_right, height,
                        width, p1, p2, kind == 1);
        return;
    }
    // EXCHANGE 2: block-edge states handed to the neighbouring blocks through global memory
    // every row (ring of 4 rows per edge)
    __shared__ unsigned diag[2][2][COLS + 2][WORDS];
    __shared__ unsigned diag_min[2][2][COLS + 2];
    const bool up = kind == 3;
    [[maybe_unused]] const int sweep = kind - 2;
    [[maybe_unused]] const unsigned sweep_blocks = (width + COLS - 1) / COLS;
#if !CLUSTER
    // (a cluster's blocks all stay: each takes part in every cluster barrier)
    if (blockIdx.x >= sweep_blocks) return;
#endif
    const int group = threadIdx.x / LANES, sub = threadIdx.x % LANES;
    const int u = blockIdx.x * COLS + group;
    const int uc = min(u, width - 1);
    const int first = sub * PER_LANE;
    unsigned char* out = (up ? out_up : out_down) + first;
    for (int i = threadIdx.x; i < 2 * 2 * (COLS + 2) * WORDS; i += blockDim.x)
        (&diag[0][0][0][0])[i] = 0u;
    for (int i = threadIdx.x; i < 2 * 2 * (COLS + 2); i += blockDim.x)
        (&diag_min[0][0][0])[i] = 0u;
    __syncthreads();
#if CLUSTER
    cluster_barrier();
#endif
    const unsigned p1_pair = (unsigned)p1 * 0x10001u, p2_pair = (unsigned)p2 * 0x10001u;
    unsigned vert[PAIRS];
#pragma unroll
    for (int p = 0; p < PAIRS; ++p) vert[p] = 0u;
    unsigned vert_min = 0u;
    const int dv = up ? -1 : 1;
    int v = up ? height - 1 : 0;
    // census loaded ROWS_AHEAD rows ahead into rotating register sets
    unsigned set_left[ROWS_AHEAD], set_right[ROWS_AHEAD][PER_LANE];
    auto load = [&](int row, unsigned& left, unsigned (&right)[PER_LANE]) {
        load_words(census_left + (size_t)row * width, census_right + (size_t)row * width, uc,
                   uc - first - kappa[row], left, right);
    };
#pragma unroll
    for (int j = 0; j < ROWS_AHEAD; ++j)
        if (j < height) load(v + j * dv, set_left[j], set_right[j]);
#pragma unroll 1
    for (int r0 = 0; r0 < height; r0 += ROWS_AHEAD) {
#pragma unroll
        for (int j = 0; j < ROWS_AHEAD; ++j) {
            const int r = r0 + j;
            if (r >= height) break;
            const int parity = r & 1;
            unsigned cost[PAIRS];
            pair_costs(set_left[j], set_right[j], cost);
            if (r + ROWS_AHEAD < height) load(v + ROWS_AHEAD * dv, set_left[j], set_right[j]);
            unsigned below = __shfl_up_sync(0xffffffffu, vert[PAIRS - 1], 1, LANES);
            unsigned above = __shfl_down_sync(0xffffffffu, vert[0], 1, LANES);
            if (sub == 0) below = FAR_HALF << 16;
            if (sub == LANES - 1) above = FAR_HALF;
            unsigned nv[PAIRS], ntl[PAIRS], ntr[PAIRS];
            const unsigned lv = step_dir(vert, below, above, vert_min, cost, p1_pair, p2_pair, nv);
            const unsigned* tl = diag[parity][0][group];
            const unsigned* tr = diag[parity][1][group + 2];
            const unsigned* tl_min = &diag_min[parity][0][group];
            const unsigned* tr_min = &diag_min[parity][1][group + 2];
#if CLUSTER
            {
                // block-edge columns read the neighbouring block's edge column in its shared
                // memory
                const unsigned rank = cluster_rank();
                if (group == 0 && rank > 0) {
                    tl = cluster_map(&diag[parity][0][COLS][0], rank - 1);
                    tl_min = cluster_map(&diag_min[parity][0][COLS], rank - 1);
                }
                if (group == COLS - 1 && rank + 1 < CLUSTER) {
                    tr = cluster_map(&diag[parity][1][1][0], rank + 1);
                    tr_min = cluster_map(&diag_min[parity][1][1], rank + 1);
                }
            }
#endif
            unsigned ptl[PAIRS], ptr[PAIRS];
#pragma unroll
            for (int p = 0; p < PAIRS; ++p) {
                ptl[p] = tl[first / 2 + p];
                ptr[p] = tr[first / 2 + p];
            }
            const unsigned btl = sub ? tl[first / 2 - 1] : FAR_HALF << 16;
            const unsigned atl = sub < LANES - 1 ? tl[first / 2 + PAIRS] : FAR_HALF;
            const unsigned btr = sub ? tr[first / 2 - 1] : FAR_HALF << 16;
            const unsigned atr = sub < LANES - 1 ? tr[first / 2 + PAIRS] : FAR_HALF;
            const unsigned ltl = step_dir(ptl, btl, atl, *tl_min, cost, p1_pair,
                                          p2_pair, ntl);
            const unsigned ltr = step_dir(ptr, btr, atr, *tr_min, cost,
                                          p1_pair, p2_pair, ntr);
            unsigned char* cell = out + ((size_t)v * width + uc) * LEVELS;
            if (u < width) {
#pragma unroll
                for (int p = 0; p < PAIRS; ++p) {
                    const unsigned bytes = __byte_perm(nv[p], 0u, 0x3320)
                                           + __byte_perm(ntl[p], 0u, 0x3320)
                                           + __byte_perm(ntr[p], 0u, 0x3320);
                    __stcs(reinterpret_cast<unsigned short*>(cell) + p, (unsigned short)bytes);
                }
            }
            vert_min = group_minimum<LANES>(lv);
            const unsigned mtl = group_minimum<LANES>(ltl), mtr = group_minimum<LANES>(ltr);
#if EXCHANGE == 2
            // [sweep][block][side 0: rightmost column's TL state, 1: leftmost's TR][row % 4]
            // [WORDS]
            const unsigned tag = (epoch & 31u) << 11 | (unsigned)(r + 1);
            unsigned long long* const ring64 = reinterpret_cast<unsigned long long*>(edges);
            auto slot_of = [&](int block, int side) {
                return ring64 + ((((size_t)sweep * sweep_blocks + block) * 2 + side) * 4 + (r & 3))
                                    * WORDS + first / 2;
            };
            if (group == COLS - 1 && blockIdx.x + 1 < sweep_blocks) {
#pragma unroll
                for (int p = 0; p < PAIRS; ++p)
                    publish(slot_of(blockIdx.x, 0) + p, ntl[p], tag << 16 | (mtl & 0xffffu));
            }
            if (group == 0 && blockIdx.x > 0) {
#pragma unroll
                for (int p = 0; p < PAIRS; ++p)
                    publish(slot_of(blockIdx.x, 1) + p, ntr[p], tag << 16 | (mtr & 0xffffu));
            }
#endif
            // columns right of the image: a fresh start for the down-left diagonal beside them
            const bool real = u < width;
#pragma unroll
            for (int p = 0; p < PAIRS; ++p) {
                vert[p] = nv[p];
                diag[parity ^ 1][0][group + 1][first / 2 + p] = real ? ntl[p] : 0u;
                diag[parity ^ 1][1][group + 1][first / 2 + p] = real ? ntr[p] : 0u;
            }
            if (sub == 0) {
                diag_min[parity ^ 1][0][group + 1] = real ? mtl : 0u;
                diag_min[parity ^ 1][1][group + 1] = real ? mtr : 0u;
            }
#if EXCHANGE == 2
            if (group == 0 && blockIdx.x > 0) {
                unsigned pairs[PAIRS];
                const unsigned m = receive(slot_of(blockIdx.x - 1, 0), tag, pairs, failed);
#pragma unroll
                for (int p = 0; p < PAIRS; ++p) diag[parity ^ 1][0][0][first / 2 + p] = pairs[p];
                if (sub == 0) diag_min[parity ^ 1][0][0] = m;
            }
            if (group == COLS - 1 && blockIdx.x + 1 < sweep_blocks) {
                unsigned pairs[PAIRS];
                const unsigned m = receive(slot_of(blockIdx.x + 1, 1), tag, pairs, failed);
#pragma unroll
                for (int p = 0; p < PAIRS; ++p)
                    diag[parity ^ 1][1][COLS + 1][first / 2 + p] = pairs[p];
                if (sub == 0) diag_min[parity ^ 1][1][COLS + 1] = m;
            }
#endif
#if CLUSTER
            cluster_barrier();
#else
            __syncthreads();
#endif
            v += dv;
        }
    }
}
