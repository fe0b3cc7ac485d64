// Disparity transformation D2 = D1 - f(u, v) + delta_DT, one thread per pixel. Reference:
// stages/transform.transform_disparity: f in float64 in the reference's operation order
// (no FMA), rounded to float32, then float32 arithmetic; NaN stays NaN.
// road: a0, a1, cos(phi), sin(phi), c0..c5, curved (stages/road_model.RoadModel.kernel_params).
// Defined by the launcher (stages/transform.py, _kernel): the road parameters' layout (ROAD_*).
extern "C" __global__ void transform_disparity(const float* disparity, float* transformed,
                                               int height, int width, const double* road,
                                               float delta) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const double a0 = road[ROAD_A0], a1 = road[ROAD_A1], cos_phi = road[ROAD_COS],
                 sin_phi = road[ROAD_SIN];
    const double u = col, v = row;
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
    const long long index = (long long)row * width + col;
    transformed[index] = __fadd_rn(__fsub_rn(disparity[index], __double2float_rn(value)), delta);
}
