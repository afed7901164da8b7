//! The parts of ozz's SIMD maths the sampling and local-to-model jobs use, as its SSE build
//! compiles them (`include/ozz/base/maths/internal/simd_math_sse-inl.h`, `soa_float.h`,
//! `soa_quaternion.h`, `soa_transform.h`, `soa_float4x4.h`): the 12-bit estimates `RcpEst`
//! (`rcpps`) and `RSqrtEst` (`rsqrtps`), `RSqrtEstNR`, `HalfToFloat`/`FloatToHalf`, and the
//! SoA types of four lanes (`SimdFloat4` is [`Vec4`], an `__m128`).

use glam::{Mat4, Vec4};

/// The SSE/SSE2 intrinsics the port calls, as safe functions.
#[allow(unsafe_code)]
pub mod sse {
    pub use std::arch::x86_64::{__m128, __m128i};

    use std::arch::x86_64 as arch;

    macro_rules! safe {
        ($($name:ident($($arg:ident: $ty:ty),*) -> $ret:ty;)*) => {$(
            #[inline(always)]
            pub fn $name($($arg: $ty),*) -> $ret {
                // SAFETY: SSE and SSE2 are part of the x86-64 baseline, so every CPU this is
                // compiled for has the intrinsic; it takes no pointer.
                unsafe { arch::$name($($arg),*) }
            }
        )*};
    }

    safe! {
        _mm_add_ps(a: __m128, b: __m128) -> __m128;
        _mm_sub_ps(a: __m128, b: __m128) -> __m128;
        _mm_mul_ps(a: __m128, b: __m128) -> __m128;
        _mm_and_ps(a: __m128, b: __m128) -> __m128;
        _mm_andnot_ps(a: __m128, b: __m128) -> __m128;
        _mm_or_ps(a: __m128, b: __m128) -> __m128;
        _mm_rcp_ps(a: __m128) -> __m128;
        _mm_rsqrt_ps(a: __m128) -> __m128;
        _mm_set_ps1(a: f32) -> __m128;
        _mm_unpacklo_ps(a: __m128, b: __m128) -> __m128;
        _mm_unpackhi_ps(a: __m128, b: __m128) -> __m128;
        _mm_cvtepi32_ps(a: __m128i) -> __m128;
        _mm_castps_si128(a: __m128) -> __m128i;
        _mm_castsi128_ps(a: __m128i) -> __m128;
        _mm_set1_epi32(a: i32) -> __m128i;
        _mm_setr_epi32(a: i32, b: i32, c: i32, d: i32) -> __m128i;
        _mm_and_si128(a: __m128i, b: __m128i) -> __m128i;
        _mm_or_si128(a: __m128i, b: __m128i) -> __m128i;
        _mm_xor_si128(a: __m128i, b: __m128i) -> __m128i;
        _mm_cmpgt_epi32(a: __m128i, b: __m128i) -> __m128i;
    }

    /// `_mm_slli_epi32::<IMM8>`.
    #[inline(always)]
    pub fn _mm_slli_epi32<const IMM8: i32>(a: __m128i) -> __m128i {
        // SAFETY: as above (SSE2 is in the x86-64 baseline; no pointer).
        unsafe { arch::_mm_slli_epi32::<IMM8>(a) }
    }
}

use sse::{
    __m128, __m128i, _mm_add_ps, _mm_and_ps, _mm_and_si128, _mm_castsi128_ps, _mm_cmpgt_epi32,
    _mm_mul_ps, _mm_or_ps, _mm_rcp_ps, _mm_rsqrt_ps, _mm_set_ps1, _mm_set1_epi32, _mm_slli_epi32,
    _mm_sub_ps, _mm_unpackhi_ps, _mm_unpacklo_ps, _mm_xor_si128,
};

/// `RcpEst`: `1 / v` to 12 bits (relative error ≤ 1.5 · 2⁻¹²).
#[inline(always)]
pub fn rcp_est(v: Vec4) -> Vec4 {
    Vec4::from(_mm_rcp_ps(v.into()))
}

/// `RSqrtEst`: `1 / √v` to 12 bits (relative error ≤ 1.5 · 2⁻¹²).
#[inline(always)]
pub fn rsqrt_est(v: Vec4) -> Vec4 {
    Vec4::from(_mm_rsqrt_ps(v.into()))
}

