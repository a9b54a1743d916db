//! The base image's noise band: a reconstruction should not leave the base image by more than
//! a few standard deviations of the base's own noise. Where it does, it is wrong there (a
//! filter that blurred a wire away, a network that darkened a dim room, a solve that spread an
//! emitter), and the band's edge is a better answer than either.
//!
//! Per pixel and channel, with `s` the standard deviation of the base's noise (the square root
//! of the variance layer averaged over the 3 x 3 neighbourhood, reflect-101 borders: a
//! variance of the mean estimated from a few passes is itself noisy, and its 3 x 3 mean
//! undershoots less), the output is clamped to `[I_b - k s, I_b + k s]`. Frames without a
//! variance layer are left as they are.
//!
//! **Trimming** (`band_trim`, `R`): at [`TRIM_MIN_SPP`] samples per pixel or more, a neighbour
//! whose base value exceeds `R (I_b + 0.1)` is left out of that mean (the pixel itself always
//! counts): beside an emitter's edge the 3 x 3 mean takes the edge's variance (hundreds of
//! times a dark pixel's), and the band then lets through what a solve or a filter spread out
//! of the emitter (`l1` on the test split's `lamps` at 64 spp, 1.36x its base). The 0.1 is the
//! square root of relMSE's 0.01, the radiance below which errors count as absolute. Below
//! 64 spp the variance layer is too often an undershoot (a pixel whose few samples all missed
//! a lamp's light has variance 0), so the wide band an emitter causes is the safer one there;
//! frames whose spp is unknown are not trimmed. `R` = 8 was chosen on validation; the 64 spp
//! gate after test showed caustics losing at 16 spp, so fresh renders of every family are its
//! check (`docs/benchmarks.md`, thirty-first session).
//!
//! **Edge trimming** (`band_emitters`): below 64 spp, or with the spp unknown, a neighbour
//! beyond the same ratio still leaves the mean when the gradients confirm it as a bright
//! object's edge pixel (`recon/emitters.rs`: the gradients across its jumps see them, where a
//! firefly's do not). That tells the lamp that FRGR spreads into the dark around it from the
//! caustic whose dark neighbours' wide band is right, which the spp gate could not: on `frgr`
//! (its default; `l1` and `gradnet` keep it off, as validation chose) the test split's
//! `lamps` at 4 spp goes from 1.13x its base to 0.24x, new renders of the test families'
//! `lamps` at 4 spp from 1.85x to 0.97x, and no validation, test or new frame is worse by
//! more than 0.2 % (`docs/benchmarks.md`, thirty-second session).
//!
//! **Scope** (`band_scope`): `all` clamps every pixel; `edges` only the pixels whose mean
//! lost a neighbour to trimming (the dark ring around an emitter), and only at
//! [`EDGES_MIN_SPP`] spp or more. It is the prior paths' choice (`l1`'s `prior` preset and
//! `combiner`): OIDN spreads a bulb into its ring (the guard's `lamps_16spp`, L1 on the prior
//! 8.4x its base), and there the band is right; elsewhere the prior is so much better than the
//! base that the band's cuts where the variance undershoots outweigh what it catches (the band
//! everywhere: on validation at 4 spp 0.7 % worse on average, 23 % on `indirect`). Below 16 spp a
//! dark pixel beside a lamp too often has no sample on it (validation `dusk` 4 spp +3.7 %).
//! On validation, against no band: L1 on the prior 1.4 % better at 16 spp and 3.0 % at 64,
//! the combiner 0 % and 1.1 %, no frame worse by more than 0.3 %; on test, evaluated once,
//! 14 % / 6.5 % and 8.6 % / 3.5 %, no frame worse by more than 1.3 % (`docs/benchmarks.md`,
//! thirty-third session). The band keeps one width for every method: narrower bands (k = 1
//! to 4) did a little better at 16 and 64 spp on validation, driven by two families, and
//! trend towards the base image beside every lamp.
//!
//! The width `k` is each method's `noise_band` parameter. Its default, 5, was chosen on the
//! validation split (`docs/benchmarks.md`, "The noise band"): there it removes the gross
//! departures (FRGR's geometric-mean relMSE falls 6-23 % and no FRGR frame is worse than its
//! base any more; GradNet's falls 2-9 % and its worst frame goes from 9.5x to 5.0x its base)
//! and leaves L1 as it was (within 0.3 %); narrower bands cut into good reconstructions where
//! the variance estimate undershoots (dark pixels whose few samples were all 0). On the test
//! split, evaluated once: FRGR -5 to +0.2 %, GradNet -2 to -7 %, L1 -0.1 to -0.2 %; the frames
//! that lose to their base there (bulbs in view, sub-pixel wires) lose less but still lose.
//! Its cost is one pass over the frame: 7 ms at 1280 x 720, 15 ms with edge trimming (2
//! threads, Intel Xeon with AMX, sixty-second session; the 3 x 3 sums go by whole-row passes,
//! one per neighbour, which vectorise; pixel by pixel it took 28 and 36 ms). The band trusts
//! the variance layer: a layer of zeros makes the output the base image.

