// Census semi-global matching on the device. Algorithm and reference:
// pothole_detector/stages/census_sgm.py. Compile-time: LEVELS (a multiple of LANES), LANES (4
// to 32 threads per path line), SELECT_LANES (threads per pixel in sgm_select; LANES if not
// given), CENSUS_RY, CENSUS_RX, INVALID_COST, BORDER_Y, BORDER_X, SHIFT_BITS (the GPT shift
// table's fixed point, perspective.SHIFT_BITS; 16 if not given). Path costs: uint8
// [4][H][W][PATH_LEVELS], the first LEVELS of each pixel's PATH_LEVELS bytes holding levels 0
// to LEVELS - 1 (the rest: padding, see PADDED), slot s holding the sum of the directions
// FIRST_PASS[s] and SECOND_PASS[s] (each path cost is at most INVALID_COST + P2 <= 127, so a
// pair fits a byte; between the passes a pixel's bytes may lie pair by pair, see
// INTERLEAVED_PAIRS). In sgm_select thread `sub` of a group holds levels sub * SELECT_PER_LANE
// and the next SELECT_PER_LANE - 1; sgm_paths_write and sgm_paths_add: see PACKED. Optional:
// PATH_LEVELS (LEVELS unless padded), HORIZONTALS_SECOND, PATH_THREADS; PATH_BLOCKS,
// WRITE_PATH_BLOCKS, PREFETCH_STEPS, WRITE_PREFETCH_STEPS, OLD_AHEAD, SUMS_RING, SUMS_L2_AHEAD,
// INTERLEAVED_PAIRS (tuning).

#define PER_LANE (PATH_LEVELS / LANES)
#define OUTSIDE_COST (1 << 20)

// (dx, dy) of the eight path directions: census_sgm.DIRECTIONS.
__constant__ int DIRECTION_DX[8] = {1, -1, 0, 0, 1, -1, 1, -1};
__constant__ int DIRECTION_DY[8] = {0, 0, 1, -1, 1, 1, -1, -1};
// Directions of the first pass (written) and of the second (added to the same slot): slots 0
// and 1 take the horizontal and the vertical walks, the horizontal ones first unless
// HORIZONTALS_SECOND; slots 2 and 3 the diagonals.
#if HORIZONTALS_SECOND
__constant__ int FIRST_PASS[4] = {2, 3, 4, 5};
__constant__ int SECOND_PASS[4] = {0, 1, 6, 7};
#else
__constant__ int FIRST_PASS[4] = {0, 1, 4, 5};
__constant__ int SECOND_PASS[4] = {2, 3, 6, 7};
#endif

// sgm_select's own lane count (the path kernels' LANES by default): SELECT_LANES threads take
// one pixel, SELECT_PER_LANE levels each.
#define SELECT_PER_LANE (PATH_LEVELS / SELECT_LANES)

// One lane's SELECT_PER_LANE consecutive path bytes of a pixel in each of the four slots
// (sgm_select), as loaded: with an even count the lane's bytes start on a 2-byte boundary and
// are read 4 or 2 at a time. Path bytes are written once and read once per pass, so they go
// through the cache as streaming data (evict first), which leaves L2 to the census words
// every step reads.
#if SELECT_PER_LANE % 4 == 0
#define SELECT_READS (SELECT_PER_LANE / 4)
#elif SELECT_PER_LANE % 2 == 0
#define SELECT_READS (SELECT_PER_LANE / 2)
#else
#define SELECT_READS SELECT_PER_LANE
#endif
struct PathReads {
    unsigned slot[4][SELECT_READS];
};
// Whether each group reads its next pixel's path bytes while it searches the current one's.
#define SELECT_AHEAD (SELECT_READS <= 4)

__device__ __forceinline__ void read_path_bytes(const unsigned char* cell, size_t plane,
                                                PathReads& reads) {
#pragma unroll
    for (int s = 0; s < 4; ++s) {
        const unsigned char* at = cell + s * plane;
#pragma unroll
        for (int r = 0; r < SELECT_READS; ++r) {
#if SELECT_PER_LANE % 4 == 0
            reads.slot[s][r] = __ldcs(reinterpret_cast<const unsigned*>(at) + r);
#elif SELECT_PER_LANE % 2 == 0
            reads.slot[s][r] = __ldcs(reinterpret_cast<const unsigned short*>(at) + r);
#else
            reads.slot[s][r] = __ldcs(at + r);
#endif
        }
    }
}

// The four slots' bytes of `reads` summed into 16-bit halves, two levels per 32-bit add (a
// total of four slots is at most 4 x 254, so no half carries into the next). SLOT_PAIR_BYTES
// (the launcher's, where a path cost is at most 63: INVALID_COST + P2 <= 63): two slots'
// bytes are first added as bytes (at most 4 x 63 = 252 each), then the two sums spread.
__device__ __forceinline__ void add_path_bytes(const PathReads& reads,
                                               unsigned (&totals)[(SELECT_PER_LANE + 1) / 2]) {
#pragma unroll
    for (int r = 0; r < SELECT_READS; ++r) {
#if SLOT_PAIR_BYTES && SELECT_PER_LANE % 2 == 0
        const unsigned first = reads.slot[0][r] + reads.slot[1][r];
        const unsigned second = reads.slot[2][r] + reads.slot[3][r];
#if SELECT_PER_LANE % 4 == 0
        totals[2 * r] += __byte_perm(first, 0u, 0x4140) + __byte_perm(second, 0u, 0x4140);
        totals[2 * r + 1] += __byte_perm(first, 0u, 0x4342) + __byte_perm(second, 0u, 0x4342);
#else
        totals[r] += __byte_perm(first, 0u, 0x4140) + __byte_perm(second, 0u, 0x4140);
#endif
#else
#pragma unroll
        for (int s = 0; s < 4; ++s) {
            const unsigned word = reads.slot[s][r];
#if SELECT_PER_LANE % 4 == 0
            totals[2 * r] += __byte_perm(word, 0u, 0x4140);
            totals[2 * r + 1] += __byte_perm(word, 0u, 0x4342);
#elif SELECT_PER_LANE % 2 == 0
            totals[r] += __byte_perm(word, 0u, 0x4140);
#else
            totals[r / 2] += word << (16 * (r % 2));
#endif
        }
#endif
    }
}

// Minimum of `value` over groups of GROUP lanes (every lane of the warp takes part). With 16
// or 32 lanes by warp reductions (one per group, independent of each other); else by
// shuffles.
template <int GROUP>
__device__ __forceinline__ unsigned group_minimum(unsigned value) {
    if (GROUP == 32) {
        value = __reduce_min_sync(0xffffffffu, value);
    } else if (GROUP == 16) {
        const bool high = threadIdx.x & 16;
        const unsigned low_min = __reduce_min_sync(0xffffffffu, high ? 0xffffffffu : value);
        const unsigned high_min = __reduce_min_sync(0xffffffffu, high ? value : 0xffffffffu);
        value = high ? high_min : low_min;
    } else {
#pragma unroll
        for (int offset = GROUP / 2; offset > 0; offset >>= 1)
            value = min(value, __shfl_xor_sync(0xffffffffu, value, offset, GROUP));
    }
    return value;
}

__device__ __forceinline__ int clamp_index(int i, int n) { return min(max(i, 0), n - 1); }

// blockIdx.z: 0 = left, 1 = right. Blocks of CENSUS_BLOCK_X x CENSUS_BLOCK_Y threads, each thread
// four adjacent pixels of a row; each block first copies its pixels and the window's margin
// (edge-replicated) into shared memory, then every thread reads the window rows of its four pixels
// as CENSUS_WORDS aligned 32-bit words each and compares four byte pairs at once (SIMD within a
// register): for bytes a and b, with t = (b | 0x80) - (a & 0x7f) per byte (no borrow between
// bytes), a > b is bit 7 of a & ~b where the top bits differ, else of ~t. Eight comparisons' bits
// gather in one word (byte i: pixel i) by shifting; four such words are transposed into the
// pixels' census words.
#define CENSUS_BLOCK_X 32
#define CENSUS_BLOCK_Y 8
#define CENSUS_WORDS ((2 * CENSUS_RX + 3) / 4 + 1)
#define CENSUS_TILE_X (4 * (CENSUS_BLOCK_X - 1) + 4 * CENSUS_WORDS)
#define CENSUS_TILE_Y (CENSUS_BLOCK_Y + 2 * CENSUS_RY)
#define CENSUS_BITS (CENSUS_RY * (2 * CENSUS_RX + 1) + CENSUS_RX)
static_assert(CENSUS_BITS <= 32, "a census word holds at most 32 comparisons");