/// `RSqrtEstNR`: `RSqrtEst` and one Newton-Raphson step, `0.5 · r · (3 − v · r · r)`.
#[inline(always)]
pub fn rsqrt_est_nr(v: Vec4) -> Vec4 {
    let v: __m128 = v.into();
    let nr = _mm_rsqrt_ps(v);
    let muls = _mm_mul_ps(_mm_mul_ps(v, nr), nr);
    Vec4::from(_mm_mul_ps(
        _mm_mul_ps(_mm_set_ps1(0.5), nr),
        _mm_sub_ps(_mm_set_ps1(3.0), muls),
    ))
}

/// `HalfToFloat(SimdInt4)`: four IEEE half floats (low 16 bits of each lane) to floats
/// (F. Giesen's "half to float done quic").
#[inline(always)]
pub fn half_to_float(h: __m128i) -> Vec4 {
    let mask_nosign = _mm_set1_epi32(0x7fff);
    let magic = _mm_castsi128_ps(_mm_set1_epi32((254 - 15) << 23));
    let was_infnan = _mm_set1_epi32(0x7bff);
    let exp_infnan = _mm_castsi128_ps(_mm_set1_epi32(255 << 23));

    let expmant = _mm_and_si128(mask_nosign, h);
    let shifted = _mm_slli_epi32::<13>(expmant);
    let scaled = _mm_mul_ps(_mm_castsi128_ps(shifted), magic);
    let b_wasinfnan = _mm_cmpgt_epi32(expmant, was_infnan);
    let sign = _mm_slli_epi32::<16>(_mm_xor_si128(h, expmant));
    let infnanexp = _mm_and_ps(_mm_castsi128_ps(b_wasinfnan), exp_infnan);
    let sign_inf = _mm_or_ps(_mm_castsi128_ps(sign), infnanexp);
    Vec4::from(_mm_or_ps(scaled, sign_inf))
}

/// `FloatToHalf(float)` (the scalar form of the reference implementation, used offline):
/// rounds half up on the magnitude, clamps overflow to infinity, keeps NaN.
#[must_use]
pub fn float_to_half(f: f32) -> u16 {
    let f32infty: u32 = 255 << 23;
    let f16infty: u32 = 31 << 23;
    let magic = f32::from_bits(15 << 23);
    let sign_mask: u32 = 0x8000_0000;
    let round_mask: u32 = !0x0000_0fff;

    let bits = f.to_bits();
    let sign = bits & sign_mask;
    let f_nosign = bits & !sign_mask;
    if f_nosign >= f32infty {
        let result = (if f_nosign > f32infty { 0x7e00 } else { 0x7c00 }) | (sign >> 16);
        result as u16
    } else {
        let rounded = f32::from_bits(f_nosign & round_mask);
        let exp = (rounded * magic).to_bits();
        let re_rounded = exp.wrapping_sub(round_mask);
        let result = (re_rounded.min(f16infty) >> 13) | (sign >> 16);
        result as u16
    }
}

/// `SoaFloat3`: four 3-vectors, one per lane.
#[derive(Clone, Copy, Debug)]
pub struct SoaFloat3 {
    pub x: Vec4,
    pub y: Vec4,
    pub z: Vec4,
}

/// `SoaQuaternion`: four quaternions, one per lane.
#[derive(Clone, Copy, Debug)]
pub struct SoaQuaternion {
    pub x: Vec4,
    pub y: Vec4,
    pub z: Vec4,
    pub w: Vec4,
}

/// `SoaTransform`: four local transforms `T · R · S`, one per lane.
#[derive(Clone, Copy, Debug)]
pub struct SoaTransform {
    pub translation: SoaFloat3,
    pub rotation: SoaQuaternion,
    pub scale: SoaFloat3,
}

impl SoaTransform {
    /// `SoaTransform::identity()`.
    pub const IDENTITY: Self = Self {
        translation: SoaFloat3 {
            x: Vec4::ZERO,
            y: Vec4::ZERO,
            z: Vec4::ZERO,
        },
        rotation: SoaQuaternion {
            x: Vec4::ZERO,
            y: Vec4::ZERO,
            z: Vec4::ZERO,
            w: Vec4::ONE,
        },
        scale: SoaFloat3 {
            x: Vec4::ONE,
            y: Vec4::ONE,
            z: Vec4::ONE,
        },
    };
}

/// `Lerp(SoaFloat3, SoaFloat3, SimdFloat4)`: `(b − a) · f + a` per lane.
#[inline(always)]
pub fn lerp3(a: &SoaFloat3, b: &SoaFloat3, f: Vec4) -> SoaFloat3 {
    SoaFloat3 {
        x: (b.x - a.x) * f + a.x,
        y: (b.y - a.y) * f + a.y,
        z: (b.z - a.z) * f + a.z,
    }
}

