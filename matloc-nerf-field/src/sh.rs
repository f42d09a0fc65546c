/// Number of spherical-harmonics coefficients at degree 4 (bands l = 0..=3).
pub const SH_DIM: usize = 16;

/// Real spherical harmonics of a unit direction up to degree 4 (16 coefficients), with the
/// sign and normalisation conventions of tiny-cuda-nn's `SphericalHarmonics` encoding, so
/// weights are interchangeable with nerfacto's.
#[inline]
pub fn sh_encode(d: [f32; 3]) -> [f32; SH_DIM] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        0.282_094_8,
        -0.488_602_5 * y,
        0.488_602_5 * z,
        -0.488_602_5 * x,
        1.092_548_4 * x * y,
        -1.092_548_4 * y * z,
        0.946_174_7 * zz - 0.315_391_57,
        -1.092_548_4 * x * z,
        0.546_274_2 * (xx - yy),
        0.590_043_6 * y * (-3.0 * xx + yy),
        2.890_611_4 * x * y * z,
        0.457_045_8 * y * (1.0 - 5.0 * zz),
        0.373_176_33 * z * (5.0 * zz - 3.0),
        0.457_045_8 * x * (1.0 - 5.0 * zz),
        1.445_305_7 * z * (xx - yy),
        0.590_043_6 * x * (-xx + 3.0 * yy),
    ]
}