// The four bytes of a tile row starting `start` (known at compile time once the loops are
// unrolled) bytes into the thread's words.
__device__ __forceinline__ unsigned census_window(const unsigned (&words)[CENSUS_WORDS],
                                                  int start) {
    if (start % 4 == 0) return words[start / 4];
    return __funnelshift_r(words[start / 4], words[start / 4 + 1], 8 * (start % 4));
}

// Bit 7 of each byte: whether that byte of `a` is above the same byte of `b` (unsigned).
__device__ __forceinline__ unsigned bytes_above(unsigned a, unsigned b) {
    const unsigned t = (b | 0x80808080u) - (a & 0x7f7f7f7fu);
    return (a & ~b) | (~(a ^ b) & ~t);
}

extern "C" __global__ void __launch_bounds__(CENSUS_BLOCK_X * CENSUS_BLOCK_Y)
census_pair(const unsigned char* left, const unsigned char* right, unsigned* census_left,
            unsigned* census_right, int height, int width) {
    __shared__ __align__(4) unsigned char tile[CENSUS_TILE_Y][CENSUS_TILE_X];
    const unsigned char* image = blockIdx.z == 0 ? left : right;
    const int u0 = blockIdx.x * 4 * CENSUS_BLOCK_X - CENSUS_RX;
    const int v0 = blockIdx.y * CENSUS_BLOCK_Y - CENSUS_RY;
    for (int i = threadIdx.y * CENSUS_BLOCK_X + threadIdx.x; i < CENSUS_TILE_Y * CENSUS_TILE_X;
         i += CENSUS_BLOCK_X * CENSUS_BLOCK_Y) {
        const int y = i / CENSUS_TILE_X, x = i % CENSUS_TILE_X;
        tile[y][x] = image[clamp_index(v0 + y, height) * width + clamp_index(u0 + x, width)];
    }
    __syncthreads();
    const int u = (blockIdx.x * CENSUS_BLOCK_X + threadIdx.x) * 4;
    const int v = blockIdx.y * CENSUS_BLOCK_Y + threadIdx.y;
    if (u >= width || v >= height) return;
    unsigned rows[2 * CENSUS_RY + 1][CENSUS_WORDS];
#pragma unroll
    for (int r = 0; r <= 2 * CENSUS_RY; ++r) {
#pragma unroll
        for (int w = 0; w < CENSUS_WORDS; ++w)
            rows[r][w] = reinterpret_cast<const unsigned*>(&tile[threadIdx.y + r][0])
                [threadIdx.x + w];
    }
    unsigned gathered[4] = {0u, 0u, 0u, 0u};
    unsigned bits = 0u;
    int bit = 0;
#pragma unroll
    for (int dy = 0; dy <= CENSUS_RY; ++dy) {
#pragma unroll
        for (int dx = -CENSUS_RX; dx <= CENSUS_RX; ++dx) {
            if (dy == 0 && dx <= 0) continue;
            const unsigned ahead = census_window(rows[CENSUS_RY + dy], CENSUS_RX + dx);
            const unsigned behind = census_window(rows[CENSUS_RY - dy], CENSUS_RX - dx);
            bits = ((bits >> 1) & 0x7f7f7f7fu) | (bytes_above(ahead, behind) & 0x80808080u);
            ++bit;
            if (bit % 8 == 0 || bit == CENSUS_BITS) {
                const int count = bit % 8 == 0 ? 8 : bit % 8;  // the first at bit 0
                gathered[(bit - 1) / 8] =
                    (bits >> (8 - count)) & ((0xffu >> (8 - count)) * 0x01010101u);
                bits = 0u;
            }
        }
    }
    // transpose: byte i of gathered[g] is bits 8g to 8g + 7 of pixel i's word
    const unsigned low_even = __byte_perm(gathered[0], gathered[1], 0x5140);
    const unsigned low_odd = __byte_perm(gathered[0], gathered[1], 0x7362);
    const unsigned high_even = __byte_perm(gathered[2], gathered[3], 0x5140);
    const unsigned high_odd = __byte_perm(gathered[2], gathered[3], 0x7362);
    const unsigned words[4] = {__byte_perm(low_even, high_even, 0x5410),
                               __byte_perm(low_even, high_even, 0x7632),
                               __byte_perm(low_odd, high_odd, 0x5410),
                               __byte_perm(low_odd, high_odd, 0x7632)};
    unsigned* out = (blockIdx.z == 0 ? census_left : census_right) + (size_t)v * width + u;
#pragma unroll
    for (int i = 0; i < 4; ++i)
        if (u + i < width) out[i] = words[i];
}

// kappa(x, v) of the GPT shift table `shifts` (int32 [3][height]: each row's first column
// that shows a right pixel, then the rows' lines base and step in 1 / 2^SHIFT_BITS px; see
// stages/perspective.py): max(0, floor((base + step x) / 2^SHIFT_BITS)).
__device__ __forceinline__ int gpt_shift(const int* shifts, int height, int v, int x) {
    return max(0, (shifts[height + v] + shifts[2 * height + v] * x) >> SHIFT_BITS);
}

// The GPT-transformed right census: word y of row v is the right census word of column
// x - kappa(x, v), x = y + first(v), so that the path kernels, taking first(v) as the row's
// shift, read column u - d of the transformed census at level d. Words from width - first(v)
// on are never read (a copy of the row's last word).
extern "C" __global__ void gpt_census(const unsigned* census_right, const int* shifts,
                                      unsigned* transformed, int height, int width) {
    const int y = blockIdx.x * blockDim.x + threadIdx.x;
    const int v = blockIdx.y;
    if (y >= width) return;
    const int x = y + shifts[v];
    const int source = clamp_index(x - gpt_shift(shifts, height, v, x), width);
    transformed[(size_t)v * width + y] = census_right[(size_t)v * width + source];
}

// Threads of a path block (the launcher's census_sgm.path_threads: 128 where a lane holds at most
// 8 packed levels, else 256) and the blocks of them the path kernels are built to fit on one
// multiprocessor: 20 warps (at most 102 registers) with blocks of 128 threads; blocks of 256 (the
// longer ranges) keep the registers they need.
#define PATH_BLOCKS (PATH_THREADS <= 128 ? 640 / PATH_THREADS : 1)
#define WRITE_PATH_BLOCKS PATH_BLOCKS

