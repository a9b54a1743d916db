//! Small helpers shared by the filter's stages: borders, luminance, planes.

/// Reflect-101 border rule (`dcb|abcd|cba`), the release's choice almost everywhere: index
/// `i` (possibly outside `0..n`) mapped into `0..n`.
#[inline]
pub(crate) fn reflect(i: isize, n: usize) -> usize {
    if n == 1 {
        return 0;
    }
    let n = n as isize;
    let period = 2 * (n - 1);
    let mut i = i.rem_euclid(period);
    if i >= n {
        i = period - i;
    }
    i as usize
}

/// Rec. 709 luminance weights.
pub(crate) const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_101() {
        let got: Vec<usize> = (-4..8).map(|i| reflect(i, 4)).collect();
        assert_eq!(got, [2, 3, 2, 1, 0, 1, 2, 3, 2, 1, 0, 1]);
        assert_eq!(reflect(-3, 1), 0);
        assert_eq!(reflect(5, 2), 1);
    }
}