use rayon::prelude::*;

use super::emitters::edge_pixels;
use super::param::{choices, Param, Range};
use super::{Method, Reconstructor};
use crate::error::Result;
use crate::frame::Frame;
use crate::image::Image;
use crate::progress::Progress;
use crate::recon::ops::reflect;
use crate::report::Report;

/// Default `noise_band`: the band's half-width in standard deviations of the base's noise.
pub(crate) const NOISE_BAND: f32 = 5.0;

/// Default `band_trim`: neighbours brighter than this many times (the pixel + [`TRIM_FLOOR`])
/// leave the band's variance mean.
pub(crate) const BAND_TRIM: f32 = 8.0;

/// Where the noise band clamps the output.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum BandScope {
    /// Every pixel (the default of every method that has a band).
    All,
    /// Only the pixels whose band the trimming narrowed: the dark neighbours of an emitter's
    /// edge, where a solve or a denoiser spreads the emitter. The prior path's choice: there
    /// the band everywhere undoes the prior where a dark pixel's few samples all missed the
    /// light (variance 0).
    Edges,
}

choices!(BandScope { All => "all", Edges => "edges" });

/// The least spp at which the band is trimmed (frames of unknown spp never are).
pub(crate) const TRIM_MIN_SPP: f32 = 64.0;

/// The least spp at which [`BandScope::Edges`] clamps at all (frames of unknown spp never
/// do): with `n` samples a dark pixel beside a lamp covering a fraction `a` of its footprint
/// misses the lamp with probability `(1 - a)^n`, 13 % at `a` = 0.4 and 4 spp, 0.03 % at 16;
/// then its variance is 0 and its band excludes the right answer.
pub(crate) const EDGES_MIN_SPP: f32 = 16.0;

/// Radiance added to the pixel's base value in the trimming test: the square root of relMSE's
/// 0.01, so that dark pixels compare against a fixed level rather than against 0.
const TRIM_FLOOR: f32 = 0.1;

/// The trimming that applies to `frame`: the ratio (0: none) and, where only the neighbours
/// that are a bright object's edge leave the mean, those pixels' flags. At [`TRIM_MIN_SPP`] or
/// more every neighbour beyond the ratio leaves; below (or with the spp unknown) only edge
/// pixels do, where `edges` asks for it, else none. Fails only with
/// [`Error::OutOfMemory`](crate::Error::OutOfMemory).
fn trimming(trim: f32, edges: bool, frame: &Frame) -> Result<(f32, Option<Vec<bool>>)> {
    if trim <= 0.0 {
        return Ok((0.0, None));
    }
    match frame.spp() {
        Some(spp) if spp >= TRIM_MIN_SPP => Ok((trim, None)),
        _ if edges => Ok((trim, Some(edge_pixels(frame, trim)?))),
        _ => Ok((0.0, None)),
    }
}

/// The `noise_band` entry of a method's parameter table (`get` and `set` reach its field):
/// one name, range and meaning for every method that has a band.
pub(crate) const fn param<C>(get: fn(&C) -> f32, set: fn(&mut C, f32)) -> Param<C> {
    Param::float(
        "noise_band",
        Range::closed(0.0, 1e6),
        NOISE_BAND_DOC,
        get,
        set,
    )
}