// With an even number of levels per lane (PACKED) a lane holds consecutive levels sub * PER_LANE +
// k, two per 32-bit word (16-bit halves; which two: see pair_level), and aggregates them with the
// halfword min instructions (DPX on sm_90); otherwise it holds levels sub + LANES k one per
// register, so the group's loads and stores of one k are contiguous.
#define PACKED (PER_LANE % 2 == 0)
#define PAIRS (PER_LANE / 2)
// PADDED: the path lanes hold PATH_LEVELS > LEVELS levels, where only then each lane gets an
// even number (PACKED; each half of a pair padded or not on its own). A padded level
// costs PAD_COST, so its path cost stays at least that, far above any real one (at most 127):
// it is never the path minimum nor a real level's best neighbour; and it stays below
// FAR_HALF - P1 (no carry out of its half). A pixel's last PATH_LEVELS - LEVELS bytes in the
// path volume hold no path cost; nothing reads them as one.
#define PADDED (PATH_LEVELS > LEVELS)
#define PAD_COST 0x3fffu
static_assert(!PADDED || (PACKED && LEVELS % 2 == 0), "padding needs packed even levels");
#if PACKED
#define LANE_FIRST_LEVEL(sub) ((sub) * PER_LANE)
#define LEVEL_STEP 1
// LANE_WORD: a lane holds two pairs (four levels), so its bytes of a pixel are one aligned
// 32-bit word (PATH_LEVELS is a multiple of 16), loaded and stored whole, the first pass's
// sums added to it by one 32-bit add (each byte's sum is below 256: no carry between them)
#define LANE_WORD (PAIRS == 2)
#define OLD_WORDS (LANE_WORD ? 1 : PAIRS)
// a lane's first path byte in a pixel and the halfwords between its pairs, by layout
#define LANE_OFFSET(interleaved, sub) ((interleaved) ? 2 * (sub) : LANE_FIRST_LEVEL(sub))
#define PAIR_STRIDE(interleaved) ((interleaved) ? LANES : 1)
#else
#define LANE_FIRST_LEVEL(sub) (sub)
#define LEVEL_STEP LANES
#define LANE_WORD 0
#define OLD_WORDS PER_LANE
#define LANE_OFFSET(interleaved, sub) LANE_FIRST_LEVEL(sub)
#define PAIR_STRIDE(interleaved) 1
#endif
// The lane's highest level is at most `start` (u - kappa - the lane's first level) away:
// every candidate column of the step lies inside the image.
#define ALL_INSIDE(start) ((start) >= LEVEL_STEP * (PER_LANE - 1))
// Steps whose loads are in flight ahead of the one aggregated.
#define PREFETCH_STEPS (PACKED && PER_LANE <= 8 ? 6 : 3)
// Steps ahead that the second pass loads the first pass's sums into registers.
#define OLD_AHEAD PREFETCH_STEPS
static_assert(OLD_AHEAD >= 1 && OLD_AHEAD <= PREFETCH_STEPS, "OLD_AHEAD: 1 to PREFETCH_STEPS");
// Steps whose loads are in flight ahead of the one aggregated, in the first pass.
#define WRITE_PREFETCH_STEPS (PACKED && PER_LANE <= 8 ? 5 : 3)
// Steps ahead that the second pass asks L2 for the first pass's sums (0: never), so that the loads
// OLD_AHEAD steps ahead find them there.
#define SUMS_L2_AHEAD 24
// SUMS_RING (a power of two, 0: off): the second pass copies the first pass's sums of each line's
// pixel SUMS_COPY_AHEAD steps ahead (below) into a ring of SUMS_RING pixels per line in shared
// memory, by asynchronous copies of 16 bytes a lane, instead of loading them into registers
// OLD_AHEAD steps ahead (L2 still asked SUMS_L2_AHEAD steps ahead).
#define SUMS_RING (LANES <= 16 && PACKED && PATH_LEVELS % 16 == 0 \
                   && PATH_THREADS / LANES * 16 * PATH_LEVELS <= 16 * 1024 ? 16 : 0)
static_assert(SUMS_RING == 0 || (SUMS_RING >= 2 && (SUMS_RING & (SUMS_RING - 1)) == 0),
              "SUMS_RING: 0 or a power of two");
static_assert(SUMS_RING == 0 || (PACKED && PATH_LEVELS % 16 == 0),
              "SUMS_RING: packed levels, 16-byte pixels");
// A checked run waits once, before its first step, for all of its entries and copies the sums of
// the run's pixels SUMS_COPY_AHEAD steps on in one go, 16 bytes a lane, and asks L2 for those
// SUMS_L2_AHEAD steps on (fewer copy instructions, address computations and L2 requests than a
// wait and a copy per step; 0: per step everywhere). Each step commits one copy group (empty
// within a run), so a step waits for at most SUMS_COPY_AHEAD - 1 later groups and a run for
// SUMS_COPY_AHEAD - PREFETCH_STEPS; the entries a run copies into are those the steps before it
// read.
#define COPY_PARTS                                                                          \
    (PATH_LEVELS <= 16 ? 1 : PATH_LEVELS <= 32 ? 2 : PATH_LEVELS <= 64 ? 4                  \
     : PATH_LEVELS <= 128 ? 8 : 16)
#define COPY_STEP_LANES (LANES / COPY_PARTS)
static_assert(SUMS_RING == 0 || COPY_STEP_LANES >= 1,
              "run copies: a pixel's parts, rounded up to a power of two, fit the lanes");
// Steps ahead that a pixel's sums are copied.
#define SUMS_COPY_AHEAD (SUMS_RING - PREFETCH_STEPS)
static_assert(SUMS_RING == 0 || (SUMS_COPY_AHEAD >= 1 && SUMS_COPY_AHEAD < SUMS_RING),
              "SUMS_COPY_AHEAD: 1 to SUMS_RING - 1");
// INTERLEAVED_PAIRS: the first pass writes a pixel's path bytes pair by pair, pair p of lane `sub`
// at byte 2 * LANES * p + 2 * sub (each of a group's pair stores 2 * LANES contiguous bytes, whole
// 32-byte sectors, instead of 2 bytes every PER_LANE); the second pass reads them from its ring in
// that layout (each pixel there whole before any lane writes it) and writes its sums in the winner
// search's, lane by lane. Where the lanes hold three or more pairs and the second pass has the
// ring (with two, LANE_WORD: a group's word stores are contiguous already).
#define INTERLEAVED_PAIRS (SUMS_RING && PER_LANE >= 6)
static_assert(!INTERLEAVED_PAIRS || (SUMS_RING && PER_LANE >= 6),
              "INTERLEAVED_PAIRS: the second pass's ring and three or more pairs a lane");
static_assert(SUMS_RING == 0
                  || (SUMS_COPY_AHEAD >= PREFETCH_STEPS
                      && SUMS_COPY_AHEAD + PREFETCH_STEPS <= SUMS_RING),
              "run copies: a run's copies fit the ring beside the run's entries");
// A lane's pair p holds levels first + p (low half) and first + PAIRS + p (high half) instead of
// first + 2p and first + 2p + 1, so that the levels beside an inner pair's are the pairs beside it
// (no funnel shift); the two edge pairs' neighbours are one byte permute each. Stores put the
// levels back in order (halfword h: levels first + 2h and first + 2h + 1, a permute of two pairs),
// so the path volume is the same. Two instructions a step fewer at 3 pairs a lane.
#define PAIR_LEVEL(p, half) ((p) + (half) * PAIRS)
// A right census word that costs INVALID_COST against `left` (the census bits are the low
// INVALID_COST bits): stands in for the columns left of the image.
static_assert(INVALID_COST >= 1 && INVALID_COST <= 31, "census words of 1 to 31 bits");
__device__ __forceinline__ unsigned invalid_word(unsigned left) {
    return ~left & ((1u << INVALID_COST) - 1u);
}
// Halfword stand-in for "outside the range": above any path cost plus P1, no carry out.
#define FAR_HALF 0x7fffu

// Two levels' matching costs (each below 2^16) as one halfword pair, `low` in the low half, by a
// multiply-add (the FMA pipe) instead of a byte permute (the integer ALU pipe, the busier one).
__device__ __forceinline__ unsigned pack_costs(unsigned low, unsigned high) {
    unsigned pair;
    asm("mad.lo.u32 %0, %1, 65536, %2;" : "=r"(pair) : "r"(high), "r"(low));
    return pair;
}

// What one path step reads: the left census word, the right census words of the lane's
// levels (invalid_word(left) left of the image) and, when adding, the path sums of the first
// pass (PACKED: two bytes per entry).
struct StepData {
    unsigned left;
    unsigned right[PER_LANE];
    unsigned old[OLD_WORDS];
};

// A compile-time flag as a value (for the generic step lambda).
template <bool B>
struct Flag {
    static constexpr bool value = B;
};

// Where a walk's loads are: the pixel index, the column less the lane's first level and
// kappa's entry for the row in shared memory.
struct Cursor {
    unsigned pixel;
    int column;
    const int* shift;
};

