// Disparity transformation D2 = D1 - f(u, v) + delta_DT, one thread per pixel. Reference:
// stages/transform.transform_disparity: f in float64 in the reference's operation order
// (no FMA), rounded to float32, then float32 arithmetic; NaN stays NaN.
// road: a0, a1, cos(phi), sin(phi), c0..c5, curved (stages/road_model.RoadModel.kernel_params).
extern "C" __global__ void transform_disparity(const float* disparity, float* transformed,
                                               int height, int width, const double* road,
                                               float delta) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const double a0 = road[0], a1 = road[1], cos_phi = road[2], sin_phi = road[3];
    const double u = col, v = row;
    double value = __dadd_rn(a0, __dmul_rn(a1, __dsub_rn(__dmul_rn(v, cos_phi),
                                                         __dmul_rn(u, sin_phi))));
    if (road[10] != 0.0) {
        const double c0 = road[4], c1 = road[5], c2 = road[6], c3 = road[7], c4 = road[8],
                     c5 = road[9];
        const double x = __ddiv_rn(u, 1000.0), y = __ddiv_rn(v, 1000.0);
        const double inner_x = __dadd_rn(__dadd_rn(c1, __dmul_rn(c3, x)), __dmul_rn(c4, y));
        const double inner_y = __dadd_rn(c2, __dmul_rn(c5, y));
        value = __dadd_rn(value, __dadd_rn(__dadd_rn(c0, __dmul_rn(x, inner_x)),
                                           __dmul_rn(y, inner_y)));
    }
    const long long index = (long long)row * width + col;
    transformed[index] = __fadd_rn(__fsub_rn(disparity[index], __double2float_rn(value)), delta);
}
