// Robust road fit on the device: one launch of one block per multiprocessor (launched
// cooperatively, so every block is resident) runs every round of stages/road_model.fit_road
// (planar rounds with the roll solve, then the quadratic rounds), so the only readback is the
// result. The elements are cut into segments of 32 columns of a row, dealt to the warps of
// the grid in turn; sums and histograms are combined through global memory behind grid
// barriers, block partials summed in block order, so every block holds the same totals and
// solves the same small systems. Per element of the subsampled map: d = sub * scale at column
// table u[j], row table v[i]; x = u / 1000, y = v / 1000 come from the same tables. The robust
// sigma is the exact median of |residual| (as float32) by a three-pass radix select (each
// block's keys in its shared memory where they fit, per-block histograms added into global
// ones).
//
// out: [0] status (0 ok, 1 fewer than 3 valid, 2 degenerate), [1] valid count,
// [2..4] a0, a1, phi, [5] planar inliers, [6] planar sigma, [7..12] curvature c0..c5,
// [13] quadratic inliers, [14] quadratic sigma.
// model: the chosen model as the other kernels read it (stages/road_model.RoadModel
// .kernel_params): a0, a1, cos(phi), sin(phi), c0..c5 (zeros unless the quadratic model is
// chosen), curved (0 or 1); NaN when the fit failed, so later stages find no road.
// prior: a road model in the same layout, then at PRIOR_TOLERANCE the distance (px) from it
// within which the fit takes pixels (0: no prior, every valid pixel), at PRIOR_MIN_SHARE the
// share of the valid pixels that must lie that close (else every valid pixel).
// Defined by the launcher (stages/road_model.py, _kernel): THREADS, BINS, MAX_SUMS, the fit
// report's layout (FIT_*), the road parameters' (ROAD_*) and PRIOR_*.

#include "block_scan.cuh"
#include "grid_barrier.cuh"
#include "road_disparity.cuh"
#include "warp_sum.cuh"

#define WARPS (THREADS / 32)
#define PER_THREAD_BINS (BINS / THREADS)
static_assert(PER_THREAD_BINS == 8, "locate reads two 4-bin vectors per thread");
#define NOT_MASKED 0xffffffffu
// doubles that fit the shared histograms, which grid_sums stages the blocks' totals in
#define STAGED_TOTALS (2 * BINS * sizeof(unsigned) / sizeof(double))
static_assert(STAGED_TOTALS >= MAX_SUMS, "a block's totals fit the staging");

__device__ __forceinline__ bool finite(float x) {
    return (__float_as_uint(x) & 0x7f800000u) != 0x7f800000u;
}

// Grid-wide state of one thread: the launch's workspace and how many barriers, sums and
// histograms it has passed (every thread makes the same calls, so the counts agree).
struct GridWork {
    unsigned* barrier;   // arrivals at grid barriers, 0 at launch
    double* partials;    // [2][gridDim.x][MAX_SUMS] block totals, alternate buffers
    unsigned* hists;     // [HIST_BUFFERS][BINS], 0 at launch, each used once
    unsigned barriers;
    int sums;
    int histograms;
};

// The grid's barrier (grid_barrier.cuh) on the launch's arrival counter.
__device__ __forceinline__ void grid_sync(GridWork& grid) {
    grid_barrier(grid.barrier, grid.barriers);
}

// Calls f(i, row, col, local) for this block's elements (local: the element's index among
// the block's): segments of 32 columns of a row go to the warps of the grid in turn (coalesced
// rows); every pass uses this partition, so an element is always handled by the same thread.
template <typename F>
__device__ __forceinline__ void for_each_element(int height, int width, F&& f) {
    const int lane = threadIdx.x & 31;
    const int per_row = (width + 31) >> 5;
    const int segments = height * per_row;
    const int stride = gridDim.x * WARPS;
    int local = threadIdx.x;
    for (int s = blockIdx.x * WARPS + (threadIdx.x >> 5); s < segments;
         s += stride, local += THREADS) {
        const int row = s / per_row;
        const int col = (s - row * per_row) * 32 + lane;
        if (col < width) f(row * width + col, row, col, local);
    }
}