// The census words of the step at `at` into `data`; INSIDE: every column of the lane's levels is
// known to lie inside the image (no test). The right words are indexed from a per-lane base,
// census_right less the lane's first level, opaque to the compiler (`lane_right`, `lane_first` 0),
// which saves the step a multiply-add.
template <bool INSIDE>
__device__ __forceinline__ void load_census(const unsigned* __restrict__ census_left,
                                            const unsigned* __restrict__ lane_right,
                                            int lane_first, const Cursor& at,
                                            StepData& data) {
    data.left = __ldg(census_left + at.pixel);
    const int shift = *at.shift;
    // the lane's highest level's column is `start` less than its lowest level's
    const int start = at.column - shift;
    // unsigned: where the index is negative (left of row 0) no word is read (a word read lies
    // at or right of column 0, so pixel - shift >= the lane's first level there)
    const unsigned* right = lane_right + (at.pixel - lane_first - shift);
    if (INSIDE || ALL_INSIDE(start)) {
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) data.right[k] = __ldg(right - LEVEL_STEP * k);
    } else {
        const unsigned outside = invalid_word(data.left);
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k)
            data.right[k] = start >= LEVEL_STEP * k ? __ldg(right - LEVEL_STEP * k) : outside;
    }
}

// HORIZONTAL_REUSE (packed lanes): a horizontal walk's checked steps take their right census words
// from the set of the step before (one column on, the same columns one level over): rightward
// (SIGN 1) level first + k's word is the step before's level first + k - 1, the lowest level's the
// lower lane's highest (a shuffle), lane 0's a new load; leftward (SIGN -1) mirrored, the highest
// lane loading. One load and one shuffle a step instead of PER_LANE loads (the words still move
// between the register sets). Every column a checked step reads lies inside the image, and so did
// it the step before: those words are real census words, not stand-ins.
#define HORIZONTAL_REUSE PACKED
static_assert(!HORIZONTAL_REUSE || PACKED, "HORIZONTAL_REUSE: packed lanes (consecutive levels)");
template <int SIGN>
__device__ __forceinline__ void derive_census(const unsigned* __restrict__ census_left,
                                              const unsigned* __restrict__ lane_right,
                                              int lane_first, const Cursor& at, int sub,
                                              const StepData& prior, StepData& data) {
    data.left = __ldg(census_left + at.pixel);
    const unsigned* right = lane_right + (at.pixel - lane_first - *at.shift);
    if (SIGN > 0) {
        const unsigned below = __shfl_up_sync(0xffffffffu, prior.right[PER_LANE - 1], 1, LANES);
        unsigned fresh = below;
        if (sub == 0) fresh = __ldg(right);
#pragma unroll
        for (int k = PER_LANE - 1; k > 0; --k) data.right[k] = prior.right[k - 1];
        data.right[0] = fresh;
    } else {
        const unsigned above = __shfl_down_sync(0xffffffffu, prior.right[0], 1, LANES);
        unsigned fresh = above;
        if (sub == LANES - 1) fresh = __ldg(right - (PER_LANE - 1));
#pragma unroll
        for (int k = 0; k < PER_LANE - 1; ++k) data.right[k] = prior.right[k + 1];
        data.right[PER_LANE - 1] = fresh;
    }
}

__device__ __forceinline__ void prefetch_sums(const unsigned char* cells, unsigned pixel) {
    asm volatile("prefetch.global.L2 [%0];" : : "l"(cells + (size_t)pixel * PATH_LEVELS));
}

// The group's copies of one pixel's sums (PATH_LEVELS bytes at `cell`) into `ring` (a shared
// address), 16 bytes a lane; then the lane's commit of its copy group.
__device__ __forceinline__ void copy_sums(unsigned ring, const unsigned char* cell, int sub,
                                          bool wanted) {
    if (wanted) {
#pragma unroll
        for (int c = sub; c < PATH_LEVELS / 16; c += LANES)
            asm volatile("cp.async.cg.shared.global [%0], [%1], 16;"
                         : : "r"(ring + 16 * c), "l"(cell + 16 * c));
    }
    asm volatile("cp.async.commit_group;");
}

__device__ __forceinline__ void load_sums(const unsigned char* cells, unsigned pixel,
                                          StepData& data) {
    const unsigned char* cell = cells + (size_t)pixel * PATH_LEVELS;
#if LANE_WORD
    data.old[0] = __ldcs(reinterpret_cast<const unsigned*>(cell));
#elif PACKED
#pragma unroll
    for (int p = 0; p < PAIRS; ++p)
        data.old[p] = __ldcs(reinterpret_cast<const unsigned short*>(cell) + p);
#else
#pragma unroll
    for (int k = 0; k < PER_LANE; ++k) data.old[k] = __ldcs(cell + LANES * k);
#endif
}

#if PACKED
// Halfword h of a lane's path costs in `current` (pairs, each value below 256) with its levels
// in order: first + 2h in the low byte, first + 2h + 1 in the high.
__device__ __forceinline__ unsigned ordered_bytes(const unsigned (&current)[PAIRS], int h) {
    const int low = 2 * h, high = 2 * h + 1;
    return __byte_perm(current[low % PAIRS], current[high % PAIRS],
                       2 * (low / PAIRS) | (4 + 2 * (high / PAIRS)) << 4);
}

// A step's stores: the lane's PER_LANE bytes of the pixel at `cell` as PAIRS halfwords,
// PAIR_STRIDE(STORED) halfwords apart (LANE_WORD: as one word); ADD: plus the first pass's bytes
// in `old` (the same halfwords, or word).
template <bool ADD, bool STORED>
__device__ __forceinline__ void store_path_bytes(const unsigned (&current)[PAIRS],
                                                 const unsigned (&old)[OLD_WORDS],
                                                 unsigned char* cell) {
#if LANE_WORD
    // levels first to first + 3: the low bytes of pairs 0 and 1, then their third bytes
    unsigned word = __byte_perm(current[0], current[1], 0x6240);
    if (ADD) word += old[0];
    __stcs(reinterpret_cast<unsigned*>(cell), word);
#else
#pragma unroll
    for (int h = 0; h < PAIRS; ++h) {
        unsigned bytes = ordered_bytes(current, h);
        if (ADD) bytes += old[h];
        __stcs(reinterpret_cast<unsigned short*>(cell) + PAIR_STRIDE(STORED) * h,
               (unsigned short)bytes);
    }
#endif
}
#endif

// `pointer` as a value the compiler cannot take apart, so that an address from it is one
// wide multiply-add instead of a sum rebuilt from its parts at every use.
template <typename T>
__device__ __forceinline__ T* opaque(T* pointer) {
    asm("" : "+l"(pointer));
    return pointer;
}

// Steps from (u, v) along (dx, dy) until the line leaves the image.
__device__ __forceinline__ int line_steps(int u, int v, int dx, int dy, int height,
                                          int width) {
    const int along_x = dx > 0 ? width - u : dx < 0 ? u + 1 : 1 << 30;
    const int along_y = dy > 0 ? height - v : dy < 0 ? v + 1 : 1 << 30;
    return min(along_x, along_y);
}

__device__ __forceinline__ int lines_of(int direction, int height, int width) {
    const int dx = DIRECTION_DX[direction], dy = DIRECTION_DY[direction];
    return dy == 0 ? height : dx == 0 ? width : width + height - 1;
}

