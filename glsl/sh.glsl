// Real spherical harmonics up to degree 3, constants and sign convention as the Inria 3DGS code
// (forward.cu computeColorFromSH). Coefficients of Gaussian i are sh[(i * coeffs + k) * 3 + c].
// Kernels access the coefficients as vec4s (lavapipe pays per access, not per byte): a row of
// 3 * coeffs floats starts at float off, so its vec4s start at off / 4 and its first float is
// component off % 4 (nonzero for degrees 0 and 2). Reads may take up to 3 floats beyond either
// end of a row (the host allocates SH buffers in whole vec4s); writes store the partial vec4s
// at a row's ends component by component.
#ifndef INSTGS_SH_GLSL
#define INSTGS_SH_GLSL
// Floats of a degree-3 row plus up to 3 before and after it: 13 vec4s.
#define SH_RAW_FLOATS 52
const float SH_C0 = 0.28209479177387814;
const float SH_C1 = 0.4886025119029199;
const float SH_C2[5] = float[5](1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                -1.0925484305920792, 0.5462742152960396);
const float SH_C3[7] = float[7](-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                                0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                                -0.5900435899266435);

// The basis values for direction `dir` (unit length), degree `deg`; unused entries are zero.
void sh_basis(vec3 dir, uint deg, out float b[16]) {
    for (int k = 0; k < 16; k++) b[k] = 0.0;
    b[0] = SH_C0;
    if (deg < 1) return;
    float x = dir.x, y = dir.y, z = dir.z;
    b[1] = -SH_C1 * y;
    b[2] = SH_C1 * z;
    b[3] = -SH_C1 * x;
    if (deg < 2) return;
    float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    b[4] = SH_C2[0] * xy;
    b[5] = SH_C2[1] * yz;
    b[6] = SH_C2[2] * (2.0 * zz - xx - yy);
    b[7] = SH_C2[3] * xz;
    b[8] = SH_C2[4] * (xx - yy);
    if (deg < 3) return;
    b[9] = SH_C3[0] * y * (3.0 * xx - yy);
    b[10] = SH_C3[1] * xy * z;
    b[11] = SH_C3[2] * y * (4.0 * zz - xx - yy);
    b[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    b[13] = SH_C3[4] * x * (4.0 * zz - xx - yy);
    b[14] = SH_C3[5] * z * (xx - yy);
    b[15] = SH_C3[6] * x * (xx - 3.0 * yy);
}

// d b[k] / d dir for the same basis (dir treated as a free 3-vector; the caller projects out the
// radial part of the normalisation).
void sh_basis_grad(vec3 dir, uint deg, out vec3 db[16]) {
    for (int k = 0; k < 16; k++) db[k] = vec3(0.0);
    if (deg < 1) return;
    float x = dir.x, y = dir.y, z = dir.z;
    db[1] = vec3(0.0, -SH_C1, 0.0);
    db[2] = vec3(0.0, 0.0, SH_C1);
    db[3] = vec3(-SH_C1, 0.0, 0.0);
    if (deg < 2) return;
    float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    db[4] = SH_C2[0] * vec3(y, x, 0.0);
    db[5] = SH_C2[1] * vec3(0.0, z, y);
    db[6] = SH_C2[2] * vec3(-2.0 * x, -2.0 * y, 4.0 * z);
    db[7] = SH_C2[3] * vec3(z, 0.0, x);
    db[8] = SH_C2[4] * vec3(2.0 * x, -2.0 * y, 0.0);
    if (deg < 3) return;
    db[9] = SH_C3[0] * vec3(6.0 * xy, 3.0 * xx - 3.0 * yy, 0.0);
    db[10] = SH_C3[1] * vec3(yz, xz, xy);
    db[11] = SH_C3[2] * vec3(-2.0 * xy, 4.0 * zz - xx - 3.0 * yy, 8.0 * yz);
    db[12] = SH_C3[3] * vec3(-6.0 * xz, -6.0 * yz, 6.0 * zz - 3.0 * xx - 3.0 * yy);
    db[13] = SH_C3[4] * vec3(4.0 * zz - 3.0 * xx - yy, -2.0 * xy, 8.0 * xz);
    db[14] = SH_C3[5] * vec3(2.0 * xz, -2.0 * yz, xx - yy);
    db[15] = SH_C3[6] * vec3(3.0 * xx - 3.0 * yy, -6.0 * xy, 0.0);
}
#endif