/// `NLerpEst`: the lerp of `a` and `b` normalised with `RSqrtEstNR` (no shortest-path test:
/// the builder put successive keys of a track in the same hemisphere).
#[inline(always)]
pub fn nlerp_est(a: &SoaQuaternion, b: &SoaQuaternion, f: Vec4) -> SoaQuaternion {
    let x = (b.x - a.x) * f + a.x;
    let y = (b.y - a.y) * f + a.y;
    let z = (b.z - a.z) * f + a.z;
    let w = (b.w - a.w) * f + a.w;
    let len2 = x * x + y * y + z * z + w * w;
    let inv_len = rsqrt_est_nr(len2);
    SoaQuaternion {
        x: x * inv_len,
        y: y * inv_len,
        z: z * inv_len,
        w: w * inv_len,
    }
}

/// `SoaFloat4x4`: four 4×4 matrices, column-major, one per lane.
#[derive(Clone, Copy, Debug)]
pub struct SoaFloat4x4 {
    /// `cols[c][r]`: column `c`, row `r`, one lane per matrix.
    pub cols: [[Vec4; 4]; 4],
}

impl SoaFloat4x4 {
    /// `SoaFloat4x4::FromAffine`: `T(t) · R(q) · S(s)` per lane, `q` assumed unit.
    #[inline(always)]
    pub fn from_affine(t: &SoaFloat3, q: &SoaQuaternion, s: &SoaFloat3) -> Self {
        let zero = Vec4::ZERO;
        let one = Vec4::ONE;
        let two = one + one;
        let xx = q.x * q.x;
        let xy = q.x * q.y;
        let xz = q.x * q.z;
        let xw = q.x * q.w;
        let yy = q.y * q.y;
        let yz = q.y * q.z;
        let yw = q.y * q.w;
        let zz = q.z * q.z;
        let zw = q.z * q.w;
        Self {
            cols: [
                [
                    s.x * (one - two * (yy + zz)),
                    s.x * two * (xy + zw),
                    s.x * two * (xz - yw),
                    zero,
                ],
                [
                    s.y * two * (xy - zw),
                    s.y * (one - two * (xx + zz)),
                    s.y * two * (yz + xw),
                    zero,
                ],
                [
                    s.z * two * (xz + yw),
                    s.z * two * (yz - xw),
                    s.z * (one - two * (xx + yy)),
                    zero,
                ],
                [t.x, t.y, t.z, one],
            ],
        }
    }
}

/// `Transpose16x16`: the four lanes of an SoA matrix to four AoS matrices (`_mm_unpack*_ps`,
/// as the SSE build).
#[inline(always)]
pub fn transpose16x16(m: &SoaFloat4x4) -> [Mat4; 4] {
    let i = |c: usize, r: usize| -> __m128 { m.cols[c][r].into() };
    let mut out = [[Vec4::ZERO; 4]; 4];
    for c in 0..4 {
        let tmp0 = _mm_unpacklo_ps(i(c, 0), i(c, 2));
        let tmp1 = _mm_unpacklo_ps(i(c, 1), i(c, 3));
        let tmp2 = _mm_unpackhi_ps(i(c, 0), i(c, 2));
        let tmp3 = _mm_unpackhi_ps(i(c, 1), i(c, 3));
        out[0][c] = Vec4::from(_mm_unpacklo_ps(tmp0, tmp1));
        out[1][c] = Vec4::from(_mm_unpackhi_ps(tmp0, tmp1));
        out[2][c] = Vec4::from(_mm_unpacklo_ps(tmp2, tmp3));
        out[3][c] = Vec4::from(_mm_unpackhi_ps(tmp2, tmp3));
    }
    out.map(|[a, b, c, d]| Mat4::from_cols(a, b, c, d))
}

/// `operator*(Float4x4, Float4x4)` of the SSE build: each column of `b` as
/// `((a₀ · bₓ + a₁ · b_y) + a₂ · b_z) + a₃ · b_w`.
#[inline(always)]
pub fn mul_mat4(a: &Mat4, b: &Mat4) -> Mat4 {
    let col = |v: Vec4| -> Vec4 {
        let a01 = Vec4::from(_mm_add_ps(
            _mm_mul_ps(a.x_axis.into(), Vec4::splat(v.x).into()),
            _mm_mul_ps(a.y_axis.into(), Vec4::splat(v.y).into()),
        ));
        let a012 = a01 + a.z_axis * Vec4::splat(v.z);
        a012 + a.w_axis * Vec4::splat(v.w)
    };
    Mat4::from_cols(col(b.x_axis), col(b.y_axis), col(b.z_axis), col(b.w_axis))
}