struct RoadState {
    double a0, a1, cos_phi, sin_phi, phi;
    double curvature[6];
    double threshold;
    int use_mask;
    int status;
    unsigned prefix[2], rank[2];
    double sums[MAX_SUMS];
};

// a0 + a1 (v cos(phi) - u sin(phi)), in the reference's order, without FMA.
__device__ __forceinline__ double planar_at(const RoadState& s, double u, double v) {
    return __dadd_rn(s.a0, __dmul_rn(s.a1, __dsub_rn(__dmul_rn(v, s.cos_phi),
                                                    __dmul_rn(u, s.sin_phi))));
}

// The road disparity of a model in the kernel parameters' layout, as road_model.params_at.
__device__ __forceinline__ double params_at(const double* p, double u, double v, double x,
                                            double y) {
    const double planar = road_planar(p, u, v);
    return __dadd_rn(planar, __dmul_rn(p[ROAD_CURVED], curvature_at(p + ROAD_C0, x, y, planar)));
}

// Sum of COUNT per-thread values over the grid in a fixed order (warps, then blocks); result
// in state.sums of every block. The blocks' totals are read into `staging` (shared, room for
// STAGED_TOTALS doubles; free during the call) by the whole block at once, then added in block
// order from there.
template <int COUNT>
__device__ void grid_sums(double (&values)[COUNT], double (*partial)[MAX_SUMS],
                          RoadState& state, GridWork& grid, double* staging) {
    const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
#pragma unroll
    for (int k = 0; k < COUNT; ++k) {
        const double value = warp_sum(values[k]);
        if (lane == 0) partial[warp][k] = value;
    }
    __syncthreads();
    double* totals = grid.partials + (grid.sums & 1) * gridDim.x * MAX_SUMS;
    grid.sums += 1;
    if (threadIdx.x < COUNT) {
        double total = 0.0;
        for (int w = 0; w < WARPS; ++w) total += partial[w][threadIdx.x];
        totals[blockIdx.x * MAX_SUMS + threadIdx.x] = total;
    }
    grid_sync(grid);
    constexpr int PER_STAGE = STAGED_TOTALS / COUNT;  // blocks' totals staged at a time
    double total = 0.0;
    for (int first = 0; first < (int)gridDim.x; first += PER_STAGE) {
        const int staged = min(PER_STAGE, (int)gridDim.x - first) * COUNT;
        for (int i = threadIdx.x; i < staged; i += THREADS)
            staging[i] = __ldcg(&totals[(first + i / COUNT) * MAX_SUMS + i % COUNT]);
        __syncthreads();
        if (threadIdx.x < COUNT)
            for (int i = threadIdx.x; i < staged; i += COUNT) total += staging[i];
        __syncthreads();
    }
    if (threadIdx.x < COUNT) state.sums[threadIdx.x] = total;
    __syncthreads();
}

// Adds the block's histogram to the next unused global one (non-zero bins only) and returns
// that global histogram; read it after a grid_sync.
__device__ const unsigned* publish_histogram(const unsigned* hist, GridWork& grid) {
    unsigned* global = grid.hists + (long long)grid.histograms * BINS;
    grid.histograms += 1;
    for (int i = threadIdx.x; i < BINS; i += THREADS) {
        const unsigned count = hist[i];
        if (count != 0) atomicAdd(&global[i], count);
    }
    return global;
}

