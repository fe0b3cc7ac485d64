// Rectification: bilinear remap in fixed point, one thread per rectified pixel. Reference:
// stages/rectify._remap_cpu (the same integers). index: flat raw index of the 2x2
// neighbourhood's top left, -1 outside the raw image (the pixel is 0); fraction: x | y << 8 in
// 1 / 2^REMAP_FRACTION_BITS px. Defined by the launcher (stages/rectify.py): REMAP_FRACTION_BITS.

extern "C" __global__ void remap_bilinear(const unsigned char* __restrict__ source, int width,
                                          const int* __restrict__ index,
                                          const unsigned short* __restrict__ fraction,
                                          unsigned char* __restrict__ out, int count) {
    const int pixel = blockIdx.x * blockDim.x + threadIdx.x;
    if (pixel >= count) return;
    const int start = index[pixel];
    if (start < 0) {
        out[pixel] = 0;
        return;
    }
    const int one = 1 << REMAP_FRACTION_BITS;
    const int fx = fraction[pixel] & 0xFF;
    const int fy = fraction[pixel] >> 8;
    const int top = (one - fx) * source[start] + fx * source[start + 1];
    const int bottom = (one - fx) * source[start + width] + fx * source[start + width + 1];
    out[pixel] = (unsigned char)(((one - fy) * top + fy * bottom
                                  + (1 << (2 * REMAP_FRACTION_BITS - 1)))
                                 >> (2 * REMAP_FRACTION_BITS));
}