// The lines of `block` of `slot` (walking `direction`; `rings`: the shared address of the
// groups' rings of sums, SUMS_RING). Each group of LANES threads walks one line from where it
// enters the image; the groups of a warp step together as long as the longest of their lines
// (a group whose line has ended, or that has none, computes on stale registers and stores
// nothing), so the group exchanges are whole-warp operations. HSIGN: the walk's dx where it
// is horizontal and takes its census words from the step before (HORIZONTAL_REUSE), else 0.
template <bool ADD, int HSIGN>
__device__ __forceinline__ void walk_line(const unsigned* __restrict__ census_left,
                                          const unsigned* __restrict__ census_right,
                                          const int* kappa, unsigned char* paths, int height,
                                          int width, int p1, int p2, int slot, int block,
                                          int direction, unsigned rings) {
    extern __shared__ int row_shift[];
    // the layout this pass writes (the second pass: always the winner search's)
    constexpr bool STORED = ADD ? false : INTERLEAVED_PAIRS;
    const int groups_per_block = blockDim.x / LANES;
    const int dx = DIRECTION_DX[direction], dy = DIRECTION_DY[direction];
    const int sub = threadIdx.x % LANES;
    const int line = block * groups_per_block + threadIdx.x / LANES;
    int u, v;
    if (dy == 0) {
        v = line; u = dx > 0 ? 0 : width - 1;
    } else if (dx == 0) {
        u = line; v = dy > 0 ? 0 : height - 1;
    } else if (line < width) {
        u = line; v = dy > 0 ? 0 : height - 1;
    } else {
        const int along = line - width + 1;
        u = dx > 0 ? 0 : width - 1; v = dy > 0 ? along : height - 1 - along;
    }
    for (int i = threadIdx.x; i < height; i += blockDim.x) row_shift[i] = kappa[i];
    __syncthreads();
    const int steps = line < lines_of(direction, height, width)
                          ? line_steps(u, v, dx, dy, height, width) : 0;
    const int warp_steps = __reduce_max_sync(0xffffffffu, (unsigned)steps);
    if (warp_steps == 0) return;
    const int first = LANE_FIRST_LEVEL(sub);
    // this lane's first path byte of pixel 0 in the slot
    unsigned char* cells =
        opaque(paths + (size_t)slot * height * width * PATH_LEVELS + LANE_OFFSET(STORED, sub));
    const int delta = dy * width + dx;
    // the census loads run AHEAD steps ahead of the step aggregated (the sums
    // OLD_AHEAD), into one of AHEAD register sets used in turn
    constexpr int AHEAD = ADD ? PREFETCH_STEPS : WRITE_PREFETCH_STEPS;
    unsigned pixel = (unsigned)(v * width + u);
    Cursor ahead = {pixel, u - first, row_shift + v};
    const unsigned* const lane_right = opaque(census_right - first);
    constexpr int lane_first = 0;
    StepData sets[AHEAD];
#if SUMS_RING
    // the group's ring: the sums of the pixels of steps step to step + SUMS_RING - 1
    const unsigned ring = rings + threadIdx.x / LANES * SUMS_RING * PATH_LEVELS;
    const unsigned char* pixel_cells = cells - LANE_OFFSET(STORED, sub);
    if (ADD) {
#pragma unroll 1
        for (int s = 0; s < SUMS_COPY_AHEAD; ++s)
            copy_sums(ring + s * PATH_LEVELS,
                      pixel_cells + (size_t)(pixel + s * delta) * PATH_LEVELS, sub, s < steps);
    }
    // this lane's share of a run's copies: part sub % COPY_PARTS (if a pixel has it) of the
    // run's pixels sub / COPY_PARTS, that + COPY_STEP_LANES, ...; the lane's first source
    // byte less the run's first pixel's and its ring bytes' offset in an entry
    const int copy_part = sub & (COPY_PARTS - 1);
    const int copy_first = copy_part < PATH_LEVELS / 16 ? sub / COPY_PARTS : PREFETCH_STEPS;
    const int copy_source = copy_first * delta * PATH_LEVELS + 16 * copy_part;
    const int copy_stride = COPY_STEP_LANES * delta * PATH_LEVELS;
    const unsigned copy_ring = ring + 16 * copy_part;
#endif
    if (ADD && SUMS_L2_AHEAD > 0) {
#pragma unroll 1
        for (int s = OLD_AHEAD; s < min(steps, SUMS_L2_AHEAD); ++s)
            prefetch_sums(cells, pixel + s * delta);
    }
#pragma unroll
    for (int s = 0; s < AHEAD; ++s) {
        if (s < steps) {
            load_census<false>(census_left, lane_right, lane_first, ahead, sets[s]);
            if (ADD && !SUMS_RING && s < OLD_AHEAD) load_sums(cells, ahead.pixel, sets[s]);
        }
        ahead.pixel += delta;
        ahead.column += dx;
        ahead.shift += dy;
    }
    // zero previous costs and minimum make the first step's path cost its matching cost
#if PACKED
    unsigned previous[PAIRS];
#pragma unroll
    for (int p = 0; p < PAIRS; ++p) previous[p] = 0u;
    unsigned minimum = 0u;  // the path minimum in both halves
    const unsigned p1_pair = (unsigned)p1 * 0x10001u;
    const unsigned p2_pair = (unsigned)p2 * 0x10001u;
#if PADDED
    unsigned pad[PAIRS];
#pragma unroll
    for (int p = 0; p < PAIRS; ++p)
        pad[p] = (first + PAIR_LEVEL(p, 0) < LEVELS ? 0u : PAD_COST)
                 | (first + PAIR_LEVEL(p, 1) < LEVELS ? 0u : PAD_COST << 16);
#endif
#else
    int previous[PER_LANE];
#pragma unroll
    for (int k = 0; k < PER_LANE; ++k) previous[k] = 0;
    int previous_min = 0;
#endif
    const int sums_delta = OLD_AHEAD * delta;
    const int l2_delta = SUMS_L2_AHEAD * delta;
    int step = 0;
    // one step with the register set `data` (and the sums into `later`, the set OLD_AHEAD
    // steps on); false once the warp's lines have all ended
    // FAST: a run of steps checked beforehand (all of them and the loads they make inside
    // every line of the warp and inside the image), with no test between them
    auto advance = [&](StepData& data, StepData& later, const StepData& prior,
                       auto fast) -> bool {
        constexpr bool FAST = decltype(fast)::value;
        unsigned old[OLD_WORDS];
#if SUMS_RING
        if (ADD) {
            // this step's copies are done once at most SUMS_COPY_AHEAD - 1 later groups are
            // pending; the warp's barrier then shows each lane what the others copied (a checked
            // run waits before its first step)
            if (!FAST) {
                asm volatile("cp.async.wait_group %0;" : : "n"(SUMS_COPY_AHEAD - 1));
                __syncwarp();
            }
            const unsigned at = ring + (step & (SUMS_RING - 1)) * PATH_LEVELS
                                + LANE_OFFSET(INTERLEAVED_PAIRS, sub);
#if LANE_WORD
            asm volatile("ld.shared.u32 %0, [%1];" : "=r"(old[0]) : "r"(at));
#else
#pragma unroll
            for (int w = 0; w < OLD_WORDS; ++w)
                asm volatile("ld.shared.u16 %0, [%1];"
                             : "=r"(old[w]) : "r"(at + 2 * PAIR_STRIDE(INTERLEAVED_PAIRS) * w));
#endif
            if (FAST) {
                asm volatile("cp.async.commit_group;");
            } else {
                // into an entry read before the barrier
                copy_sums(ring + ((step + SUMS_COPY_AHEAD) & (SUMS_RING - 1)) * PATH_LEVELS,
                          pixel_cells + (size_t)(pixel + SUMS_COPY_AHEAD * delta)
                                            * PATH_LEVELS,
                          sub, step + SUMS_COPY_AHEAD < steps);
            }
        }
#else
        if (ADD) {
#pragma unroll
            for (int w = 0; w < OLD_WORDS; ++w) old[w] = data.old[w];
        }
#endif
#if PACKED
        // halfword pairs: level first + PAIR_LEVEL(p, 0) in the low half, PAIR_LEVEL(p, 1)
        // in the high
        unsigned current[PAIRS];
#pragma unroll
        for (int p = 0; p < PAIRS; ++p)
            current[p] = pack_costs(__popc(data.left ^ data.right[PAIR_LEVEL(p, 0)]),
                                    __popc(data.left ^ data.right[PAIR_LEVEL(p, 1)]));
#if PADDED
#pragma unroll
        for (int p = 0; p < PAIRS; ++p) current[p] |= pad[p];
#endif
#else
        int current[PER_LANE];
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) current[k] = __popc(data.left ^ data.right[k]);
#endif
        if (FAST && HSIGN != 0)
            derive_census<HSIGN>(census_left, lane_right, lane_first, ahead, sub, prior, data);
        else if (FAST)
            load_census<true>(census_left, lane_right, lane_first, ahead, data);
        else if (step + AHEAD < steps)
            load_census<false>(census_left, lane_right, lane_first, ahead, data);
        if (ADD && !SUMS_RING && (FAST || step + OLD_AHEAD < steps))
            load_sums(cells, pixel + sums_delta, later);
        if (ADD && SUMS_L2_AHEAD > 0 && !FAST
            && step + SUMS_L2_AHEAD < steps)
            prefetch_sums(cells, pixel + l2_delta);
        ahead.pixel += delta;
        ahead.column += dx;
        ahead.shift += dy;
        const bool store = FAST || step < steps;
        unsigned char* cell = cells + (size_t)pixel * PATH_LEVELS;
#if PACKED
        unsigned least;
        {
            // lower[p] / upper[p]: the levels one below / above pair p's, half by half; the
            // level below this lane's first is the high half of the lower lane's last pair,
            // the one above its last the low half of the upper lane's first
            unsigned below = __shfl_up_sync(0xffffffffu, previous[PAIRS - 1], 1, LANES);
            unsigned above = __shfl_down_sync(0xffffffffu, previous[0], 1, LANES);
            if (sub == 0) below = FAR_HALF << 16;
            if (sub == LANES - 1) above = FAR_HALF;
            unsigned lower[PAIRS], upper[PAIRS];
            // pair p's neighbours are pairs p - 1 and p + 1; pair 0's lower levels: the lower
            // lane's last and this lane's first + PAIRS - 1 (pair PAIRS - 1's low half); pair
            // PAIRS - 1's upper: this lane's first + PAIRS (pair 0's high half) and the upper
            // lane's first
            lower[0] = __byte_perm(below, previous[PAIRS - 1], 0x5432);
            upper[PAIRS - 1] = __byte_perm(previous[0], above, 0x5432);
#pragma unroll
            for (int p = 1; p < PAIRS; ++p) {
                lower[p] = previous[p - 1];
                upper[p - 1] = previous[p];
            }
            const unsigned jump_less_p1 = minimum + p2_pair - p1_pair;
#pragma unroll
            for (int p = 0; p < PAIRS; ++p) {
                // min(previous, lower + P1, upper + P1, minimum + P2)
                const unsigned neighbours = __vimin3_u16x2(lower[p], upper[p], jump_less_p1);
                const unsigned best = __viaddmin_u16x2(neighbours, p1_pair, previous[p]);
                // every half of best is >= the minimum and the sums stay below 256: plain
                // 32-bit arithmetic cannot borrow or carry across the halves
                current[p] = current[p] + best - minimum;
            }
            least = current[0];
#pragma unroll
            for (int p = 1; p < PAIRS; ++p) least = __vminu2(least, current[p]);
            // both halves: the lane's least
            least = __vminu2(least, __byte_perm(least, 0u, 0x1032));
        }
        if (store) {
            // the lane's levels in order as bytes (every value is below 128, the second
            // pass's sum below 256)
            store_path_bytes<ADD, STORED>(current, old, cell);
        }
#pragma unroll
        for (int p = 0; p < PAIRS; ++p) previous[p] = current[p];
        minimum = group_minimum<LANES>(least);
#else
        {
            const int jump = previous_min + p2;
            const int left_lane = (sub + LANES - 1) % LANES, right_lane = (sub + 1) % LANES;
#pragma unroll
            for (int k = 0; k < PER_LANE; ++k) {
                // level d - 1: lane sub - 1, or the last lane's previous register for lane 0
                const int give_lower = sub == LANES - 1 && k > 0 ? previous[k - 1]
                                                                 : previous[k];
                int lower = __shfl_sync(0xffffffffu, give_lower, left_lane, LANES);
                if (sub == 0 && k == 0) lower = OUTSIDE_COST;
                // level d + 1: lane sub + 1, or lane 0's next register for the last lane
                const int give_upper = sub == 0 && k < PER_LANE - 1 ? previous[k + 1]
                                                                    : previous[k];
                int upper = __shfl_sync(0xffffffffu, give_upper, right_lane, LANES);
                if (sub == LANES - 1 && k == PER_LANE - 1) upper = OUTSIDE_COST;
                const int best = min(min(previous[k], min(lower, upper) + p1), jump);
                current[k] += best - previous_min;
            }
        }
        unsigned least = (unsigned)current[0];
#pragma unroll
        for (int k = 1; k < PER_LANE; ++k) least = min(least, (unsigned)current[k]);
        if (store) {
#pragma unroll
            for (int k = 0; k < PER_LANE; ++k) {
                const int stored = ADD ? (int)old[k] + current[k] : current[k];
                __stcs(reinterpret_cast<char*>(cell) + LANES * k, (char)stored);
            }
        }
#pragma unroll
        for (int k = 0; k < PER_LANE; ++k) previous[k] = current[k];
        previous_min = (int)group_minimum<LANES>(least);
#endif
        pixel += delta;
        return ++step < warp_steps;
    };
    // whether the next AHEAD steps can run as one checked run: every line of the
    // warp has them and the loads they make, and the loads' columns are inside the image
    auto run_ahead = [&]() -> bool {
        bool inside = step + 2 * AHEAD <= steps;
#pragma unroll
        for (int j = 0; j < AHEAD; ++j)
            inside = inside && ALL_INSIDE(ahead.column + j * dx - ahead.shift[j * dy]);
        return __all_sync(0xffffffffu, inside);
    };
