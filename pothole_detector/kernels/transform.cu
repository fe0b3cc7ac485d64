// Disparity transformation D2 = D1 - f(u, v) + delta_DT, one thread per pixel. Reference:
// stages/transform.transform_disparity: f in float64 in the reference's operation order
// (no FMA), rounded to float32, then float32 arithmetic; NaN stays NaN.
extern "C" __global__ void transform_disparity(const float* disparity, float* transformed,
                                               int height, int width, double a0, double a1,
                                               double cos_phi, double sin_phi, double c0,
                                               double c1, double c2, double c3, double c4,
                                               double c5, int curved, float delta) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const double u = col, v = row;
    double road = __dadd_rn(a0, __dmul_rn(a1, __dsub_rn(__dmul_rn(v, cos_phi),
                                                        __dmul_rn(u, sin_phi))));
    if (curved) {
        const double x = __ddiv_rn(u, 1000.0), y = __ddiv_rn(v, 1000.0);
        const double inner_x = __dadd_rn(__dadd_rn(c1, __dmul_rn(c3, x)), __dmul_rn(c4, y));
        const double inner_y = __dadd_rn(c2, __dmul_rn(c5, y));
        road = __dadd_rn(road, __dadd_rn(__dadd_rn(c0, __dmul_rn(x, inner_x)),
                                         __dmul_rn(y, inner_y)));
    }
    const long long index = (long long)row * width + col;
    transformed[index] = __fadd_rn(__fsub_rn(disparity[index], __double2float_rn(road)), delta);
}
