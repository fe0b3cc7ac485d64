// The road's disparity f(u, v) of a model in the kernel parameters' layout (ROAD_*, defined by
// the including kernel's launcher; stages/road_model.RoadModel.kernel_params), in float64 in
// stages/road_model.RoadModel.at's operation order without FMA.
#pragma once

__device__ __forceinline__ double road_disparity(const double* road, double u, double v) {
    const double a0 = road[ROAD_A0], a1 = road[ROAD_A1], cos_phi = road[ROAD_COS],
                 sin_phi = road[ROAD_SIN];
    double value = __dadd_rn(a0, __dmul_rn(a1, __dsub_rn(__dmul_rn(v, cos_phi),
                                                         __dmul_rn(u, sin_phi))));
    if (road[ROAD_CURVED] != 0.0) {
        const double c0 = road[ROAD_C0], c1 = road[ROAD_C0 + 1], c2 = road[ROAD_C0 + 2],
                     c3 = road[ROAD_C0 + 3], c4 = road[ROAD_C0 + 4], c5 = road[ROAD_C0 + 5];
        const double x = __ddiv_rn(u, 1000.0), y = __ddiv_rn(v, 1000.0);
        const double inner_x = __dadd_rn(__dadd_rn(c1, __dmul_rn(c3, x)), __dmul_rn(c4, y));
        const double inner_y = __dadd_rn(c2, __dmul_rn(c5, y));
        value = __dadd_rn(value, __dadd_rn(__dadd_rn(c0, __dmul_rn(x, inner_x)),
                                           __dmul_rn(y, inner_y)));
    }
    return value;
}
