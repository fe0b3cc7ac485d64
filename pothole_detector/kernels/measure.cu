// Per-pothole sums in one pass over the label image. Reference: stages/measure.py (measure,
// depth_below_road, surface_patches, hidden_floor_depth, under_opening). sums: float64
// [count + 1][SUMS], columns SUM_* (measure.Sum: pixels, footprint area, valid area, floor
// area, depth x floor area (the depth hidden_floor_depth estimates), x, y, z x area (valid
// pixels), pixels in a far corner region, pixels of significant superpixels); extremes:
// int32 [count + 1][EXTREMES], columns EXTREME_* (measure.Extreme: largest depth as
// order-preserving float bits, of points under the pothole's opening; u min, v min, u max,
// v max). Warps whose labelled pixels share one label add once per warp.
// Defined by the launcher (stages/measure.py, _kernel): SUMS, EXTREMES, SUM_*, EXTREME_*,
// THREADS, HIDDEN_FLOOR_* (measure.HIDDEN_FLOOR_CONSTANTS) and the road parameters' layout and
// constants (ROAD_*, stages/road_model.ROAD_DEFINES).

#include "road_disparity.cuh"

#define FULL_MASK 0xffffffffu

__device__ __forceinline__ int ordered_bits(float value) {
    const int bits = __float_as_int(value);
    return bits >= 0 ? bits : bits ^ 0x7fffffff;
}

__device__ __forceinline__ bool finite(float x) {
    return (__float_as_uint(x) & 0x7f800000u) != 0x7f800000u;
}

// The 3D point of pixel (u, v) with disparity d (z = f B / d; NaN where d <= 0 or NaN).
__device__ __forceinline__ void point_at(int u, int v, float d, double f, double cx, double cy,
                                         double fb, double* point) {
    const double z = d > 0.0f ? fb / (double)d : __longlong_as_double(0x7ff8000000000000ll);
    point[0] = (u - cx) * z / f;
    point[1] = (v - cy) * z / f;
    point[2] = z;
}

// measure.surface_patches: n . (dQ/du x dQ/dv) by central differences, 0 where it is not
// positive, a neighbour lies off the image or has no disparity; edge_on: the patch is seen at a
// grazing angle (sine) under HIDDEN_FLOOR_GRAZING_PERCENT % of the road's.
__device__ double surface_patch(const float* disparity, int u, int v, int height, int width,
                                double f, double cx, double cy, double fb, const double* normal,
                                bool* edge_on) {
    *edge_on = false;
    if (u <= 0 || u >= width - 1 || v <= 0 || v >= height - 1) return 0.0;
    const long long at = (long long)v * width + u;
    double right[3], left[3], below[3], above[3];
    point_at(u + 1, v, disparity[at + 1], f, cx, cy, fb, right);
    point_at(u - 1, v, disparity[at - 1], f, cx, cy, fb, left);
    point_at(u, v + 1, disparity[at + width], f, cx, cy, fb, below);
    point_at(u, v - 1, disparity[at - width], f, cx, cy, fb, above);
    double du[3], dv[3];
    for (int k = 0; k < 3; ++k) {
        du[k] = 0.5 * (right[k] - left[k]);
        dv[k] = 0.5 * (below[k] - above[k]);
    }
    const double cross[3] = {du[1] * dv[2] - du[2] * dv[1], du[2] * dv[0] - du[0] * dv[2],
                             du[0] * dv[1] - du[1] * dv[0]};
    const double area = normal[0] * cross[0] + normal[1] * cross[1] + normal[2] * cross[2];
    const double ray_x = (u - cx) / f, ray_y = (v - cy) / f;
    const double seen = fabs(cross[0] * ray_x + cross[1] * ray_y + cross[2]);
    const double incidence = normal[0] * ray_x + normal[1] * ray_y + normal[2];
    const double size = sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]);
    *edge_on = seen < HIDDEN_FLOOR_GRAZING_PERCENT / 100.0 * incidence * size;
    return isfinite(area) && area > 0.0 ? area : 0.0;
}

// measure.depth_below_road of one pixel: its depth below the road, NaN where its ray does not
// meet the road plane in front of the camera or d is not positive; and where footprint is
// given, the pixel's footprint on the road (0 where its ray does not meet the road plane).
__device__ float depth_below(const double* road, const double* normal, int u, int v, float d,
                             double f, double cx, double cy, double fb,
                             double* footprint = nullptr) {
    const double road_d = road_disparity(road, (double)u, (double)v);
    const double incidence = normal[0] * (u - cx) / f + normal[1] * (v - cy) / f + normal[2];
    const bool on_road = road_d > 0.0 && incidence > 0.0;
    const double road_z = fb / road_d;
    if (footprint != nullptr)
        *footprint = on_road ? (double)(float)(road_z * road_z / (f * f * incidence)) : 0.0;
    if (!(on_road && d > 0.0f)) return __int_as_float(0x7fffffff);
    return fmaxf((float)((fb / (double)d - road_z) * incidence), 0.0f);
}

