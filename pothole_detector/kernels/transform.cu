// Disparity transformation D2 = D1 - f(u, v) + delta_DT, one thread per pixel. Reference:
// stages/transform.transform_disparity: f in float64 in the reference's operation order
// (no FMA, road_disparity.cuh), rounded to float32, then float32 arithmetic; NaN stays NaN.
// road: a0, a1, cos(phi), sin(phi), c0..c5, curved (stages/road_model.RoadModel.kernel_params).
// Defined by the launcher (stages/transform.py, _kernel): the road parameters' layout (ROAD_*).
#include "road_disparity.cuh"

extern "C" __global__ void transform_disparity(const float* disparity, float* transformed,
                                               int height, int width, const double* road,
                                               float delta) {
    const int col = blockIdx.x * blockDim.x + threadIdx.x;
    const int row = blockIdx.y * blockDim.y + threadIdx.y;
    if (col >= width || row >= height) return;
    const double value = road_disparity(road, col, row);
    const long long index = (long long)row * width + col;
    transformed[index] = __fadd_rn(__fsub_rn(disparity[index], __double2float_rn(value)), delta);
}
