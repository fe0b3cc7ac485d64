// The road's disparity f(u, v) of a model in the kernel parameters' layout (ROAD_*, with
// CURVATURE_SCALE_PX, INVERSE_SCALE_PX and MIN_ROAD_DISPARITY_PX:
// stages/road_model.ROAD_DEFINES), in float64 in stages/road_model's operation order without
// FMA.
#pragma once

// The quadratic correction's inverse disparity w = INVERSE_SCALE_PX / max(planar,
// MIN_ROAD_DISPARITY_PX) (road_model._inverse).
__device__ __forceinline__ double road_inverse(double planar) {
    return __ddiv_rn((double)INVERSE_SCALE_PX, fmax(planar, (double)MIN_ROAD_DISPARITY_PX));
}

// The quadratic correction q = c0 + c1 x + c2 y + w (c5 + x (c4 + x c3)), x = u / 1000,
// y = v / 1000 (road_model._poly).
__device__ __forceinline__ double curvature_at(const double* c, double x, double y,
                                              double planar) {
    const double inverse = road_inverse(planar);
    const double inner = __dadd_rn(c[5], __dmul_rn(x, __dadd_rn(c[4], __dmul_rn(x, c[3]))));
    return __dadd_rn(__dadd_rn(__dadd_rn(c[0], __dmul_rn(x, c[1])), __dmul_rn(y, c[2])),
                     __dmul_rn(inverse, inner));
}

__device__ __forceinline__ double road_planar(const double* road, double u, double v) {
    return __dadd_rn(road[ROAD_A0], __dmul_rn(road[ROAD_A1],
                                              __dsub_rn(__dmul_rn(v, road[ROAD_COS]),
                                                        __dmul_rn(u, road[ROAD_SIN]))));
}

__device__ __forceinline__ double road_disparity(const double* road, double u, double v) {
    const double planar = road_planar(road, u, v);
    if (road[ROAD_CURVED] == 0.0) return planar;
    const double x = __ddiv_rn(u, (double)CURVATURE_SCALE_PX);
    const double y = __ddiv_rn(v, (double)CURVATURE_SCALE_PX);
    return __dadd_rn(planar, curvature_at(road + ROAD_C0, x, y, planar));
}

// The unit normal of the plane n . P = f B of the model's linear part, n = (beta f, gamma f,
// a0 + beta cx + gamma cy) (road_model.road_plane), into normal; returns |n|.
__device__ __forceinline__ double road_unit_normal(const double* road, double f, double cx,
                                                  double cy, double* normal) {
    const double beta = -road[ROAD_A1] * road[ROAD_SIN], gamma = road[ROAD_A1] * road[ROAD_COS];
    const double x = beta * f, y = gamma * f, z = road[ROAD_A0] + beta * cx + gamma * cy;
    const double norm = sqrt(x * x + y * y + z * z);
    normal[0] = x / norm;
    normal[1] = y / norm;
    normal[2] = z / norm;
    return norm;
}

// Whether the model's curvature at disparity d stays within MAX_CURVATURE_PERCENT of its
// plane's disparity planar (road_model.MAX_CURVATURE_SHARE), where the model is the road.
__device__ __forceinline__ bool road_modelled(double d, double planar) {
    return fabs(__dsub_rn(d, planar)) <= (MAX_CURVATURE_PERCENT / 100.0) * planar;
}