// measure.hidden_floor_depth of an edge-on pixel (u, v) of pothole label with depth: halfway
// (HIDDEN_FLOOR_BLEND_PERCENT) to the deepest floor of the same pothole seen within
// HIDDEN_FLOOR_ROWS - 1 rows farther up the column, where that is deeper.
__device__ float hidden_floor_depth(const int* labels, const float* disparity, int u, int v,
                                    int width, int label, float depth, double f, double cx,
                                    double cy, double fb, const double* road,
                                    const double* normal) {
    float beyond = __int_as_float(0xff800000);
    for (int step = 1; step < HIDDEN_FLOOR_ROWS && v - step >= 0; ++step) {
        const long long at = (long long)(v - step) * width + u;
        if (labels[at] != label) continue;
        const float seen = depth_below(road, normal, u, v - step, disparity[at], f, cx, cy, fb);
        if (finite(seen)) beyond = fmaxf(beyond, seen);
    }
    return beyond > depth ? depth + HIDDEN_FLOOR_BLEND_PERCENT / 100.0f * (beyond - depth)
                          : depth;
}

// measure.under_opening of pixel (u, v) of pothole label with disparity d and finite depth:
// whether the road point right above its surface point (along the road's unit normal) lies in
// the pothole's outline; where it falls off the image, the pixel where the step towards it
// leaves the image stands for it. Rounded as NumPy does, without fused multiply-adds.
__device__ bool under_opening(const int* labels, int u, int v, int height, int width, int label,
                              float d, float depth, double f, double cx, double cy, double fb,
                              const double* normal) {
    const double z0 = fb / (double)d, lift = depth;
    const double x = __dsub_rn((u - cx) * z0 / f, __dmul_rn(lift, normal[0]));
    const double y = __dsub_rn((v - cy) * z0 / f, __dmul_rn(lift, normal[1]));
    const double z = __dsub_rn(z0, __dmul_rn(lift, normal[2]));
    const double du = f * x / z + cx - u, dv = f * y / z + cy - v;
    if (!(z > 0.0 && isfinite(du) && isfinite(dv))) return true;
    double reach = 1.0;
    if (du > 0.0) reach = fmin(reach, (width - 1 - u) / du);
    if (du < 0.0) reach = fmin(reach, -u / du);
    if (dv > 0.0) reach = fmin(reach, (height - 1 - v) / dv);
    if (dv < 0.0) reach = fmin(reach, -v / dv);
    const double step = fmax(reach, 0.0);
    const int at_u = min(max((int)rint(__dadd_rn(u, __dmul_rn(step, du))), 0), width - 1);
    const int at_v = min(max((int)rint(__dadd_rn(v, __dmul_rn(step, dv))), 0), height - 1);
    return labels[(long long)at_v * width + at_u] == label;
}

extern "C" __global__ void measure_reset(double* sums, int* extremes, int count) {
    const int label = blockIdx.x * blockDim.x + threadIdx.x;
    if (label > count) return;
    for (int k = 0; k < SUMS; ++k) sums[label * SUMS + k] = 0.0;
    int* row = extremes + label * EXTREMES;
    row[EXTREME_LARGEST_DEPTH] = ordered_bits(__int_as_float(0xff800000));
    row[EXTREME_U_MIN] = row[EXTREME_V_MIN] = 0x7fffffff;
    row[EXTREME_U_MAX] = row[EXTREME_V_MAX] = -1;
}

