//! `pareto.png` and `pareto.svg`: relMSE against median seconds, log-log, one panel per spp;
//! `scaling.png` and `scaling.svg` (with `--scales`): median seconds against pixels, log-log,
//! one line per variant and frame.
//!
//! Text is drawn with DejaVu Sans compiled into the binary (plotters' `ab_glyph` path), so
//! neither system fonts nor fontconfig are needed. The PNG is rendered into a buffer and
//! encoded with the `png` crate the library already uses.

use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use super::aggregate::{Panel, Point};
use super::measure::Row;

/// Pixels per panel.
const PANEL_WIDTH: u32 = 560;
/// Height of the panels.
const PANEL_HEIGHT: u32 = 480;
/// Height of the legend strip under the panels.
const LEGEND_HEIGHT: u32 = 40;
/// The font family every text uses.
const FONT: &str = "sans-serif";

/// Writes both plots to `png` and `svg`.
pub fn write(png: &Path, svg: &Path, panels: &[Panel]) -> gdrecon::Result<()> {
    register_dejavu().map_err(|e| plot_error(png, e))?;
    let size = (
        PANEL_WIDTH * panels.len().max(1) as u32,
        PANEL_HEIGHT + LEGEND_HEIGHT,
    );
    let mut pixels = vec![0u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        draw(&root, panels).map_err(|e| plot_error(png, e.to_string()))?;
    }
    encode_png(png, &pixels, size)?;
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, size).into_drawing_area();
        draw(&root, panels).map_err(|e| plot_error(svg, e.to_string()))?;
    }
    super::report::write(svg, &text)
}

/// One line of the scaling plot: variant, method, (pixels, seconds) by increasing size.
type Line = (String, String, Vec<(f64, f64)>);

/// Writes the scaling plot to `png` and `svg`: every (variant, frame) of `rows` timed at two
/// or more sizes.
pub fn write_scaling(png: &Path, svg: &Path, rows: &[Row]) -> gdrecon::Result<()> {
    register_dejavu().map_err(|e| plot_error(png, e))?;
    let lines: Vec<Line> = super::summary::groups(rows)
        .into_iter()
        .filter_map(|(variant, frame)| {
            let of: Vec<&Row> = rows
                .iter()
                .filter(|r| r.variant == variant && r.frame == frame)
                .collect();
            let mut points: Vec<(f64, f64)> =
                of.iter().map(|r| (r.pixels() as f64, r.median_s)).collect();
            points.sort_by(|a, b| a.0.total_cmp(&b.0));
            let method = of.first()?.method.clone();
            (points.len() >= 2).then_some((variant, method, points))
        })
        .collect();
    let size = (PANEL_WIDTH + 360, PANEL_HEIGHT + 60);
    let mut pixels = vec![0u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        draw_scaling(&root, &lines).map_err(|e| plot_error(png, e.to_string()))?;
    }
    encode_png(png, &pixels, size)?;
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, size).into_drawing_area();
        draw_scaling(&root, &lines).map_err(|e| plot_error(svg, e.to_string()))?;
    }
    super::report::write(svg, &text)
}

/// Seconds against pixels, one coloured line per variant, labelled at its largest size.
fn draw_scaling<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    lines: &[Line],
) -> DrawResult<DB> {
    root.fill(&WHITE)?;
    let all = || lines.iter().flat_map(|l| l.2.iter().copied());
    let (x0, x1) = log_bounds(all().map(|p| p.0));
    let (y0, y1) = log_bounds(all().map(|p| p.1));
    let mut chart = ChartBuilder::on(root)
        .caption("time against frame size", (FONT, 20))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (x0..x1 * 3.0)
                .log_scale()
                .with_key_points(key_points(x0, x1 * 3.0)),
            (y0..y1).log_scale().with_key_points(key_points(y0, y1)),
        )?;
    chart
        .configure_mesh()
        .x_desc("pixels per frame")
        .y_desc("median seconds per frame")
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .y_label_formatter(&|v| tick(*v))
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 14))
        .light_line_style(WHITE)
        .draw()?;
    for (variant, method, points) in lines {
        let color = method_color(method);
        chart.draw_series(LineSeries::new(
            points.iter().copied(),
            color.stroke_width(2),
        ))?;
        chart.draw_series(points.iter().map(|&p| Circle::new(p, 4, color.filled())))?;
        if let Some(&last) = points.last() {
            chart.draw_series(std::iter::once(
                EmptyElement::at(last) + Text::new(label(variant), (8, -6), (FONT, 12)),
            ))?;
        }
    }
    root.present()
}

/// A variant's label, OIDN named as such.
fn label(variant: &str) -> String {
    if variant == super::aggregate::OIDN {
        format!("{variant} (OIDN)")
    } else {
        variant.to_owned()
    }
}