#if SUMS_RING
    // before a checked run: wait for the run's AHEAD entries (in once at most
    // SUMS_COPY_AHEAD - AHEAD later groups are pending), then copy the sums of the run's
    // steps SUMS_COPY_AHEAD on into entries read before the barrier (committed by the run's
    // first step) and ask L2 for both ends of each of its pixels SUMS_L2_AHEAD steps on
    auto start_run = [&]() {
        asm volatile("cp.async.wait_group %0;" : : "n"(SUMS_COPY_AHEAD - AHEAD));
        __syncwarp();
        const unsigned char* source =
            pixel_cells + (size_t)(pixel + SUMS_COPY_AHEAD * delta) * PATH_LEVELS;
        const int copied = step + SUMS_COPY_AHEAD;
        const unsigned char* lane_source = source + copy_source;
#pragma unroll
        for (int i = 0; i * COPY_STEP_LANES < PREFETCH_STEPS; ++i) {
            const int at = copy_first + i * COPY_STEP_LANES;
            if (at < PREFETCH_STEPS && copied + at < steps)
                asm volatile("cp.async.cg.shared.global [%0], [%1], 16;"
                             : : "r"(copy_ring + ((copied + at) & (SUMS_RING - 1))
                                                     * PATH_LEVELS),
                                 "l"(lane_source + i * copy_stride));
        }
        if (SUMS_L2_AHEAD > 0 && sub < 2 * AHEAD) {
            // lanes 2j and 2j + 1: the first and last byte of the pixel j steps on
            const int later = sub >> 1;
            if (step + SUMS_L2_AHEAD + later < steps)
                asm volatile("prefetch.global.L2 [%0];"
                             : : "l"(pixel_cells
                                     + (size_t)(pixel + (SUMS_L2_AHEAD + later) * delta)
                                           * PATH_LEVELS
                                     + (sub & 1) * (PATH_LEVELS - 1)));
        }
    };
#endif
    // written out: with many levels per lane the compiler would not unroll a loop over the
    // sets, and a set indexed at run time lives in local memory
    static_assert(AHEAD >= 1 && AHEAD <= 8, "PREFETCH_STEPS: 1 to 8");
