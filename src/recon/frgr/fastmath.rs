//! Elementary functions written with plain `f32` operations (and `mul_add`) and no branches, so
//! that the loops calling them vectorise (`f32::exp` is a call into libm, one lane at a time).

/// `e^x` for `x <= 0`, as Cephes' `expf`: `x = n ln 2 + r` with `n` the nearest integer to
/// `x / ln 2` (so `|r| <= ln 2 / 2`), `e^r` by a degree-6 polynomial, `2^n` built from its
/// exponent bits. Relative error below 2e-7 on `[-87, 0]` (tested); 0 below -87 (where `e^x`
/// is below 1.7e-38) and for `-inf`. Positive `x` is outside its domain (wrong results above
/// about 88, where `2^n` would overflow); NaN gives NaN. The polynomial and the reduction are
/// [`madd`]s, fused when `FUSED` (pass [`fused!`]).
#[inline(always)]
pub(crate) fn exp_nonpositive<const FUSED: bool>(x: f32) -> f32 {
    // Adding 1.5 * 2^23 rounds to an integer (current rounding mode: to nearest), which then
    // sits in the low mantissa bits of `t`.
    const ROUND: f32 = 12_582_912.0;
    // ln 2 split in two so that `n * LN2_HI` is exact for |n| < 2^15.
    const LN2_HI: f32 = 355.0 / 512.0;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let t = madd::<FUSED>(x, std::f32::consts::LOG2_E, ROUND);
    let n = t - ROUND;
    let r = madd::<FUSED>(n, -LN2_LO, madd::<FUSED>(n, -LN2_HI, x));
    let p = madd::<FUSED>(1.987_569_2e-4, r, 1.398_199_9e-3);
    let p = madd::<FUSED>(p, r, 8.333_452e-3);
    let p = madd::<FUSED>(p, r, 4.166_579_6e-2);
    let p = madd::<FUSED>(p, r, 1.666_666_5e-1);
    let p = madd::<FUSED>(p, r, 0.5);
    let er = madd::<FUSED>(p, r * r, r) + 1.0;
    // `t`'s representation is 0x4B40_0000 + n: shifted by 23 only `n`'s low 9 bits remain, in
    // the exponent field; biased by 127 they make 2^n (-126 <= n <= 0 here).
    let two_n = f32::from_bits((t.to_bits() << 23).wrapping_add(127 << 23));
    let y = er * two_n;
    if x < -87.0 {
        0.0
    } else {
        y
    }
}

/// `a * b + c`: with one rounding when `FUSED` (`f32::mul_add`, one FMA instruction where the
/// CPU has it), else two (a multiply, then an add). Kernels pass [`fused!`]: fused in their
/// builds for CPUs with FMA, unfused in the baseline build, where `mul_add` would be a call into
/// libm for every lane (correct, but tens of times slower).
#[inline(always)]
pub(crate) fn madd<const FUSED: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FUSED {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// Whether the multiversioned function it is written in is being compiled with FMA (every
/// AArch64 CPU has it): the `FUSED` argument of [`madd`] and its users.
macro_rules! fused {
    () => {
        multiversion::target::target_cfg_f!(target_feature = "fma") || cfg!(target_arch = "aarch64")
    };
}
pub(crate) use fused;

/// `max(a, b)` as one SIMD instruction (`maxps`): `b` when either is NaN. `f32::max` needs
/// extra instructions to return the number when one operand is NaN.
#[inline(always)]
pub(crate) fn max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// `min(a, b)` as one SIMD instruction (`minps`): `b` when either is NaN.
#[inline(always)]
pub(crate) fn min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_matches_f64_exp_on_its_domain() {
        let mut worst = 0.0f64;
        let steps = 2_000_000;
        for i in 0..=steps {
            let x = -87.0 * i as f32 / steps as f32;
            let want = f64::from(x).exp();
            let rel = ((f64::from(exp_nonpositive::<true>(x)) - want) / want).abs();
            worst = worst.max(rel);
        }
        assert!(worst < 2e-7, "{worst}");
        let mut unfused = 0.0f64;
        for i in 0..=steps {
            let x = -87.0 * i as f32 / steps as f32;
            let want = f64::from(x).exp();
            unfused = unfused.max(((f64::from(exp_nonpositive::<false>(x)) - want) / want).abs());
        }
        assert!(unfused < 2e-7, "{unfused}");
        assert_eq!(exp_nonpositive::<true>(0.0), 1.0);
        assert_eq!(exp_nonpositive::<true>(-0.0), 1.0);
        assert_eq!(exp_nonpositive::<true>(-87.5), 0.0);
        assert_eq!(exp_nonpositive::<true>(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_nonpositive::<true>(f32::MIN), 0.0);
    }
}