// The bins of the grid's histogram `hist` (global) holding the elements state.rank[which]
// (0-based, by ascending bin) for which = first_which..last_which, from one read of the
// histogram: state.prefix[which] gains the bin as its low `bits` bits, state.rank[which]
// becomes the rank inside the bin. Call after the grid_sync that follows its publication.
__device__ void locate(const unsigned* hist, int first_which, int last_which, int bits,
                       RoadState& state, unsigned* warp_totals) {
    const unsigned ranks[2] = {state.rank[0], state.rank[1]};
    const int first = threadIdx.x * PER_THREAD_BINS;
    const uint4 low = __ldcg(reinterpret_cast<const uint4*>(hist + first));
    const uint4 high = __ldcg(reinterpret_cast<const uint4*>(hist + first + 4));
    const unsigned counts[PER_THREAD_BINS] = {low.x, low.y, low.z, low.w,
                                              high.x, high.y, high.z, high.w};
    unsigned local = 0;
#pragma unroll
    for (int b = 0; b < PER_THREAD_BINS; ++b) local += counts[b];
    const unsigned before = block_inclusive_scan(local, warp_totals) - local;
    for (int which = first_which; which <= last_which; ++which) {
        const unsigned rank = ranks[which];
        if (rank < before || rank >= before + local) continue;
        unsigned below = before;
        for (int b = 0; b < PER_THREAD_BINS; ++b) {
            const unsigned count = counts[b];
            if (rank < below + count) {
                state.prefix[which] = (state.prefix[which] << bits) | (unsigned)(first + b);
                state.rank[which] = rank - below;
                break;
            }
            below += count;
        }
    }
    __syncthreads();
}

// 1.4826 x median of the masked keys (float bits of |residual|, NOT_MASKED else) over the
// grid: keys[local] in shared memory (local_keys) or keys[i] in global memory. Each block's
// pass-0 histogram (key >> 20) is already in its hist[0].
__device__ double robust_sigma(const unsigned* keys, bool local_keys, int height, int width,
                               unsigned count, unsigned (*hist)[BINS], RoadState& state,
                               unsigned* warp_totals, GridWork& grid) {
    const unsigned* first = publish_histogram(hist[0], grid);
    grid_sync(grid);
    if (count == 0) return 0.0;
    if (threadIdx.x == 0) {
        state.prefix[0] = state.prefix[1] = 0;
        state.rank[0] = (count - 1) / 2;
        state.rank[1] = count / 2;
    }
    __syncthreads();
    locate(first, 0, 1, 12, state, warp_totals);
    for (int pass = 1; pass <= 2; ++pass) {
        for (int i = threadIdx.x; i < 2 * BINS; i += THREADS) (&hist[0][0])[i] = 0;
        __syncthreads();
        const unsigned p0 = state.prefix[0], p1 = state.prefix[1];
        const int known = pass == 1 ? 20 : 8;
        for_each_element(height, width, [&](int i, int, int, int local) {
            const unsigned key = keys[local_keys ? local : i];
            if (key == NOT_MASKED) return;
            const unsigned bin = pass == 1 ? (key >> 8) & 0xfffu : key & 0xffu;
            if ((key >> known) == p0) atomicAdd(&hist[0][bin], 1u);
            if (p1 != p0 && (key >> known) == p1) atomicAdd(&hist[1][bin], 1u);
        });
        __syncthreads();
        const unsigned* low = publish_histogram(hist[0], grid);
        const unsigned* high = p1 != p0 ? publish_histogram(hist[1], grid) : low;
        grid_sync(grid);
        const int bits = pass == 1 ? 12 : 8;
        if (p1 == p0) {
            locate(low, 0, 1, bits, state, warp_totals);
        } else {
            locate(low, 0, 0, bits, state, warp_totals);
            locate(high, 1, 1, bits, state, warp_totals);
        }
    }
    const float low = __uint_as_float(state.prefix[0]);
    const float high = __uint_as_float(state.prefix[1]);
    return 1.4826 * ((double)low + (double)high) / 2.0;
}

