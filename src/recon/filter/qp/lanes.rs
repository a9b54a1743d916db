//! Eight `f32` lanes with elementwise operators, written so that LLVM's vectorisers turn each
//! into SIMD instructions (two SSE registers on baseline x86-64) with no `unsafe` and no
//! nightly `std::simd`. Every operation is the scalar IEEE operation applied per lane, so a
//! lane computes bit for bit what scalar code would.

use std::ops::{Add, BitAnd, Div, Mul, Neg, Sub};

/// Lanes per vector (the arithmetic below is spelt out for 8).
pub(crate) const LANES: usize = 8;

/// Eight `f32` lanes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct F8(pub [f32; LANES]);

/// A per-lane condition: all bits set (true) or clear (false).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C, align(32))]
pub(crate) struct M8(pub [i32; LANES]);

/// Eight `i32` lanes (counters).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C, align(32))]
pub(crate) struct I8(pub [i32; LANES]);

macro_rules! lanewise {
    ($trait:ident, $f:ident, $op:tt) => {
        impl $trait for F8 {
            type Output = F8;
            #[inline(always)]
            fn $f(self, o: F8) -> F8 {
                // Spelt out: written as a loop, LLVM's SLP vectoriser tends to keep the
                // accumulators of the solver with their lanes reversed (a shuffle per add).
                let (a, b) = (self.0, o.0);
                F8([
                    a[0] $op b[0],
                    a[1] $op b[1],
                    a[2] $op b[2],
                    a[3] $op b[3],
                    a[4] $op b[4],
                    a[5] $op b[5],
                    a[6] $op b[6],
                    a[7] $op b[7],
                ])
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

impl Neg for F8 {
    type Output = F8;
    #[inline(always)]
    fn neg(self) -> F8 {
        self.map(|x| -x)
    }
}

impl F8 {
    #[inline(always)]
    pub fn splat(x: f32) -> F8 {
        F8([x; LANES])
    }

    /// The first eight values of `s`.
    #[inline(always)]
    pub fn load(s: &[f32]) -> F8 {
        let mut r = F8::default();
        r.0.copy_from_slice(&s[..LANES]);
        r
    }

    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> F8 {
        let mut r = self;
        for x in &mut r.0 {
            *x = f(*x);
        }
        r
    }

    #[inline(always)]
    pub fn sqrt(self) -> F8 {
        self.map(f32::sqrt)
    }

    /// Clamped to `[0, 1]` (as `f32::clamp`).
    #[inline(always)]
    pub fn clamp01(self) -> F8 {
        self.map(|x| x.clamp(0.0, 1.0))
    }

    #[inline(always)]
    pub fn lt(self, o: F8) -> M8 {
        let mut m = M8::default();
        for i in 0..LANES {
            m.0[i] = -i32::from(self.0[i] < o.0[i]);
        }
        m
    }

    #[inline(always)]
    pub fn is_finite(self) -> M8 {
        let mut m = M8::default();
        for i in 0..LANES {
            m.0[i] = -i32::from(self.0[i].is_finite());
        }
        m
    }

    /// `a` where `m`, else `b`.
    #[inline(always)]
    pub fn select(m: M8, a: F8, b: F8) -> F8 {
        let mut r = b;
        for i in 0..LANES {
            let k = m.0[i] as u32;
            r.0[i] = f32::from_bits((a.0[i].to_bits() & k) | (b.0[i].to_bits() & !k));
        }
        r
    }
}

impl BitAnd for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitand(self, o: M8) -> M8 {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] &= o.0[i];
        }
        r
    }
}

impl M8 {
    #[inline(always)]
    pub fn from_bools(b: [bool; LANES]) -> M8 {
        M8(b.map(|x| -i32::from(x)))
    }

    /// `self` and not `o`.
    #[inline(always)]
    pub fn and_not(self, o: M8) -> M8 {
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

impl I8 {
    #[inline(always)]
    pub fn lt(self, n: i32) -> M8 {
        let mut m = M8::default();
        for i in 0..LANES {
            m.0[i] = -i32::from(self.0[i] < n);
        }
        m
    }

    /// One more where `m`.
    #[inline(always)]
    pub fn inc(self, m: M8) -> I8 {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] -= m.0[i];
        }
        r
    }

    /// One more where `up`, zero where `reset` (disjoint masks), unchanged elsewhere.
    #[inline(always)]
    pub fn inc_or_reset(self, up: M8, reset: M8) -> I8 {
        let mut r = self;
        for i in 0..LANES {
            r.0[i] = (r.0[i] & !reset.0[i]) - up.0[i];
        }
        r
    }
}