/// A plotting failure as an error naming the file.
fn plot_error(path: &Path, message: String) -> gdrecon::Error {
    gdrecon::Error::Io {
        path: path.to_owned(),
        source: std::io::Error::other(format!("drawing the plot failed: {message}")),
    }
}

/// Registers the bundled font once.
fn register_dejavu() -> Result<(), String> {
    static DONE: OnceLock<bool> = OnceLock::new();
    let ok = *DONE
        .get_or_init(|| register_font(FONT, FontStyle::Normal, dejavu::sans::regular()).is_ok());
    ok.then_some(())
        .ok_or_else(|| "the bundled DejaVu Sans font did not load".to_owned())
}

/// Encodes an RGB8 buffer as PNG.
fn encode_png(path: &Path, pixels: &[u8], (w, h): (u32, u32)) -> gdrecon::Result<()> {
    let io = |source| gdrecon::Error::Io {
        path: path.to_owned(),
        source,
    };
    let file = std::fs::File::create(path).map_err(io)?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let as_io = |e: png::EncodingError| match e {
        png::EncodingError::IoError(source) => io(source),
        other => io(std::io::Error::other(other.to_string())),
    };
    let mut writer = encoder.write_header().map_err(as_io)?;
    writer.write_image_data(pixels).map_err(as_io)?;
    writer.finish().map_err(as_io)
}

/// The error type of drawing on backend `DB`.
type DrawResult<DB> = Result<(), DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;

/// Draws every panel side by side (or a note when there is nothing to plot).
fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, panels: &[Panel]) -> DrawResult<DB> {
    root.fill(&WHITE)?;
    if panels.is_empty() {
        root.draw(&Text::new(
            "nothing to plot: no frame with a reference and a known spp",
            (20, 20),
            (FONT, 16),
        ))?;
    }
    let (top, bottom) = root.split_vertically(PANEL_HEIGHT);
    for (area, panel) in top
        .split_evenly((1, panels.len().max(1)))
        .iter()
        .zip(panels)
    {
        draw_panel(area, panel)?;
    }
    draw_legend(&bottom, panels)?;
    root.present()
}

/// The legend strip: one colour per method, then what filled, hollow and the line mean.
fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    panels: &[Panel],
) -> DrawResult<DB> {
    let all: Vec<Point> = panels.iter().flat_map(|p| p.points.clone()).collect();
    let y = (LEGEND_HEIGHT / 2) as i32;
    let mut x = 70;
    for method in methods(&all) {
        area.draw(&Circle::new((x, y), 5, method_color(&method).filled()))?;
        area.draw(&Text::new(method.clone(), (x + 10, y - 8), (FONT, 14)))?;
        x += 30 + 9 * method.len() as i32;
    }
    let grey = BLACK.mix(0.45);
    area.draw(&PathElement::new(vec![(x, y), (x + 24, y)], grey))?;
    area.draw(&Text::new(
        "Pareto front: filled points (no other variant is both faster and more accurate); \
         hollow: dominated",
        (x + 32, y - 8),
        (FONT, 14),
    ))
}

/// One spp: the variants' points, labelled, coloured by method, and the Pareto front.
fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, panel: &Panel) -> DrawResult<DB> {
    let (x0, x1) = log_bounds(panel.points.iter().map(|p| p.seconds));
    let (y0, y1) = log_bounds(panel.points.iter().map(|p| p.rel_mse));
    let mut chart = ChartBuilder::on(area)
        .caption(format!("{} spp", panel.spp), (FONT, 20))
        .margin(14)
        .x_label_area_size(44)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (x0..x1).log_scale().with_key_points(key_points(x0, x1)),
            (y0..y1).log_scale().with_key_points(key_points(y0, y1)),
        )?;
    chart
        .configure_mesh()
        .x_desc("median seconds per frame")
        .y_desc("relMSE, geometric mean over scenes")
        .x_label_formatter(&|v| tick(*v))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 14))
        .light_line_style(WHITE)
        .draw()?;
    let grey = BLACK.mix(0.45);
    chart.draw_series(LineSeries::new(front(&panel.points), grey.stroke_width(1)))?;
    let font: TextStyle = (FONT, 12).into();
    let pixels: Vec<Pixel> = panel
        .points
        .iter()
        .map(|p| chart.backend_coord(&(p.seconds, p.rel_mse)))
        .collect();
    let sizes = panel
        .points
        .iter()
        .map(|p| area.estimate_text_size(&p.variant, &font))
        .collect::<Result<Vec<_>, _>>()?;
    let offsets = label_offsets(&pixels, &sizes, chart.plotting_area().get_pixel_range());
    chart.draw_series(panel.points.iter().zip(offsets).map(|(p, offset)| {
        EmptyElement::at((p.seconds, p.rel_mse))
            + Circle::new((0, 0), 5, marker_style(p, method_color(&p.method)))
            + Text::new(p.variant.clone(), offset, font.clone())
    }))?;
    Ok(())
}