/// The `band_trim` entry of a method's parameter table, shared as [`param`].
pub(crate) const fn trim_param<C>(get: fn(&C) -> f32, set: fn(&mut C, f32)) -> Param<C> {
    Param::float(
        "band_trim",
        Range::closed(0.0, 1e6),
        BAND_TRIM_DOC,
        get,
        set,
    )
}

/// The `band_emitters` entry of a method's parameter table, shared as [`param`].
pub(crate) const fn emitters_param<C>(get: fn(&C) -> bool, set: fn(&mut C, bool)) -> Param<C> {
    Param::bool("band_emitters", BAND_EMITTERS_DOC, get, set)
}

/// The `band_scope` entry of a method's parameter table, shared as [`param`].
/// `get` and `set` take the choice's index ([`BandScope::index`], [`BandScope::ALL`]).
pub(crate) const fn scope_param<C>(get: fn(&C) -> usize, set: fn(&mut C, usize)) -> Param<C> {
    Param::choice("band_scope", BandScope::NAMES, BAND_SCOPE_DOC, get, set)
}

/// The documentation of every method's `band_scope` parameter.
const BAND_SCOPE_DOC: &str =
    "Where the noise band clamps: every pixel (all), or only the pixels whose band the \
     trimming narrowed, the dark neighbours of an emitter's edge, at 16 spp or more (edges)";

/// The documentation of every method's `band_emitters` parameter.
const BAND_EMITTERS_DOC: &str =
    "Below 64 spp, or with the spp unknown, still trim the noise band of the neighbours that \
     the gradients confirm as a bright object's edge (a lamp in view, not a firefly), at the \
     band_trim ratio";

/// The documentation of every method's `band_trim` parameter.
const BAND_TRIM_DOC: &str =
    "At 64 spp or more (frames that carry their spp), leave out of the noise band's 3 x 3 \
     variance mean the neighbours whose base colour exceeds this many times (the pixel's + \
     0.1): an emitter's edge then no longer widens its dark neighbours' band (below 64 spp, \
     band_emitters trims at the same ratio); 0: never";

/// The documentation of every method's `noise_band` parameter.
const NOISE_BAND_DOC: &str =
    "Clamp the output to the base image ± this many standard deviations of its noise (the \
     variance layer's 3 x 3 mean): where a reconstruction leaves the base by more, it is \
     wrong there; 0: off (frames without a variance layer are never clamped)";

/// `inner`, its output clamped to the noise band of half-width `k`, trimmed at ratio `trim`
/// where the frame's spp allows, and below that of edge pixels if `edges`, over `scope`
/// (`inner` itself when `k` is 0). The band is taken around the frame the plan is given, whatever `inner` makes of
/// it (the prior path anchors its solve to a prior, not to the base).
pub(crate) fn banded(
    inner: Box<dyn Reconstructor>,
    k: f32,
    trim: f32,
    edges: bool,
    scope: BandScope,
) -> Box<dyn Reconstructor> {
    if k > 0.0 {
        Box::new(Banded {
            inner,
            k,
            trim,
            edges,
            scope,
        })
    } else {
        inner
    }
}

struct Banded {
    inner: Box<dyn Reconstructor>,
    k: f32,
    trim: f32,
    edges: bool,
    scope: BandScope,
}

impl Reconstructor for Banded {
    fn method(&self) -> Method {
        self.inner.method()
    }

    fn reconstruct_into(
        &mut self,
        frame: &Frame,
        out: &mut Image,
        report: &mut Report,
        progress: &Progress,
    ) -> Result<()> {
        self.inner.reconstruct_into(frame, out, report, progress)?;
        if frame.variance().is_none() {
            report.skip("noise band (no variance layer)");
            return Ok(());
        }
        if self.scope == BandScope::Edges && frame.spp().is_none_or(|spp| spp < EDGES_MIN_SPP) {
            report.skip("noise band (edges only, from 16 spp)");
            return Ok(());
        }
        let k = self.k;
        let (moved, trim, edges) = report.time("noise band", || -> Result<_> {
            let (trim, edges) = trimming(self.trim, self.edges, frame)?;
            let moved = clamp_to_band(out, frame, k, trim, edges.as_deref(), self.scope);
            Ok((moved, trim, edges))
        })?;
        if moved > 0 {
            let how = match (trim > 0.0, edges) {
                (false, _) => String::new(),
                (true, None) => format!(", trimmed at {trim}x"),
                (true, Some(e)) => format!(
                    ", trimmed at {trim}x of {} edge pixels",
                    e.iter().filter(|&&e| e).count()
                ),
            };
            report.note(format!(
                "noise band: {moved} values clamped to the base ± {k} standard deviations{how}"
            ));
        }
        Ok(())
    }
}