#define SET(i) sets[(i) % AHEAD], sets[((i) + OLD_AHEAD) % AHEAD], \
               sets[((i) + AHEAD - 1) % AHEAD]
    const Flag<true> fast;
    const Flag<false> checked;
    while (true) {
        if (run_ahead()) {
#if SUMS_RING
            if (ADD) start_run();
#endif
            advance(SET(0), fast);
            if (AHEAD > 1) advance(SET(1), fast);
            if (AHEAD > 2) advance(SET(2), fast);
            if (AHEAD > 3) advance(SET(3), fast);
            if (AHEAD > 4) advance(SET(4), fast);
            if (AHEAD > 5) advance(SET(5), fast);
            if (AHEAD > 6) advance(SET(6), fast);
            if (AHEAD > 7) advance(SET(7), fast);
            continue;
        }
        if (!advance(SET(0), checked)) return;
        if (AHEAD > 1 && !advance(SET(1), checked)) return;
        if (AHEAD > 2 && !advance(SET(2), checked)) return;
        if (AHEAD > 3 && !advance(SET(3), checked)) return;
        if (AHEAD > 4 && !advance(SET(4), checked)) return;
        if (AHEAD > 5 && !advance(SET(5), checked)) return;
        if (AHEAD > 6 && !advance(SET(6), checked)) return;
        if (AHEAD > 7 && !advance(SET(7), checked)) return;
    }
#undef SET
}

// One launch per pass walks all four slots: slot s takes the direction FIRST_PASS[s] in the
// first pass (path costs written: ADD false) and SECOND_PASS[s] in the second (added). The
// blocks of slot 0 come first, then those of slots 1, 2, 3, each slot with just enough blocks
// for its lines (the straight walks start first and spread over the multiprocessors).
template <bool ADD>
__device__ __forceinline__ void walk_paths(const unsigned* __restrict__ census_left,
                                           const unsigned* __restrict__ census_right,
                                           const int* kappa, unsigned char* paths, int height,
                                           int width, int p1, int p2) {
    const int groups_per_block = blockDim.x / LANES;
    int slot = 0, block = blockIdx.x, direction = 0;
#pragma unroll 1
    for (; slot < 4; ++slot) {
        direction = ADD ? SECOND_PASS[slot] : FIRST_PASS[slot];
        const int blocks = (lines_of(direction, height, width) + groups_per_block - 1)
                           / groups_per_block;
        if (block < blocks) break;
        block -= blocks;
    }
    if (slot == 4) return;
    // the groups' rings of sums (SUMS_RING, the second pass), a shared address
#if SUMS_RING
    __shared__ __align__(16) unsigned char sums_ring[PATH_THREADS / LANES][SUMS_RING][PATH_LEVELS];
    const unsigned rings = (unsigned)__cvta_generic_to_shared(sums_ring);
#else
    const unsigned rings = 0u;
#endif
    // only in the pass that walks the horizontal lines: the other pass's kernel stays one walk.
    if constexpr (HORIZONTAL_REUSE && ADD == (HORIZONTALS_SECOND != 0)) {
        if (DIRECTION_DY[direction] == 0) {
            if (DIRECTION_DX[direction] > 0)
                walk_line<ADD, 1>(census_left, census_right, kappa, paths, height, width, p1,
                                  p2, slot, block, direction, rings);
            else
                walk_line<ADD, -1>(census_left, census_right, kappa, paths, height, width, p1,
                                   p2, slot, block, direction, rings);
            return;
        }
    }
    walk_line<ADD, 0>(census_left, census_right, kappa, paths, height, width, p1, p2, slot,
                      block, direction, rings);
}

extern "C" __global__ void __launch_bounds__(PATH_THREADS, WRITE_PATH_BLOCKS)
sgm_paths_write(const unsigned* census_left, const unsigned* census_right, const int* kappa,
                unsigned char* paths, int height, int width, int p1, int p2) {
    walk_paths<false>(census_left, census_right, kappa, paths, height, width, p1, p2);
}

extern "C" __global__ void __launch_bounds__(PATH_THREADS, PATH_BLOCKS)
sgm_paths_add(const unsigned* census_left, const unsigned* census_right, const int* kappa,
              unsigned char* paths, int height, int width, int p1, int p2) {
    walk_paths<true>(census_left, census_right, kappa, paths, height, width, p1, p2);
}

// One block per row. Sum of the four slots, winner, uniqueness, the right view's winners
// (shared-memory atomicMin of cost << 16 | d per right column); then, once the row is searched,
// subpixel and the left-right check, a thread per pixel. A group of SELECT_LANES threads takes one
// pixel at a time; the groups of a warp go through the row together (a group past the row's end
// reads the last pixel and writes nothing), so the group minima are whole-warp operations. A lane
// holds its levels' totals as halfword pairs (pair h: its levels 2h, low half, and 2h + 1) and
// searches them two at a time: the winner as the least total << 5 | the level's index in the lane,
// the runner-up beyond the winner's neighbours with those three raised by a multiple of 2048 (DPX
// halfword arithmetic). raw: D0, -1 invalid.
#define SELECT_PAIRS ((SELECT_PER_LANE + 1) / 2)
static_assert(SELECT_PER_LANE <= 32, "at most 32 levels per winner search lane");
// A padded level's total (and that of an odd lane's missing last half): above any real one
// (at most 4 x 254), so never a winner, runner-up or right-view winner (every column has the
// real candidate of its own pixel at level 0), and small enough for total << 5 | index to
// fit a half.
#define FAR_TOTAL 0x3ffu
// Words of each group's totals: odd, so that the groups of a warp write into different banks.
#define TOTAL_PITCH (((PATH_LEVELS + 1) / 2) | 1)
#define SELECT_LANE_BITS \
    (SELECT_LANES <= 4 ? 2 : SELECT_LANES <= 8 ? 3 : SELECT_LANES <= 16 ? 4 : 5)
// The index pair of pair h (2h in the low half, 2h + 1 in the high) and its negation.
#define PAIR_INDEX(h) ((unsigned)(2 * (h)) | (unsigned)(2 * (h) + 1) << 16)
#define PAIR_NEGATED(h) \
    (((unsigned)(-2 * (h)) & 0xffffu) | ((unsigned)(-2 * (h) - 1) & 0xffffu) << 16)

