// The squared horizontal gradient of the left image (stages/texture.py, gradient_energy, whose
// array code is the reference), one thread per pixel: (I(u+1) - I(u-1))^2 / 4 where the pixel
// is valid and both neighbours exist, NaN elsewhere.

extern "C" __global__ void gradient_energy(const unsigned char* image, const bool* valid,
                                           long long size, int width, float* out) {
    const long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x;
    if (i >= size) return;
    const int col = (int)(i % width);
    if (!valid[i] || col == 0 || col == width - 1) {
        out[i] = __int_as_float(0x7fc00000);
        return;
    }
    const float step = (float)image[i + 1] - (float)image[i - 1];
    out[i] = 0.25f * (step * step);
}

// texture_keys: per superpixel, the RMS gradient sqrt(mean energy) (NaN where none), and the
//   sort key of the typical texture's median: the RMS gradient where observed and known, +inf
//   elsewhere.
// texture_deficit: per superpixel, the median of the sorted keys' finite ones (the mean of the
//   two middle ones for an even count) over its own RMS gradient, at least 1, the RMS gradient
//   floored at flat; 1 where it is unknown or no key is finite.
extern "C" __global__ void texture_keys(const float* energy, const bool* observed, int count,
                                        double* rms, double* keys) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= count) return;
    const double value = sqrt((double)energy[k]);
    rms[k] = value;
    keys[k] = observed[k] && isfinite(value) ? value : __longlong_as_double(0x7ff0000000000000LL);
}

extern "C" __global__ void texture_deficit(const double* rms, const double* sorted, int count,
                                           double flat, double* out) {
    const int k = blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= count) return;
    int used = 0, end = count;
    while (used < end) {
        const int middle = (used + end) / 2;
        if (isfinite(sorted[middle])) used = middle + 1;
        else end = middle;
    }
    const double typical = (sorted[max((used - 1) / 2, 0)] + sorted[min(used / 2, count - 1)])
                           / 2;
    const double value = rms[k];
    const bool known = isfinite(value) && used > 0;
    out[k] = known ? fmax(typical / fmax(value, flat), 1.0) : 1.0;
}