// stages/road_model.solve_roll on the nine moments in state.sums (thread 0).
__device__ void solve_roll(RoadState& s) {
    const double* m = s.sums;
    const double n = m[0], su = m[1], sv = m[2], sd = m[3], suu = m[4], svv = m[5],
                 suv = m[6], sud = m[7], svd = m[8];
    if (n < 3.0) {
        s.status = 1;
        return;
    }
    const double mu = su / n, mv = sv / n, md = sd / n;
    const double cuu = suu - n * mu * mu, cvv = svv - n * mv * mv, cuv = suv - n * mu * mv;
    const double cud = sud - n * mu * md, cvd = svd - n * mv * md;
    const double det = cvv * cuu - cuv * cuv;
    if (fabs(det) <= 1e-9 * fmax(cuu * cvv, 1e-300)) {
        s.status = 2;
        return;
    }
    double w[2][2] = {{(cuu * cvd - cuv * cud) / det, (cvv * cud - cuv * cvd) / det},
                      {-cud, cvd}};
    if (cvd == 0.0 && cud == 0.0) {
        w[1][0] = 1.0;
        w[1][1] = 0.0;
    }
    bool have = false;
    double best_residual = 0.0;
    for (int k = 0; k < 2; ++k) {
        const double norm = hypot(w[k][0], w[k][1]);
        if (norm == 0.0) continue;
        double c = w[k][0] / norm, sn = -w[k][1] / norm;
        if (c < 0.0) {
            c = -c;
            sn = -sn;
        }
        const double var_t = c * c * cvv - 2.0 * c * sn * cuv + sn * sn * cuu;
        const double cov_td = c * cvd - sn * cud;
        const double a1 = var_t > 0.0 ? cov_td / var_t : 0.0;
        const double residual = -a1 * cov_td;
        if (!have || residual < best_residual) {
            have = true;
            best_residual = residual;
            s.a0 = md - a1 * (c * mv - sn * mu);
            s.a1 = a1;
            s.phi = atan2(sn, c);
        }
    }
    s.cos_phi = cos(s.phi);
    s.sin_phi = sin(s.phi);
}

// Cholesky solve of the 6x6 normal equations (registers only); false when a pivot is not
// clearly positive (a rank-deficient or badly conditioned system).
__device__ __forceinline__ bool solve_cholesky(RoadState& s) {
    double a[6][6], l[6][6];
    int k = 0;
#pragma unroll
    for (int i = 0; i < 6; ++i)
#pragma unroll
        for (int j = i; j < 6; ++j) {
            a[i][j] = a[j][i] = s.sums[k++];
        }
#pragma unroll
    for (int j = 0; j < 6; ++j) {
        double pivot = a[j][j];
#pragma unroll
        for (int m = 0; m < j; ++m) pivot -= l[j][m] * l[j][m];
        if (!(pivot > 1e-10 * a[j][j])) return false;
        l[j][j] = sqrt(pivot);
#pragma unroll
        for (int i = j + 1; i < 6; ++i) {
            double value = a[i][j];
#pragma unroll
            for (int m = 0; m < j; ++m) value -= l[i][m] * l[j][m];
            l[i][j] = value / l[j][j];
        }
    }
    double y[6];
#pragma unroll
    for (int i = 0; i < 6; ++i) {
        double value = s.sums[21 + i];
#pragma unroll
        for (int m = 0; m < i; ++m) value -= l[i][m] * y[m];
        y[i] = value / l[i][i];
    }
#pragma unroll
    for (int i = 5; i >= 0; --i) {
        double value = y[i];
#pragma unroll
        for (int m = i + 1; m < 6; ++m) value -= l[m][i] * s.curvature[m];
        s.curvature[i] = value / l[i][i];
    }
    return true;
}