/// Clamps `out` to the base image ± `k` standard deviations of its noise, the variance mean
/// trimmed at ratio `trim` (0: not trimmed; the spp gate is the caller's) of every neighbour
/// beyond it, or with `edges` of those that are edge pixels only, at every pixel or (`scope`
/// [`BandScope::Edges`]) at those whose mean lost a neighbour; returns how many values moved
/// (0 without a variance layer or with `k` 0, which means off).
pub(crate) fn clamp_to_band(
    out: &mut Image,
    frame: &Frame,
    k: f32,
    trim: f32,
    edges: Option<&[bool]>,
    scope: BandScope,
) -> u64 {
    let Some(var) = frame.variance() else {
        return 0;
    };
    if k <= 0.0 {
        return 0;
    }
    let (w, h) = out.size();
    if w == 0 || h == 0 {
        return 0;
    }
    let (base, var) = (frame.color().as_slice(), var.as_slice());
    let n = w * h;
    out.as_mut_slice()
        .par_chunks_mut(w)
        .enumerate()
        .map_init(
            || (vec![0.0f64; w], vec![0u32; w], vec![0.0f32; w]),
            |(sum, count, limit), (row, values)| {
                let (c, y) = (row / h, row % h);
                let plane = c * n;
                // Rows y - 1, y, y + 1 of the variance and of the base (reflect-101).
                let at = |d: usize| plane + reflect(y as isize + d as isize - 1, h) * w;
                let rows: [Neighbours; 3] = std::array::from_fn(|d| Neighbours {
                    var: &var[at(d)..at(d) + w],
                    base: &base[at(d)..at(d) + w],
                    // The rows' edge flags (every pixel may leave when all are trimmed).
                    edge: edges.map(|e| &e[at(d) - plane..at(d) - plane + w]),
                });
                let centre = &base[plane + y * w..plane + (y + 1) * w];
                // Neighbours brighter than this leave the mean; infinite when not trimming.
                for (l, &b) in limit.iter_mut().zip(centre) {
                    *l = if trim > 0.0 {
                        trim * (b.max(0.0) + TRIM_FLOOR)
                    } else {
                        f32::INFINITY
                    };
                }
                band_sums(&rows, limit, sum, count);
                clamp_row(values, centre, sum, count, k, scope == BandScope::Edges)
            },
        )
        .sum()
}

/// A row of the variance, of the base and (when only edge pixels leave) of the edge flags.
struct Neighbours<'a> {
    var: &'a [f32],
    base: &'a [f32],
    edge: Option<&'a [bool]>,
}

/// Per pixel `x` of a row whose rows above, at and below are `rows`: `sum` of the variances of
/// the 3 x 3 neighbours kept and their `count` (a neighbour other than the pixel leaves when its
/// base exceeds `limit[x]` and, with edge flags, it is an edge pixel), in the order of the
/// rows then the columns, in f64. The columns between the two ends go by whole-row passes,
/// one per neighbour (so that they vectorise), where a neighbour that leaves adds 0.0 (the
/// sum is never -0.0, so that is leaving it out); the two end columns read across the border
/// (reflect-101).
fn band_sums(rows: &[Neighbours; 3], limit: &[f32], sum: &mut [f64], count: &mut [u32]) {
    let w = sum.len();
    let keeps = |r: &Neighbours, xx: usize, x: usize, centre: bool| {
        centre || !(r.base[xx] > limit[x] && r.edge.is_none_or(|e| e[xx]))
    };
    for x in std::iter::once(0).chain((w > 1).then_some(w - 1)) {
        let (mut s, mut k) = (0.0f64, 0u32);
        for (d, r) in rows.iter().enumerate() {
            for dx in -1..=1 {
                let xx = reflect(x as isize + dx, w);
                if keeps(r, xx, x, d == 1 && dx == 0) {
                    s += f64::from(r.var[xx]);
                    k += 1;
                }
            }
        }
        (sum[x], count[x]) = (s, k);
    }
    if w < 3 {
        return;
    }
    let m = w - 2;
    let (sum, count, limit) = (&mut sum[1..=m], &mut count[1..=m], &limit[1..=m]);
    sum.fill(0.0);
    count.fill(0);
    for (d, r) in rows.iter().enumerate() {
        for dx in 0..3 {
            let (var, base) = (&r.var[dx..dx + m], &r.base[dx..dx + m]);
            let edge = r.edge.map(|e| &e[dx..dx + m]);
            add_kept(sum, count, (var, base, edge), limit, d == 1 && dx == 1);
        }
    }
}

