// The SSIM window and constants shared by the loss kernels (see common.glsl).
#ifndef INSTGS_SSIM_GLSL
#define INSTGS_SSIM_GLSL
const float SSIM_C1 = 0.0001; // (0.01 * data range 1)^2
const float SSIM_C2 = 0.0009; // (0.03 * data range 1)^2
const float SSIM_SIGMA = 1.5;

// Normalised 1D Gaussian weights w[k], k = -SSIM_RADIUS..SSIM_RADIUS at w[k + SSIM_RADIUS].
void ssim_weights(out float w[2 * SSIM_RADIUS + 1]) {
    float sum = 0.0;
    for (int k = -SSIM_RADIUS; k <= SSIM_RADIUS; k++) {
        w[k + SSIM_RADIUS] = exp(-float(k * k) / (2.0 * SSIM_SIGMA * SSIM_SIGMA));
        sum += w[k + SSIM_RADIUS];
    }
    for (int k = 0; k < 2 * SSIM_RADIUS + 1; k++) w[k] /= sum;
}
#endif