// Least-squares (minimum norm, like numpy.linalg.lstsq) solution of the 6x6 normal equations
// in state.sums (21 upper-triangle entries, then 6 right-hand sides): Cholesky when the system
// is well conditioned, else a Jacobi eigen-decomposition with lstsq's cutoff (thread 0).
__device__ void solve_curvature(RoadState& s) {
    if (solve_cholesky(s)) return;
    double a[6][6], vectors[6][6];
    int k = 0;
    for (int i = 0; i < 6; ++i)
        for (int j = i; j < 6; ++j) {
            a[i][j] = a[j][i] = s.sums[k++];
        }
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 6; ++j) vectors[i][j] = i == j ? 1.0 : 0.0;
    for (int sweep = 0; sweep < 50; ++sweep) {
        double off = 0.0, diagonal = 0.0;
        for (int i = 0; i < 6; ++i) {
            diagonal += a[i][i] * a[i][i];
            for (int j = i + 1; j < 6; ++j) off += a[i][j] * a[i][j];
        }
        if (off <= 1e-32 * diagonal) break;
        for (int p = 0; p < 5; ++p)
            for (int q = p + 1; q < 6; ++q) {
                if (a[p][q] == 0.0) continue;
                const double theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                const double t = (theta >= 0.0 ? 1.0 : -1.0)
                                 / (fabs(theta) + sqrt(theta * theta + 1.0));
                const double c = 1.0 / sqrt(t * t + 1.0), sn = t * c;
                for (int r = 0; r < 6; ++r) {
                    const double rp = a[r][p], rq = a[r][q];
                    a[r][p] = c * rp - sn * rq;
                    a[r][q] = sn * rp + c * rq;
                }
                for (int r = 0; r < 6; ++r) {
                    const double pr = a[p][r], qr = a[q][r];
                    a[p][r] = c * pr - sn * qr;
                    a[q][r] = sn * pr + c * qr;
                }
                for (int r = 0; r < 6; ++r) {
                    const double rp = vectors[r][p], rq = vectors[r][q];
                    vectors[r][p] = c * rp - sn * rq;
                    vectors[r][q] = sn * rp + c * rq;
                }
            }
    }
    double largest = 0.0;
    for (int i = 0; i < 6; ++i) largest = fmax(largest, fabs(a[i][i]));
    const double cutoff = 6.0 * 2.220446049250313e-16 * largest;
    for (int i = 0; i < 6; ++i) s.curvature[i] = 0.0;
    for (int e = 0; e < 6; ++e) {
        if (!(fabs(a[e][e]) > cutoff)) continue;
        double projection = 0.0;
        for (int r = 0; r < 6; ++r) projection += vectors[r][e] * s.sums[21 + r];
        projection /= a[e][e];
        for (int r = 0; r < 6; ++r) s.curvature[r] += projection * vectors[r][e];
    }
}

// The model the pipeline goes on with (stages/road_model.model_from_report picks the same):
// the quadratic one where it was fitted, unless auto_select and its sigma is not below
// (1 - gain) x the planar sigma.
__device__ void write_model(const double* out, int status, int quadratic, int auto_select,
                            double gain, double* model) {
    if (status != 0) {
        const double nan = __longlong_as_double(0x7ff8000000000000ll);
        for (int i = 0; i < ROAD_PARAMS; ++i) model[i] = nan;
        return;
    }
    const bool curved = quadratic
        && !(auto_select && !(out[FIT_QUADRATIC_SIGMA] < (1.0 - gain) * out[FIT_PLANAR_SIGMA]));
    double sin_phi, cos_phi;
    sincos(out[FIT_ROLL], &sin_phi, &cos_phi);
    model[ROAD_A0] = out[FIT_A0];
    model[ROAD_A1] = out[FIT_A1];
    model[ROAD_COS] = cos_phi;
    model[ROAD_SIN] = sin_phi;
    for (int i = 0; i < 6; ++i) model[ROAD_C0 + i] = curved ? out[FIT_CURVATURE + i] : 0.0;
    model[ROAD_CURVED] = curved ? 1.0 : 0.0;
}