extern "C" __global__ void __launch_bounds__(SELECT_THREADS)
sgm_select(const unsigned char* paths, float* raw, int height, int width, int uniqueness,
           int lr_max_diff) {
    // each pixel's record (least | total below the winner << 16, total above | winner << 16 |
    // not unique << 31), then the right view's best (cost << 16 | d) per column after
    // PATH_LEVELS columns left of the image that take the candidates there (so no test), then
    // each group's totals (halfwords)
    extern __shared__ unsigned shared[];
    uint2* records = reinterpret_cast<uint2*>(shared);
    unsigned* right_best = shared + 2 * width + PATH_LEVELS;
    const int groups = blockDim.x / SELECT_LANES;
    const int group = threadIdx.x / SELECT_LANES;
    const int sub = threadIdx.x % SELECT_LANES;
    unsigned* group_totals = shared + 3 * width + PATH_LEVELS + group * TOTAL_PITCH;
    const int v = blockIdx.x;
    const size_t plane = (size_t)height * width * PATH_LEVELS;
    for (int x = threadIdx.x; x < width + PATH_LEVELS; x += blockDim.x)
        shared[2 * width + x] = 0xffffffffu;
    const int first_level = sub * SELECT_PER_LANE;
    const unsigned first_pair = (unsigned)first_level * 0x10001u;
    // halves that hold no real level: padding, and an odd lane's missing last half
    unsigned far_half[SELECT_PAIRS];
#pragma unroll
    for (int h = 0; h < SELECT_PAIRS; ++h) {
        const bool low_far = first_level + 2 * h >= LEVELS;
        const bool high_far = 2 * h + 1 >= SELECT_PER_LANE || first_level + 2 * h + 1 >= LEVELS;
        far_half[h] = (low_far ? 0xffffu : 0u) | (high_far ? 0xffff0000u : 0u);
    }
    __syncthreads();
    // each group's next pixel's path bytes are read while it searches the current one's
    const unsigned char* row_cells = paths + (size_t)v * width * PATH_LEVELS + first_level;
    PathReads next;
    if (SELECT_AHEAD)
        read_path_bytes(row_cells + (size_t)min(group, width - 1) * PATH_LEVELS, plane, next);
    for (int first = 0; first < width; first += groups) {
        // a group past the row's end repeats the last pixel: its right-view candidates are
        // that pixel's own, so they change nothing
        const int u = min(first + group, width - 1);
        const bool inside = first + group < width;
        PathReads reads;
        if (SELECT_AHEAD) {
            reads = next;
            if (first + groups < width)
                read_path_bytes(row_cells + (size_t)min(first + groups + group, width - 1)
                                                * PATH_LEVELS, plane, next);
        } else {
            read_path_bytes(row_cells + (size_t)u * PATH_LEVELS, plane, reads);
        }
        unsigned halves[SELECT_PAIRS];
#pragma unroll
        for (int h = 0; h < SELECT_PAIRS; ++h) halves[h] = 0;
        add_path_bytes(reads, halves);
        if (PADDED || SELECT_PER_LANE % 2 != 0) {
#pragma unroll
            for (int h = 0; h < SELECT_PAIRS; ++h)
                halves[h] = (halves[h] & ~far_half[h]) | (FAR_TOTAL * 0x10001u & far_half[h]);
        }
        // the winner: least total, then least level
        unsigned keys = 0xffffffffu;
#pragma unroll
        for (int h = 0; h < SELECT_PAIRS; ++h)
            keys = __vminu2(keys, halves[h] * 32u + PAIR_INDEX(h));
        keys = __vminu2(keys, __byte_perm(keys, 0u, 0x1032)) & 0xffffu;
        unsigned key = (keys >> 5) << (5 + SELECT_LANE_BITS) | (unsigned)sub << 5 | (keys & 31u);
        key = group_minimum<SELECT_LANES>(key);
        const int best = (int)((key >> 5) & (SELECT_LANES - 1)) * SELECT_PER_LANE
                         + (int)(key & 31u);
        const unsigned least = key >> (5 + SELECT_LANE_BITS);
        // the runner-up beyond the winner's neighbours: a level k of this lane with
        // |k - here| <= 1 has min(k + 2 - here, here + 2 - k) in 1 .. 2, else at most 0
        const int here = best - first_level;
        const unsigned before = ((unsigned)(2 - here) & 0xffffu) * 0x10001u;
        const unsigned after = ((unsigned)(here + 2) & 0xffffu) * 0x10001u;
        unsigned far = 0xffffffffu;
#pragma unroll
        for (int h = 0; h < SELECT_PAIRS; ++h) {
            const unsigned from_above = __viaddmax_s16x2(after, PAIR_NEGATED(h), 0x80008000u);
            const unsigned near = __viaddmin_s16x2_relu(PAIR_INDEX(h), before, from_above);
            far = __vminu2(far, halves[h] + near * 2048u);
        }
        far = __vminu2(far, __byte_perm(far, 0u, 0x1032)) & 0xffffu;
        const unsigned second = group_minimum<SELECT_LANES>(far);
#if SELECT_PER_LANE % 2 == 0
#pragma unroll
        for (int h = 0; h < SELECT_PAIRS; ++h) group_totals[first_level / 2 + h] = halves[h];
#else
#pragma unroll
        for (int k = 0; k < SELECT_PER_LANE; ++k)
            reinterpret_cast<unsigned short*>(group_totals)[first_level + k] =
                (unsigned short)(halves[k / 2] >> (16 * (k % 2)));
#endif
        // candidates (total << 16 | d) for the right view's columns u - d, each by an atomic
        unsigned* column = right_best + (u - first_level);
#pragma unroll
        for (int h = 0; h < SELECT_PAIRS; ++h) {
            const unsigned levels = first_pair + PAIR_INDEX(h);
            atomicMin(column - 2 * h, __byte_perm(levels, halves[h], 0x5410));
            if (2 * h + 1 < SELECT_PER_LANE)
                atomicMin(column - 2 * h - 1, __byte_perm(levels, halves[h], 0x7632));
        }
        __syncwarp();
        if (sub == 0 && inside) {
            const unsigned short* totals = reinterpret_cast<const unsigned short*>(group_totals);
            const unsigned below = best > 0 ? totals[best - 1] : 0u;
            const unsigned above = best < LEVELS - 1 ? totals[best + 1] : 0u;
            const bool unique =
                uniqueness <= 0 || 100u * least < (unsigned)(100 - uniqueness) * second;
            records[u] = make_uint2(least | below << 16,
                                    above | (unsigned)best << 16 | (unique ? 0u : 1u << 31));
        }
        __syncwarp();
    }
    __syncthreads();
    for (int u = threadIdx.x; u < width; u += blockDim.x) {
        const uint2 record = records[u];
        const int best = (int)((record.y >> 16) & 0x7fffu);
        const int least = (int)(record.x & 0xffffu);
        bool valid = !(record.y >> 31) && u - best >= 0;
        if (valid && lr_max_diff >= 0)
            valid = abs((int)(right_best[u - best] & 0xffffu) - best) <= lr_max_diff;
        float value = (float)best;
        if (best > 0 && best < LEVELS - 1) {
            const int below = (int)(record.x >> 16), above = (int)(record.y & 0xffffu);
            const int denominator = max(below + above - 2 * least, 1);
            value = value + __fdiv_rn((float)(below - above), 2.0f * (float)denominator);
        }
        raw[(size_t)v * width + u] = valid ? value : -1.0f;
    }
}

// 3x3 median (edge-replicated; -1 = invalid takes part), census border, the GPT shift added
// back (kappa(u - D0, v), interpolated between the columns beside u - D0, as
// perspective.add_shifts: the product is exact, so a fused multiply-add rounds alike),
// matches left of the image dropped, pixels whose band reaches left of the right image (u -
// (LEVELS - 1) < first(v)) dropped, and textureless pixels: a zero left census word here and
// at the 8 neighbours (edge-replicated).
// out: D1, NaN invalid.
extern "C" __global__ void sgm_finish(const float* raw, const unsigned* census_left,
                                      const int* shifts, float* out, int height, int width,
                                      int median) {
    const int u = blockIdx.x * blockDim.x + threadIdx.x;
    const int v = blockIdx.y * blockDim.y + threadIdx.y;
    if (u >= width || v >= height) return;
    float value;
    if (median) {
        float w[9];
#pragma unroll
        for (int a = 0; a < 3; ++a)
#pragma unroll
            for (int b = 0; b < 3; ++b)
                w[a * 3 + b] = raw[clamp_index(v + a - 1, height) * width
                                   + clamp_index(u + b - 1, width)];
#pragma unroll
        for (int i = 0; i < 5; ++i)
#pragma unroll
            for (int j = i + 1; j < 9; ++j) {
                const float low = fminf(w[i], w[j]);
                w[j] = fmaxf(w[i], w[j]);
                w[i] = low;
            }
        value = w[4];
    } else {
        value = raw[v * width + u];
    }
    const float column = (float)u - value;
    const float left_column = floorf(column);
    const float fraction = column - left_column;
    const int lower = gpt_shift(shifts, height, v, (int)left_column);
    const int upper = gpt_shift(shifts, height, v, (int)left_column + 1);
    const float disparity = value + ((float)lower + fraction * (float)(upper - lower));
    const bool border = v < BORDER_Y || v >= height - BORDER_Y || u < BORDER_X
                        || u >= width - BORDER_X;
    bool textureless = true;
#pragma unroll
    for (int a = -1; a <= 1; ++a)
#pragma unroll
        for (int b = -1; b <= 1; ++b)
            textureless = textureless
                          && census_left[clamp_index(v + a, height) * width
                                         + clamp_index(u + b, width)] == 0u;
    const bool band_outside = u - (LEVELS - 1) < shifts[v];
    const bool invalid = value < 0.0f || (float)u - disparity < 0.0f || border || textureless
                         || band_outside;
    out[v * width + u] = invalid ? __int_as_float(0x7fc00000) : disparity;
}