/// A pixel position on the backend.
type Pixel = (i32, i32);

/// A pixel rectangle `(left, top, right, bottom)`.
type Rect = (i32, i32, i32, i32);

/// Label positions relative to their points: for each label (in order) the first candidate
/// spot, right of the point, then above or below, then left, whose box stays inside the plot
/// and overlaps no point and no label placed before it; the first spot when none is free.
fn label_offsets(
    points: &[Pixel],
    sizes: &[(u32, u32)],
    (xs, ys): (std::ops::Range<i32>, std::ops::Range<i32>),
) -> Vec<Pixel> {
    let mut taken: Vec<Rect> = points
        .iter()
        .map(|&(x, y)| (x - 6, y - 6, x + 6, y + 6))
        .collect();
    let mut offsets = Vec::with_capacity(points.len());
    for (&(px, py), &(w, h)) in points.iter().zip(sizes) {
        let (w, h) = (w as i32, h as i32);
        let candidates = [
            (8, -h / 2),
            (8, -h - 3),
            (8, 3),
            (-8 - w, -h / 2),
            (-8 - w, -h - 3),
            (-8 - w, 3),
            (-w / 2, -h - 8),
            (-w / 2, 8),
            (8, h + 3),
            (8, -2 * h - 3),
        ];
        let rect = |(dx, dy): Pixel| (px + dx, py + dy, px + dx + w, py + dy + h);
        let fits = |r: Rect| {
            r.0 >= xs.start
                && r.2 <= xs.end
                && r.1 >= ys.start
                && r.3 <= ys.end
                && !taken.iter().any(|t| overlap(*t, r))
        };
        let chosen = candidates
            .into_iter()
            .find(|&c| fits(rect(c)))
            .unwrap_or(candidates[0]);
        taken.push(rect(chosen));
        offsets.push(chosen);
    }
    offsets
}

/// Whether two rectangles intersect.
fn overlap(a: Rect, b: Rect) -> bool {
    a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3
}

/// Tick values inside `lo..hi`: 1, 2 and 5 times the powers of ten, or 1 and 3, or only the
/// powers, the wider the range.
fn key_points(lo: f64, hi: f64) -> Vec<f64> {
    let first = lo.log10().floor() as i32;
    let last = hi.log10().ceil() as i32;
    let mantissas: &[f64] = match (hi / lo).log10() {
        d if d <= 1.5 => &[1.0, 2.0, 5.0],
        d if d <= 3.0 => &[1.0, 3.0],
        _ => &[1.0],
    };
    (first..=last)
        .flat_map(|e| mantissas.iter().map(move |m| m * 10f64.powi(e)))
        .filter(|v| (lo..=hi).contains(v))
        .collect()
}

/// A point's marker: filled on the Pareto front, hollow otherwise.
fn marker_style(p: &Point, color: RGBColor) -> ShapeStyle {
    if p.pareto {
        color.filled()
    } else {
        color.stroke_width(1)
    }
}

/// The Pareto points by increasing time.
fn front(points: &[Point]) -> Vec<(f64, f64)> {
    let mut front: Vec<(f64, f64)> = points
        .iter()
        .filter(|p| p.pareto)
        .map(|p| (p.seconds, p.rel_mse))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    front
}

/// The methods present, in the CLI's order (unknown names last, as first seen).
fn methods(points: &[Point]) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for p in points {
        if !out.contains(&p.method) {
            out.push(p.method.clone());
        }
    }
    let rank = |m: &String| gdrecon::Method::ALL.iter().position(|k| k.name() == m);
    out.sort_by_key(|m| rank(m).unwrap_or(usize::MAX));
    out
}

/// A fixed colour per method: its place in the registry's order picks one of these.
const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

/// The colour of `method`; grey for a name this build does not know.
fn method_color(method: &str) -> RGBColor {
    gdrecon::Method::ALL
        .iter()
        .position(|m| m.name() == method)
        .map_or(RGBColor(90, 90, 90), |i| PALETTE[i % PALETTE.len()])
}

/// A log axis range around positive values, with room for labels.
fn log_bounds(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return (0.1, 10.0);
    }
    (lo / 1.6, hi * 2.5)
}

/// An axis tick value: up to two significant digits, no trailing zeros.
fn tick(v: f64) -> String {
    if v >= 10.0 {
        format!("{v:.0}")
    } else {
        let digits = (1 - v.log10().floor() as i32).max(0) as usize;
        let s = format!("{v:.digits$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_owned()
        } else {
            s
        }
    }
}
