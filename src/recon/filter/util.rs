//! Small helpers shared by the filter's stages: borders, luminance, planes.

pub(crate) use crate::recon::ops::reflect;

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