/// One neighbour's pass of [`band_sums`]: `sum += var`, `count += 1` where it is kept (always
/// when it is the pixel itself, `centre`).
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn add_kept(
    sum: &mut [f64],
    count: &mut [u32],
    (var, base, edge): (&[f32], &[f32], Option<&[bool]>),
    limit: &[f32],
    centre: bool,
) {
    let m = sum.len();
    let (count, var, base, limit) = (&mut count[..m], &var[..m], &base[..m], &limit[..m]);
    // Three loops rather than one with the branches inside, which would not vectorise.
    match (centre, edge) {
        (true, _) => {
            for i in 0..m {
                sum[i] += f64::from(var[i]);
                count[i] += 1;
            }
        }
        (false, None) => {
            for i in 0..m {
                let leaves = base[i] > limit[i];
                let keep = !leaves;
                sum[i] += if keep { f64::from(var[i]) } else { 0.0 };
                count[i] += u32::from(keep);
            }
        }
        (false, Some(edge)) => {
            let edge = &edge[..m];
            for i in 0..m {
                let leaves = base[i] > limit[i] && edge[i];
                let keep = !leaves;
                sum[i] += if keep { f64::from(var[i]) } else { 0.0 };
                count[i] += u32::from(keep);
            }
        }
    }
}

