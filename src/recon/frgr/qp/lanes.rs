//! [`LANES`] `f32` lanes with elementwise operators, written so that LLVM's vectorisers turn
//! each into SIMD instructions (two AVX-512 registers, four AVX2 ones, or eight SSE ones on
//! baseline x86-64) with no `unsafe` and no nightly `std::simd`. Every operation is the scalar
//! IEEE operation applied per lane, so a lane computes bit for bit what scalar code would.

use std::ops::{Add, BitAnd, Div, Mul, Neg, Sub};

/// Lanes per vector (the arithmetic below is spelt out for 32). The solver's iteration is a
/// chain of dependent operations (a division among them) that the lanes of a group share, so
/// what sets its speed is how many independent chains are in flight: 32 lanes are two chains
/// of AVX-512 registers or four of AVX2 ones. Measured on an AMD Zen 4 (fifty-second session,
/// `docs/benchmarks.md`): 16 lanes (one AVX-512 register) took 20-25 % longer, 64 no less
/// than 32; with AVX2 code on the same CPU, 32 lanes were at least as fast as 16. The lanes
/// never mix, so the count changes no pixel's bits.
pub(crate) const LANES: usize = 32;

/// [`LANES`] `f32` lanes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(64))]
pub(crate) struct F32x(pub [f32; LANES]);

/// A per-lane condition: all bits set (true) or clear (false).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C, align(64))]
pub(crate) struct Mask(pub [i32; LANES]);

/// [`LANES`] `i32` lanes (counters).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C, align(64))]
pub(crate) struct I32x(pub [i32; LANES]);