// workspace: the arrival counter, then float64 [2][gridDim.x][MAX_SUMS] block totals, then
// uint32 [HIST_BUFFERS][BINS] histograms; counter and histograms zero at launch (see
// stages/road_model.fit_on_device for the layout).
extern "C" __global__ void __launch_bounds__(THREADS)
road_fit(const float* __restrict__ sub, const double* __restrict__ tables, int height,
         int width, double scale, int rounds, double outlier_k, int quadratic,
         double* __restrict__ residual, double* __restrict__ planar,
         unsigned* __restrict__ keys, int local_keys, int auto_select, double quadratic_gain,
         unsigned* __restrict__ barrier, double* __restrict__ partials,
         unsigned* __restrict__ hists, double* __restrict__ out, double* __restrict__ model,
         const double* __restrict__ prior) {
    // local_keys: the block's keys (for_each_element's local numbering) fit the dynamic
    // shared memory and the median's passes read them there instead of from `keys`
    extern __shared__ unsigned shared_keys[];
    unsigned* key_store = local_keys ? shared_keys : keys;
    __shared__ __align__(16) unsigned hist[2][BINS];
    __shared__ double partial[WARPS][MAX_SUMS];
    __shared__ unsigned warp_totals[32];
    __shared__ RoadState state;
    double* staging = reinterpret_cast<double*>(&hist[0][0]);
    GridWork grid{barrier, partials, hists, 0u, 0, 0};
    const double* column_u = tables;
    const double* row_v = tables + width;
    const double* column_x = tables + width + height;
    const double* row_y = tables + 2 * width + height;
    const bool leader = blockIdx.x == 0;
    const double prior_tolerance = prior[PRIOR_TOLERANCE];
    __shared__ int prior_active;
    // pixels the prior's band leaves out of every round, once the prior is in use
    auto outside = [&](float raw, int row, int col) {
        return prior_active && !(fabs((double)raw * scale
                                      - params_at(prior, column_u[col], row_v[row],
                                                  column_x[col], row_y[row]))
                                 <= prior_tolerance);
    };
    if (threadIdx.x == 0) prior_active = 0;
    if (threadIdx.x == 0) {
        state.status = 0;
        state.use_mask = 0;
        state.threshold = 0.0;
        for (int i = 0; i < 6; ++i) state.curvature[i] = 0.0;
    }
    __syncthreads();
    for (int phase = 0; phase < (quadratic ? 2 : 1); ++phase) {
        if (prior_tolerance > 0.0 && phase == 0) {
            // the first fit's mask: valid pixels within prior_tolerance of the prior (the
            // quadratic rounds start from the planar model's inliers, which lie there)
            double counts[2] = {0.0, 0.0};
            for_each_element(height, width, [&](int i, int row, int col, int local) {
                const float raw = sub[i];
                if (!finite(raw)) return;
                const double r = (double)raw * scale - params_at(prior, column_u[col],
                                                                 row_v[row], column_x[col],
                                                                 row_y[row]);
                residual[i] = r;
                counts[0] += 1.0;
                if (fabs(r) <= prior_tolerance) counts[1] += 1.0;
            });
            grid_sums<2>(counts, partial, state, grid, staging);
            if (threadIdx.x == 0) {
                state.use_mask = state.sums[1] >= prior[PRIOR_MIN_SHARE] * state.sums[0];
                prior_active = state.use_mask;
                state.threshold = prior_tolerance;
                if (phase == 0 && leader) out[FIT_VALID] = state.sums[0];
            }
            __syncthreads();
        }
        for (int round = 0; round <= rounds; ++round) {
            const bool use_mask = state.use_mask;
            const double threshold = state.threshold;
            // sums over the mask of this round
            if (phase == 0) {
                double values[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
                for_each_element(height, width, [&](int i, int row, int col, int local) {
                    const float raw = sub[i];
                    if (!finite(raw) || (use_mask && !(fabs(residual[i]) <= threshold))
                        || outside(raw, row, col))
                        return;
                    const double d = (double)raw * scale;
                    const double u = column_u[col], v = row_v[row];
                    values[0] += 1.0;
                    values[1] += u;
                    values[2] += v;
                    values[3] += d;
                    values[4] += u * u;
                    values[5] += v * v;
                    values[6] += u * v;
                    values[7] += u * d;
                    values[8] += v * d;
                });
                grid_sums<9>(values, partial, state, grid, staging);
                if (threadIdx.x == 0) solve_roll(state);
            } else {
                double values[27];
#pragma unroll
                for (int k = 0; k < 27; ++k) values[k] = 0.0;
                for_each_element(height, width, [&](int i, int row, int col, int local) {
                    const float raw = sub[i];
                    if (!finite(raw) || (use_mask && !(fabs(residual[i]) <= threshold))
                        || outside(raw, row, col))
                        return;
                    const double d = (double)raw * scale;
                    const double x = column_x[col], y = row_y[row];
                    const double inverse = road_inverse(planar[i]);
                    const double design[6] = {1.0, x, y, x * x * inverse, x * inverse,
                                              inverse};
                    const double target = d - planar[i];
                    int k = 0;
#pragma unroll
                    for (int a = 0; a < 6; ++a)
#pragma unroll
                        for (int b = a; b < 6; ++b) values[k++] += design[a] * design[b];
#pragma unroll
                    for (int a = 0; a < 6; ++a) values[21 + a] += design[a] * target;
                });
                grid_sums<27>(values, partial, state, grid, staging);
                if (threadIdx.x == 0) solve_curvature(state);
            }
            __syncthreads();
            if (state.status != 0) break;
            const unsigned count = (unsigned)state.sums[0];
            if (phase == 0 && round == 0 && threadIdx.x == 0 && leader
                && !(prior_tolerance > 0.0))
                out[FIT_VALID] = state.sums[0];
            // residuals of this round's model, keys of this round's mask, first histogram
            for (int i = threadIdx.x; i < 2 * BINS; i += THREADS) (&hist[0][0])[i] = 0;
            __syncthreads();
            for_each_element(height, width, [&](int i, int row, int col, int local) {
                const float raw = sub[i];
                if (!finite(raw)) {
                    key_store[local_keys ? local : i] = NOT_MASKED;
                    return;
                }
                const bool masked = (!use_mask || fabs(residual[i]) <= threshold)
                                    && !outside(raw, row, col);
                const double d = (double)raw * scale;
                double model;
                if (phase == 0) {
                    model = planar_at(state, column_u[col], row_v[row]);
                } else {
                    model = __dadd_rn(planar[i], curvature_at(state.curvature, column_x[col],
                                                              row_y[row], planar[i]));
                }
                const double r = d - model;
                residual[i] = r;
                const unsigned key = masked ? __float_as_uint((float)fabs(r)) : NOT_MASKED;
                key_store[local_keys ? local : i] = key;
                if (masked) atomicAdd(&hist[0][key >> 20], 1u);
            });
            __syncthreads();
            const double sigma = robust_sigma(key_store, local_keys, height, width, count,
                                              hist, state, warp_totals, grid);
            if (threadIdx.x == 0) {
                state.threshold = outlier_k * fmax(sigma, 1e-3);
                state.use_mask = 1;
                if (leader) out[phase == 0 ? FIT_PLANAR_SIGMA : FIT_QUADRATIC_SIGMA] = sigma;
            }
            __syncthreads();
        }
        if (state.status != 0) break;
        // inliers of the final mask; the planar model's values for the quadratic phase
        const double threshold = state.threshold;
        double inliers[1] = {0.0};
        for_each_element(height, width, [&](int i, int row, int col, int local) {
            if (!finite(sub[i])) return;
            if (fabs(residual[i]) <= threshold && !outside(sub[i], row, col)) inliers[0] += 1.0;
            if (phase == 0 && quadratic) planar[i] = planar_at(state, column_u[col], row_v[row]);
        });
        grid_sums<1>(inliers, partial, state, grid, staging);
        if (threadIdx.x == 0 && leader) {
            if (phase == 0) {
                out[FIT_A0] = state.a0;
                out[FIT_A1] = state.a1;
                out[FIT_ROLL] = state.phi;
                out[FIT_PLANAR_INLIERS] = state.sums[0];
            } else {
                for (int i = 0; i < 6; ++i) out[FIT_CURVATURE + i] = state.curvature[i];
                out[FIT_QUADRATIC_INLIERS] = state.sums[0];
            }
        }
        // the quadratic rounds start from this mask: the planar model's inliers
        __syncthreads();
    }
    if (threadIdx.x == 0 && leader) {
        out[FIT_STATUS] = state.status;
        write_model(out, state.status, quadratic, auto_select, quadratic_gain, model);
    }
}