// road: a0, a1, cos(phi), sin(phi), c0..c5, curved (stages/road_model.RoadModel
// .kernel_params). Road disparity as road_disparity.cuh; the unit normal of its linear part as
// measure.road_normal computes it. The far corner regions (components.in_far_corner): the top
// `side` rows, within `side` columns of the row's valid span first..last; `significant` (one
// byte per superpixel of `superpixels`) is read where `has_significant`.
extern "C" __global__ void __launch_bounds__(THREADS)
measure_potholes(const int* labels, const float* disparity, int height, int width,
                 double f, double cx, double cy, double fb, const double* road,
                 const int* first, const int* last, int side, const int* superpixels,
                 const bool* significant, int has_significant, double* sums, int* extremes) {
    const long long index = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const bool inside = index < (long long)height * width;
    const int label = inside ? labels[index] : 0;
    const unsigned labelled = __ballot_sync(FULL_MASK, label > 0);
    if (labelled == 0) return;
    const int u = (int)(index % width), v = (int)(index / width);
    double values[SUMS] = {};
    float depth_value = __int_as_float(0xff800000);
    if (label > 0) {
        double normal[3];
        road_unit_normal(road, f, cx, cy, normal);
        double footprint;
        const float depth = depth_below(road, normal, u, v, disparity[index], f, cx, cy, fb,
                                        &footprint);
        values[SUM_PIXELS] = 1.0;
        values[SUM_AREA] = footprint;
        values[SUM_CORNER] = v < side && (u < first[v] + side || u > last[v] - side) ? 1.0
                                                                                     : 0.0;
        values[SUM_SIGNIFICANT] = has_significant && significant[superpixels[index]] ? 1.0
                                                                                     : 0.0;
        if (finite(depth)) {
            const double uu = u, vv = v, z = fb / (double)disparity[index];
            bool edge_on;
            const double floor = surface_patch(disparity, u, v, height, width, f, cx, cy, fb,
                                               normal, &edge_on);
            const float volume_depth =
                edge_on ? hidden_floor_depth(labels, disparity, u, v, width, label, depth, f, cx,
                                             cy, fb, road, normal)
                        : depth;
            values[SUM_VALID_AREA] = footprint;
            values[SUM_FLOOR] = floor;
            values[SUM_DEPTH_FLOOR] = (double)volume_depth * floor;
            values[SUM_X] = (uu - cx) * z / f * footprint;
            values[SUM_Y] = (vv - cy) * z / f * footprint;
            values[SUM_Z] = z * footprint;
            if (under_opening(labels, u, v, height, width, label, disparity[index], depth, f,
                              cx, cy, fb, normal))
                depth_value = depth;
        }
    }
    const int lane = threadIdx.x & 31;
    const int leader_label = __shfl_sync(FULL_MASK, label, __ffs(labelled) - 1);
    if (__all_sync(FULL_MASK, label <= 0 || label == leader_label)) {
        int depth_bits = ordered_bits(depth_value);
        int u_min = label > 0 ? u : 0x7fffffff, v_min = label > 0 ? v : 0x7fffffff;
        int u_max = label > 0 ? u : -1, v_max = label > 0 ? v : -1;
#pragma unroll
        for (int offset = 16; offset > 0; offset >>= 1) {
#pragma unroll
            for (int k = 0; k < SUMS; ++k)
                values[k] += __shfl_down_sync(FULL_MASK, values[k], offset);
            depth_bits = max(depth_bits, __shfl_down_sync(FULL_MASK, depth_bits, offset));
            u_min = min(u_min, __shfl_down_sync(FULL_MASK, u_min, offset));
            v_min = min(v_min, __shfl_down_sync(FULL_MASK, v_min, offset));
            u_max = max(u_max, __shfl_down_sync(FULL_MASK, u_max, offset));
            v_max = max(v_max, __shfl_down_sync(FULL_MASK, v_max, offset));
        }
        if (lane == 0) {
            for (int k = 0; k < SUMS; ++k) atomicAdd(&sums[leader_label * SUMS + k], values[k]);
            int* row = extremes + leader_label * EXTREMES;
            atomicMax(&row[EXTREME_LARGEST_DEPTH], depth_bits);
            atomicMin(&row[EXTREME_U_MIN], u_min);
            atomicMin(&row[EXTREME_V_MIN], v_min);
            atomicMax(&row[EXTREME_U_MAX], u_max);
            atomicMax(&row[EXTREME_V_MAX], v_max);
        }
    } else if (label > 0) {
        for (int k = 0; k < SUMS; ++k) atomicAdd(&sums[label * SUMS + k], values[k]);
        int* row = extremes + label * EXTREMES;
        atomicMax(&row[EXTREME_LARGEST_DEPTH], ordered_bits(depth_value));
        atomicMin(&row[EXTREME_U_MIN], u);
        atomicMin(&row[EXTREME_V_MIN], v);
        atomicMax(&row[EXTREME_U_MAX], u);
        atomicMax(&row[EXTREME_V_MAX], v);
    }
}

// One thread: pothole p (1..min(kept[0], capacity)) stays when its footprint area reaches
// min_area, its mean depth (over its floor area) lies in [min_depth, max_depth] and is at most
// its width (the square root of its area), where it reaches into a far corner more than half
// of its pixels are on significant superpixels, and its sums make a report
// (measure.reportable); new_id numbers the ones that stay
// 1..m in order (0 for the others and for label 0); kept_after[0] = m. The pipeline's area
// filter; the host repeats the test on the same sums when it reads them back.
__device__ bool reportable(const double* row, double min_area, double min_depth,
                           double max_depth) {
    for (int k = 0; k < SUMS; ++k)
        if (!isfinite(row[k])) return false;
    const double floor = row[SUM_FLOOR], depth_floor = row[SUM_DEPTH_FLOOR];
    const double area = row[SUM_AREA];
    return area >= min_area && area > 0.0 && row[SUM_VALID_AREA] > 0.0 && floor > 0.0
           && depth_floor > 0.0 && depth_floor >= min_depth * floor
           && depth_floor <= max_depth * floor && depth_floor <= sqrt(area) * floor
           && (row[SUM_CORNER] == 0.0 || 2.0 * row[SUM_SIGNIFICANT] > row[SUM_PIXELS]);
}

extern "C" __global__ void measure_keep(const double* sums, const int* kept, int capacity,
                                        double min_area, double min_depth, double max_depth,
                                        int* new_id, int* kept_after) {
    if (threadIdx.x != 0 || blockIdx.x != 0) return;
    const int count = min(kept[0], capacity);
    int next = 0;
    new_id[0] = 0;
    for (int label = 1; label <= count; ++label)
        new_id[label] = reportable(sums + label * SUMS, min_area, min_depth, max_depth) ? ++next
                                                                                 : 0;
    kept_after[0] = next;
}
