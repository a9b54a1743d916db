//! Machine-readable results: `results.csv`, `results.json` and the plain `--csv` table.

use std::fmt::Write as _;
use std::path::Path;

use super::measure::Row;

/// The columns of `results.csv` and the keys of `results.json`, in order.
pub const COLUMNS: [&str; 17] = [
    "scene",
    "spp",
    "method",
    "setting",
    "scale",
    "width",
    "height",
    "pixels",
    "threads",
    "runs",
    "median_s",
    "min_s",
    "max_s",
    "rel_mse",
    "peak_rss_mib",
    "stages",
    "oidn_s",
];

/// A value of one column, as text for CSV and as a JSON literal.
enum Value {
    Text(String),
    Number(String),
    Missing,
}

/// The row's values in [`COLUMNS`] order.
fn values(r: &Row) -> [Value; 17] {
    use Value::{Number as N, Text as T};
    let opt = |v: Option<String>| v.map_or(Value::Missing, N);
    [
        T(r.scene.clone()),
        opt(r.spp.map(|s| s.to_string())),
        T(r.method.clone()),
        T(r.setting.clone()),
        N(r.scale.to_string()),
        N(r.width.to_string()),
        N(r.height.to_string()),
        N(r.pixels().to_string()),
        N(r.threads.to_string()),
        N(r.runs.to_string()),
        N(format!("{:.6}", r.median_s)),
        N(format!("{:.6}", r.min_s)),
        N(format!("{:.6}", r.max_s)),
        opt(r.rel_mse.map(|v| format!("{v:.5e}"))),
        opt(r.peak_rss_mib.map(|v| format!("{v:.1}"))),
        // Stage medians as `name=seconds` separated by semicolons (empty: one stage).
        T(r.stages
            .iter()
            .map(|(name, s)| format!("{name}={s:.6}"))
            .collect::<Vec<_>>()
            .join(";")),
        // OIDN's median when timed alternately with this row (`--against-oidn`).
        opt(r.oidn_s.map(|v| format!("{v:.6}"))),
    ]
}

/// `results.csv`: a header line and one line per row; missing values are empty.
pub fn csv(rows: &[Row]) -> String {
    let mut out = COLUMNS.join(",") + "\n";
    for r in rows {
        let cells: Vec<String> = values(r)
            .into_iter()
            .map(|v| match v {
                Value::Text(t) => csv_cell(&t),
                Value::Number(n) => n,
                Value::Missing => String::new(),
            })
            .collect();
        out += &(cells.join(",") + "\n");
    }
    out
}

/// Quotes a CSV cell when it holds a comma, quote or line break.
fn csv_cell(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_owned()
    }
}

/// `results.json`: an array with one object per row; missing values are `null`.
pub fn json(rows: &[Row]) -> String {
    let mut out = String::from("[\n");
    for (i, r) in rows.iter().enumerate() {
        let fields: Vec<String> = COLUMNS
            .iter()
            .zip(values(r))
            .map(|(k, v)| {
                let literal = match v {
                    Value::Text(t) => json_string(&t),
                    Value::Number(n) => n,
                    Value::Missing => "null".to_owned(),
                };
                format!("\"{k}\": {literal}")
            })
            .collect();
        let comma = if i + 1 < rows.len() { "," } else { "" };
        let _ = writeln!(out, "  {{{}}}{comma}", fields.join(", "));
    }
    out + "]\n"
}

/// A JSON string literal.
fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// The plain `--csv` table (the format `bench` always wrote).
pub fn plain_csv(rows: &[Row]) -> String {
    let mut out = String::from(
        "frame,method,width,height,threads,runs,median_s,min_s,max_s,rel_mse,peak_rss_mib\n",
    );
    for r in rows {
        let rel = r
            .rel_mse
            .map_or_else(|| "-".to_owned(), |v| format!("{v:.5e}"));
        let peak = r
            .peak_rss_mib
            .map_or_else(|| "-".to_owned(), |p| format!("{p:.0}"));
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{:.6},{:.6},{:.6},{rel},{peak}",
            csv_cell(&r.frame),
            r.variant,
            r.width,
            r.height,
            r.threads,
            r.runs,
            r.median_s,
            r.min_s,
            r.max_s
        );
    }
    out
}

/// Writes `text` to `path`, naming the file in the error.
pub fn write(path: &Path, text: &str) -> gdrecon::Result<()> {
    std::fs::write(path, text).map_err(|source| gdrecon::Error::Io {
        path: path.to_owned(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_escapes_and_nulls() {
        assert_eq!(json_string("a\"b\\c\n"), "\"a\\\"b\\\\c\\u000a\"");
        assert_eq!(csv_cell("a,b"), "\"a,b\"");
    }
}