macro_rules! lanewise {
    ($trait:ident, $f:ident, $op:tt) => {
        impl $trait for F32x {
            type Output = F32x;
            #[inline(always)]
            fn $f(self, o: F32x) -> F32x {
                // Spelt out: written as a loop, LLVM's SLP vectoriser tends to keep the
                // accumulators of the solver with their lanes reversed (a shuffle per add).
                let (a, b) = (self.0, o.0);
F32x([
                    a[0] $op b[0],
                    a[1] $op b[1],
                    a[2] $op b[2],
                    a[3] $op b[3],
                    a[4] $op b[4],
                    a[5] $op b[5],
                    a[6] $op b[6],
                    a[7] $op b[7],
                    a[8] $op b[8],
                    a[9] $op b[9],
                    a[10] $op b[10],
                    a[11] $op b[11],
                    a[12] $op b[12],
                    a[13] $op b[13],
                    a[14] $op b[14],
                    a[15] $op b[15],
                    a[16] $op b[16],
                    a[17] $op b[17],
                    a[18] $op b[18],
                    a[19] $op b[19],
                    a[20] $op b[20],
                    a[21] $op b[21],
                    a[22] $op b[22],
                    a[23] $op b[23],
                    a[24] $op b[24],
                    a[25] $op b[25],
                    a[26] $op b[26],
                    a[27] $op b[27],
                    a[28] $op b[28],
                    a[29] $op b[29],
                    a[30] $op b[30],
                    a[31] $op b[31],
                ])
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

impl Neg for F32x {
    type Output = F32x;
    #[inline(always)]
    fn neg(self) -> F32x {
        self.map(|x| -x)
    }
}

impl F32x {
    #[inline(always)]
    pub fn splat(x: f32) -> F32x {
        F32x([x; LANES])
    }

    /// The first [`LANES`] values of `s`.
    #[inline(always)]
    pub fn load(s: &[f32]) -> F32x {
        let mut r = F32x::default();
        r.0.copy_from_slice(&s[..LANES]);
        r
    }

    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> F32x {
        let mut r = self;
        for x in &mut r.0 {
            *x = f(*x);
        }
        r
    }

    /// `self * a + b` per lane, with one rounding when `FUSED` (an FMA instruction; pass
    /// `fastmath::fused!()`), else two (see `fastmath::madd`).
    #[inline(always)]
    pub fn madd<const FUSED: bool>(self, a: F32x, b: F32x) -> F32x {
        if !FUSED {
            return self * a + b;
        }
        let (x, a, b) = (self.0, a.0, b.0);
        F32x([
            x[0].mul_add(a[0], b[0]),
            x[1].mul_add(a[1], b[1]),
            x[2].mul_add(a[2], b[2]),
            x[3].mul_add(a[3], b[3]),
            x[4].mul_add(a[4], b[4]),
            x[5].mul_add(a[5], b[5]),
            x[6].mul_add(a[6], b[6]),
            x[7].mul_add(a[7], b[7]),
            x[8].mul_add(a[8], b[8]),
            x[9].mul_add(a[9], b[9]),
            x[10].mul_add(a[10], b[10]),
            x[11].mul_add(a[11], b[11]),
            x[12].mul_add(a[12], b[12]),
            x[13].mul_add(a[13], b[13]),
            x[14].mul_add(a[14], b[14]),
            x[15].mul_add(a[15], b[15]),
            x[16].mul_add(a[16], b[16]),
            x[17].mul_add(a[17], b[17]),
            x[18].mul_add(a[18], b[18]),
            x[19].mul_add(a[19], b[19]),
            x[20].mul_add(a[20], b[20]),
            x[21].mul_add(a[21], b[21]),
            x[22].mul_add(a[22], b[22]),
            x[23].mul_add(a[23], b[23]),
            x[24].mul_add(a[24], b[24]),
            x[25].mul_add(a[25], b[25]),
            x[26].mul_add(a[26], b[26]),
            x[27].mul_add(a[27], b[27]),
            x[28].mul_add(a[28], b[28]),
            x[29].mul_add(a[29], b[29]),
            x[30].mul_add(a[30], b[30]),
            x[31].mul_add(a[31], b[31]),
        ])
    }

    #[inline(always)]
    pub fn sqrt(self) -> F32x {
        self.map(f32::sqrt)
    }

    /// Clamped to `[0, 1]` (as `f32::clamp`).
    #[inline(always)]
    pub fn clamp01(self) -> F32x {
        self.map(|x| x.clamp(0.0, 1.0))
    }

    #[inline(always)]
    pub fn lt(self, o: F32x) -> Mask {
        let mut m = Mask::default();
        for i in 0..LANES {
            m.0[i] = -i32::from(self.0[i] < o.0[i]);
        }
        m
    }

    #[inline(always)]
    pub fn is_finite(self) -> Mask {
        let mut m = Mask::default();
        for i in 0..LANES {
            m.0[i] = -i32::from(self.0[i].is_finite());
        }
        m
    }

    /// `a` where `m`, else `b`.
    #[inline(always)]
    pub fn select(m: Mask, a: F32x, b: F32x) -> F32x {
        let mut r = b;
        for i in 0..LANES {
            let k = m.0[i] as u32;
            r.0[i] = f32::from_bits((a.0[i].to_bits() & k) | (b.0[i].to_bits() & !k));
        }
        r
    }
}

impl BitAnd for Mask {
    type Output = Mask;
    #[inline(always)]
    fn bitand(self, o: Mask) -> Mask {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] &= o.0[i];
        }
        r
    }
}

impl Mask {
    #[inline(always)]
    pub fn from_bools(b: [bool; LANES]) -> Mask {
        // A loop, not `array::map` (whose closure stays a call in the multiversioned band).
        let mut m = Mask::default();
        for (m, &x) in m.0.iter_mut().zip(&b) {
            *m = -i32::from(x);
        }
        m
    }

    /// `self` and not `o`.
    #[inline(always)]
    pub fn and_not(self, o: Mask) -> Mask {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] &= !o.0[i];
        }
        r
    }

    #[inline(always)]
    pub fn any(self) -> bool {
        self.0.iter().fold(0, |a, &x| a | x) != 0
    }
}

impl I32x {
    #[inline(always)]
    pub fn lt(self, n: i32) -> Mask {
        let mut m = Mask::default();
        for i in 0..LANES {
            m.0[i] = -i32::from(self.0[i] < n);
        }
        m
    }

    /// One more where `m`.
    #[inline(always)]
    pub fn inc(self, m: Mask) -> I32x {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] -= m.0[i];
        }
        r
    }

    /// One more where `up`, zero where `reset` (disjoint masks), unchanged elsewhere.
    #[inline(always)]
    pub fn inc_or_reset(self, up: Mask, reset: Mask) -> I32x {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] = (r.0[i] & !reset.0[i]) - up.0[i];
        }
        r
    }
}