/// Clamps a row's `values` to `centre ± k sqrt(sum / count)` ([`band_sums`]), except, with
/// `edges_only`, where all nine neighbours were kept; returns how many values moved.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma"
))]
fn clamp_row(
    values: &mut [f32],
    centre: &[f32],
    sum: &[f64],
    count: &[u32],
    k: f32,
    edges_only: bool,
) -> u64 {
    let w = values.len();
    let (centre, sum, count) = (&centre[..w], &sum[..w], &count[..w]);
    let mut moved = 0u64;
    for x in 0..w {
        let v = values[x];
        let b = centre[x];
        let s = ((sum[x] / f64::from(count[x])).max(0.0).sqrt() * f64::from(k)) as f32;
        // `f32::clamp`'s values (NaN stays NaN and counts as moved), as selects.
        let (lo, hi) = (b - s, b + s);
        let clamped = if v < lo {
            lo
        } else if v > hi {
            hi
        } else {
            v
        };
        // A pixel the scope leaves keeps its value.
        let keep = (edges_only && count[x] == 9) || clamped == v;
        values[x] = if keep { v } else { clamped };
        moved += u64::from(!keep);
    }
    moved
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{FrameBuilder, Layer};
    use crate::validate::Policy;

    fn frame(w: usize, h: usize, var: Option<Image>) -> Frame {
        let colour = Image::from_fn(3, w, h, |(c, x, y)| {
            0.5 + 0.1 * ((x * 3 + y + c) % 4) as f32
        });
        frame_of(colour, var, None)
    }

    fn frame_of(colour: Image, var: Option<Image>, spp: Option<f32>) -> Frame {
        let (w, h) = colour.size();
        let zero = Image::zeros(3, w, h);
        let mut b = FrameBuilder::new()
            .image(Layer::Color, colour)
            .image(Layer::Dx, zero.clone())
            .image(Layer::Dy, zero)
            .spp(spp);
        if let Some(v) = var {
            b = b.image(Layer::Variance, v);
        }
        b.build(Policy::Strict).unwrap()
    }

    /// The definition, pixel by pixel, in f64: the neighbours kept are the pixel itself and
    /// those whose base is at most `trim (b + 0.1)` (all of them when `trim` is 0), or with
    /// `edges` those too that are not edge pixels; with `scope` [`BandScope::Edges`] a pixel
    /// that kept all nine is left as it is.
    fn reference(
        out: &Image,
        frame: &Frame,
        k: f32,
        trim: f32,
        edges: Option<&[bool]>,
        scope: BandScope,
    ) -> Image {
        let (w, h) = out.size();
        let var = frame.variance().unwrap();
        let base = frame.color();
        Image::from_fn(3, w, h, |(c, x, y)| {
            let b = base.at(c, x, y);
            let (mut sum, mut count) = (0.0f64, 0.0f64);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (xx, yy) = (reflect(x as isize + dx, w), reflect(y as isize + dy, h));
                    let centre = dx == 0 && dy == 0;
                    let edge = edges.is_none_or(|e| e[yy * w + xx]);
                    if trim > 0.0
                        && !centre
                        && edge
                        && base.at(c, xx, yy) > trim * (b.max(0.0) + 0.1)
                    {
                        continue;
                    }
                    sum += f64::from(var.at(c, xx, yy));
                    count += 1.0;
                }
            }
            if scope == BandScope::Edges && count == 9.0 {
                return out.at(c, x, y);
            }
            let s = ((sum / count).sqrt() * f64::from(k)) as f32;
            out.at(c, x, y).clamp(b - s, b + s)
        })
    }

    #[test]
    fn clamps_to_the_band_as_defined() {
        // 7 x 5 is the frame the counts below are about; the others, with one, two and three
        // columns or rows and a row longer than its ends, are checked against the definition.
        for (w, h) in [(7, 5), (1, 4), (2, 3), (3, 1), (40, 6)] {
            clamps_to_the_band_as_defined_at(w, h, (w, h) == (7, 5));
        }
    }

    fn clamps_to_the_band_as_defined_at(w: usize, h: usize, counts: bool) {
        // Bright, noisy pixels scattered over dark ones: trimming at 8x leaves them out of
        // their dark neighbours' means.
        let bright = |c: usize, x: usize, y: usize| (x * 3 + y * 2 + c) % 7;
        let var = Image::from_fn(3, w, h, |(c, x, y)| match bright(c, x, y) {
            0 => 1.0,
            _ => 1e-3 * ((x + 2 * y + c) % 5) as f32,
        });
        let colour = Image::from_fn(3, w, h, |(c, x, y)| match bright(c, x, y) {
            0 => 20.0,
            1 => 0.0,
            m => 0.05 * m as f32,
        });
        let f = frame_of(colour, Some(var), Some(64.0));
        let out = Image::from_fn(3, w, h, |(c, x, y)| ((x * 7 + y * 5 + c) % 9) as f32 * 0.15);
        // Some pixels flagged as edges, to trim those alone.
        let flags: Vec<bool> = (0..w * h).map(|p| p % 3 != 1).collect();
        let mut moves = Vec::new();
        let mut scoped = Vec::new();
        for (trim, edges) in [(0.0, None), (8.0, None), (8.0, Some(&flags[..]))] {
            for k in [0.5, 2.0, 5.0] {
                let mut got = out.clone();
                let moved = clamp_to_band(&mut got, &f, k, trim, edges, BandScope::All);
                let want = reference(&out, &f, k, trim, edges, BandScope::All);
                assert_eq!(
                    got,
                    want,
                    "k = {k}, trim = {trim}, edges {}",
                    edges.is_some()
                );
                let mut near = out.clone();
                let only = clamp_to_band(&mut near, &f, k, trim, edges, BandScope::Edges);
                let want_near = reference(&out, &f, k, trim, edges, BandScope::Edges);
                assert_eq!(near, want_near, "edges scope, k = {k}, trim = {trim}");
                assert!(only <= moved, "k = {k}, trim = {trim}");
                scoped.push(only);
                let differ = out
                    .as_slice()
                    .iter()
                    .zip(want.as_slice())
                    .filter(|(a, b)| a != b)
                    .count();
                assert_eq!(moved, differ as u64, "k = {k}, trim = {trim}");
                assert!(
                    !counts || moved > 0,
                    "the test must clamp something at k = {k}"
                );
                moves.push(moved);
            }
        }
        if !counts {
            return;
        }
        assert!(
            moves[3..6].iter().zip(&moves[..3]).all(|(t, u)| t > u),
            "trimming must narrow some bands: {moves:?}"
        );
        assert!(
            moves[6..].iter().zip(&moves[3..6]).any(|(e, t)| e < t),
            "trimming edges alone must keep some bands wider: {moves:?}"
        );
        // Untrimmed, the edges scope clamps nothing; trimmed, it clamps some but not all.
        assert!(scoped[..3].iter().all(|&m| m == 0), "{scoped:?}");
        assert!(
            scoped[3..].iter().all(|&m| m > 0)
                && scoped[3..].iter().zip(&moves[3..]).any(|(s, m)| s < m),
            "{scoped:?} against {moves:?}"
        );
    }

    /// A dark pixel beside an emitter's edge: the untrimmed band takes the edge's variance and
    /// lets a spread value through; trimmed (64 spp) it does not; below 64 spp, or with the
    /// spp unknown, the band is not trimmed when the gradients do not see the edge (here they
    /// are 0).
    #[test]
    fn an_emitter_widens_no_trimmed_band() {
        let (w, h) = (5, 3);
        let colour = Image::from_fn(3, w, h, |(_, x, _)| if x >= 3 { 400.0 } else { 0.02 });
        let var = Image::from_fn(3, w, h, |(_, x, _)| match x {
            3 => 2500.0, // the edge: partly covered, a few samples on the emitter
            4 => 1.0,
            _ => 1e-4,
        });
        // The solve spread the emitter into its dark neighbour (x = 2).
        let out = Image::from_fn(3, w, h, |(_, x, _)| match x {
            2 => 4.0,
            x if x >= 3 => 400.0,
            _ => 0.02,
        });
        for (spp, trimmed) in [(Some(64.0), true), (Some(16.0), false), (None, false)] {
            let f = frame_of(colour.clone(), Some(var.clone()), spp);
            let mut got = out.clone();
            let (trim, edges) = trimming(8.0, true, &f).unwrap();
            assert!(edges.as_ref().is_none_or(|e| e.iter().all(|&e| !e)));
            clamp_to_band(&mut got, &f, 5.0, trim, edges.as_deref(), BandScope::All);
            let dark = got.at(0, 2, 1);
            if trimmed {
                // sqrt(1e-4) x 5 = 0.05 around 0.02.
                assert!((dark - 0.07).abs() < 1e-6, "spp {spp:?}: {dark}");
            } else {
                assert_eq!(
                    dark, 4.0,
                    "spp {spp:?}: the band is 5 sqrt(2500 x 3 / 9) wide"
                );
            }
        }
    }

    /// A bulb in the last two columns of a `w` x 3 frame (its edge pixel, at `w - 2`, partly
    /// covered: variance 2500), the gradient across the edge seeing it, and an output whose
    /// dark pixel beside the edge (`w - 3`) the solve spread the bulb into (4; the base 0.02,
    /// variance 1e-4, so its trimmed band reaches 0.07).
    fn seen_lamp(w: usize, spp: Option<f32>) -> (Frame, Image) {
        let h = 3;
        let colour = Image::from_fn(3, w, h, |(_, x, _)| if x >= w - 2 { 400.0 } else { 0.02 });
        let var = Image::from_fn(3, w, h, |(_, x, _)| if x == w - 2 { 2500.0 } else { 1e-4 });
        // dx(w - 3) = I(w - 2) - I(w - 3): the gradient across the edge sees it.
        let dx = Image::from_fn(3, w, h, |(_, x, _)| if x == w - 3 { 399.98 } else { 0.0 });
        let out = Image::from_fn(3, w, h, |(_, x, _)| match x {
            x if x == w - 3 => 4.0,
            x if x >= w - 2 => 400.0,
            _ => 0.02,
        });
        let frame = FrameBuilder::new()
            .image(Layer::Color, colour)
            .image(Layer::Dx, dx)
            .image(Layer::Dy, Image::zeros(3, w, h))
            .image(Layer::Variance, var)
            .spp(spp)
            .build(Policy::Strict)
            .unwrap();
        (frame, out)
    }

    /// A reconstructor that writes a fixed image, to test the band's wrapper.
    struct Fixed(Image);

    impl Reconstructor for Fixed {
        fn method(&self) -> Method {
            Method::PoissonL1
        }

        fn reconstruct_into(
            &mut self,
            _: &Frame,
            out: &mut Image,
            _: &mut Report,
            _: &Progress,
        ) -> Result<()> {
            out.as_mut_slice().copy_from_slice(self.0.as_slice());
            Ok(())
        }
    }

    /// The edges scope clamps the emitter's spread dark neighbour from 16 spp on, never below
    /// or with the spp unknown, and leaves a pixel whose band lost no neighbour as it is
    /// whatever it holds; the full scope clamps both at any spp.
    #[test]
    fn the_edges_scope_clamps_beside_edges_from_16_spp() {
        for spp in [Some(4.0), Some(15.0), Some(16.0), Some(64.0), None] {
            let (f, spread) = seen_lamp(6, spp);
            // x = 3 spread from the emitter; x = 0 far from it, wrong by more than its band.
            let out = Image::from_fn(3, 6, 3, |(c, x, y)| match x {
                0 => 1.0,
                _ => spread.at(c, x, y),
            });
            for scope in [BandScope::All, BandScope::Edges] {
                let mut r = banded(Box::new(Fixed(out.clone())), 5.0, 8.0, true, scope);
                let mut got = Image::zeros(3, 6, 3);
                let mut report = Report::default();
                r.reconstruct_into(&f, &mut got, &mut report, &Progress::none())
                    .unwrap();
                let on = scope == BandScope::All || spp.is_some_and(|s| s >= 16.0);
                let (near, far) = (got.at(1, 3, 1), got.at(1, 0, 1));
                let near_want = if on { 0.07 } else { 4.0 };
                assert!(
                    (near - near_want).abs() < 1e-6,
                    "{scope:?}, spp {spp:?}: {near}"
                );
                let far_want = if scope == BandScope::All { 0.07 } else { 1.0 };
                assert!(
                    (far - far_want).abs() < 1e-6,
                    "{scope:?}, spp {spp:?}: {far}"
                );
            }
        }
    }

    /// The same emitter, its edge now seen by the gradients: below 64 spp (and with the spp
    /// unknown) the band is trimmed of it when edge trimming is on, and only then.
    #[test]
    fn a_seen_emitter_edge_is_trimmed_at_any_spp() {
        for spp in [Some(4.0), Some(16.0), None] {
            let (f, out) = seen_lamp(5, spp);
            for on in [true, false] {
                let (trim, edges) = trimming(8.0, on, &f).unwrap();
                let mut got = out.clone();
                clamp_to_band(&mut got, &f, 5.0, trim, edges.as_deref(), BandScope::All);
                let want = if on { 0.07 } else { 4.0 };
                assert!(
                    (got.at(0, 2, 1) - want).abs() < 1e-6,
                    "spp {spp:?}, edges {on}"
                );
            }
        }
    }

    #[test]
    fn without_variance_or_width_nothing_moves() {
        let (w, h) = (6, 4);
        let out = Image::from_fn(3, w, h, |(c, x, y)| (x + y + c) as f32);
        let mut got = out.clone();
        assert_eq!(
            clamp_to_band(&mut got, &frame(w, h, None), 5.0, 8.0, None, BandScope::All),
            0
        );
        assert_eq!(got, out);
        let zero_var = frame(w, h, Some(Image::zeros(3, w, h)));
        assert_eq!(
            clamp_to_band(&mut got, &zero_var, 0.0, 8.0, None, BandScope::All),
            0
        );
        assert_eq!(got, out);
        // Zero variance and a band: the base image itself.
        clamp_to_band(&mut got, &zero_var, 5.0, 8.0, None, BandScope::All);
        assert_eq!(&got, zero_var.color());
    }
}
