//! Filtering-based reconstruction (FRGR, Yan et al. 2024), stage by stage.

pub(crate) mod enhance;
pub(crate) mod outliers;
pub(crate) mod qp;
pub(crate) mod util;
