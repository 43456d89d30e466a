//! Numeric CSV files with a header line: reading with errors that name the file, line and
//! column, and buffered writing. Offline only: never used on the real-time path.

use std::fmt;
use std::io::{BufWriter, Write};
use std::path::Path;

/// A CSV error naming the file and, where it applies, line and column (1-based).
#[derive(Debug, Clone, PartialEq)]
pub struct CsvError {
    pub path: String,
    pub line: Option<usize>,
    pub column: Option<usize>,
    pub message: String,
}

impl fmt::Display for CsvError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.path)?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if let Some(column) = self.column {
            write!(f, ":{column}")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for CsvError {}

/// Columns read from a numeric CSV file, in the order asked for.
#[derive(Debug, Clone, PartialEq)]
pub struct Columns {
    pub names: Vec<String>,
    pub data: Vec<Vec<f64>>,
    /// File line (1-based) of each data row, so later checks name the right line even
    /// when the file has blank lines.
    pub lines: Vec<usize>,
}

impl Columns {
    pub fn len(&self) -> usize {
        self.data.first().map_or(0, Vec::len)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Reads the named columns of a CSV file with a header line. Extra columns are ignored.
pub fn read_columns(path: &Path, wanted: &[&str]) -> Result<Columns, CsvError> {
    let origin = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| CsvError {
        path: origin.clone(),
        line: None,
        column: None,
        message: format!("cannot read: {e}"),
    })?;
    parse_columns(&text, &origin, wanted)
}

/// Parses CSV text; `origin` names the file in errors.
///
/// Tolerates what spreadsheets and other tools write: a UTF-8 byte-order mark, CRLF line
/// endings, blank lines, spaces around fields and double-quoted fields. Other separators
/// (`;`, tab) are rejected with an error that says so.
pub fn parse_columns(text: &str, origin: &str, wanted: &[&str]) -> Result<Columns, CsvError> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let err = |line: Option<usize>, column: Option<usize>, message: String| CsvError {
        path: origin.to_string(),
        line,
        column,
        message,
    };
    let mut lines = text.lines().enumerate();
    let header = loop {
        match lines.next() {
            None => {
                return Err(err(
                    None,
                    None,
                    format!("empty file: expected a header line `{}`", wanted.join(",")),
                ))
            }
            Some((_, l)) if l.trim().is_empty() => continue,
            Some((i, l)) => break (i + 1, l),
        }
    };
    let names: Vec<&str> = header.1.split(',').map(unquote).collect();
    if names.len() < wanted.len() {
        if let Some(sep) = [';', '\t'].into_iter().find(|c| header.1.contains(*c)) {
            let shown = if sep == '\t' {
                "tab".to_string()
            } else {
                format!("`{sep}`")
            };
            return Err(err(
                Some(header.0),
                None,
                format!(
                    "header `{}` is separated by {shown}: columns must be separated by commas, \
                     with `.` as the decimal point (expected `{}`)",
                    header.1.trim(),
                    wanted.join(",")
                ),
            ));
        }
    }
    let mut index = Vec::with_capacity(wanted.len());
    for want in wanted {
        match names.iter().position(|n| n == want) {
            Some(i) => index.push(i),
            None => {
                return Err(err(
                    Some(header.0),
                    None,
                    format!(
                        "header `{}` lacks column `{want}`: expected `{}`",
                        header.1.trim(),
                        wanted.join(",")
                    ),
                ))
            }
        }
    }
    let needed = index.iter().copied().max().unwrap_or(0) + 1;
    let mut data: Vec<Vec<f64>> = vec![Vec::with_capacity(text.len() / 32); wanted.len()];
    let mut line_numbers = Vec::with_capacity(text.len() / 32);
    // Fields of the current line, reused across lines (no allocation per row).
    let mut fields: Vec<&str> = Vec::with_capacity(needed.max(names.len()));
    for (i, line) in lines {
        let line_no = i + 1;
        if line.trim().is_empty() {
            continue;
        }
        fields.clear();
        fields.extend(line.split(',').take(needed));
        if fields.len() < needed {
            let missing = index
                .iter()
                .filter(|&&col| col >= fields.len())
                .map(|&col| format!("`{}`", names[col]))
                .collect::<Vec<_>>()
                .join(", ");
            return Err(err(
                Some(line_no),
                Some(fields.len() + 1),
                format!(
                    "row has {} field(s), lacks column {missing} (expected `{}`)",
                    fields.len(),
                    names.join(",")
                ),
            ));
        }
        line_numbers.push(line_no);
        for (out, &col) in data.iter_mut().zip(&index) {
            let field = unquote(fields[col]);
            match field.parse::<f64>() {
                Ok(x) if x.is_finite() => out.push(x),
                Ok(_) => {
                    return Err(err(
                        Some(line_no),
                        Some(col + 1),
                        format!(
                            "column `{}` is `{field}`: expected a finite number",
                            names[col]
                        ),
                    ))
                }
                Err(_) => {
                    return Err(err(
                        Some(line_no),
                        Some(col + 1),
                        format!("column `{}` is `{field}`: not a number", names[col]),
                    ))
                }
            }
        }
    }
    Ok(Columns {
        names: wanted.iter().map(|s| s.to_string()).collect(),
        data,
        lines: line_numbers,
    })
}

/// A field without surrounding spaces and double quotes.
fn unquote(field: &str) -> &str {
    let f = field.trim();
    f.strip_prefix('"')
        .and_then(|g| g.strip_suffix('"'))
        .map_or(f, str::trim)
}

/// Largest relative deviation of one time step from the mean step.
pub const STEP_TOLERANCE: f64 = 0.02;

/// Checks that a time column is strictly increasing with a uniform step; returns the step.
///
/// Uniform means every step within `STEP_TOLERANCE` (2 %) of the mean step. Timestamps
/// are usually written with a fixed number of decimals: at 3 kHz printed to 0.1 us, or at
/// 5120 Hz printed to 1 us, rounding alone moves single steps by 0.03 % to 1 %, and such
/// files are uniformly sampled. A skipped sample or a clock jump moves a step by far more.
/// `line_numbers` gives the file line of each row (`Columns::lines`) for the errors;
/// if it is shorter than `time_s`, row i is taken to be line i + 2 (header, no blanks).
pub fn uniform_step(
    time_s: &[f64],
    line_numbers: &[usize],
    origin: &str,
    column: &str,
) -> Result<f64, CsvError> {
    let line_of = |row: usize| line_numbers.get(row).copied().unwrap_or(row + 2);
    let err = |line: Option<usize>, message: String| CsvError {
        path: origin.to_string(),
        line,
        column: None,
        message,
    };
    if time_s.len() < 2 {
        return Err(err(
            None,
            format!("needs at least two data rows, found {}", time_s.len()),
        ));
    }
    let dt = (time_s[time_s.len() - 1] - time_s[0]) / (time_s.len() - 1) as f64;
    for (i, pair) in time_s.windows(2).enumerate() {
        let step = pair[1] - pair[0];
        if step <= 0.0 {
            return Err(err(
                Some(line_of(i + 1)),
                format!(
                    "`{column}` = {} does not increase (previous {})",
                    pair[1], pair[0]
                ),
            ));
        }
        if (step - dt).abs() > STEP_TOLERANCE * dt.abs().max(1e-300) + 1e-12 {
            return Err(err(
                Some(line_of(i + 1)),
                format!("`{column}` step {step:e} s differs from the mean step {dt:e} s: the time step must be uniform"),
            ));
        }
    }
    Ok(dt)
}

/// Writes columns as CSV with a header line. Numbers use the shortest form that reads
/// back to the same `f64` (zmij), so nothing is lost between tools.
pub fn write_columns(path: &Path, names: &[&str], columns: &[&[f64]]) -> std::io::Result<()> {
    let file = std::fs::File::create(path)?;
    let mut out = BufWriter::with_capacity(1 << 20, file);
    writeln!(out, "{}", names.join(","))?;
    let rows = columns.first().map_or(0, |c| c.len());
    let mut number = zmij::Buffer::new();
    for row in 0..rows {
        for (i, col) in columns.iter().enumerate() {
            if i > 0 {
                out.write_all(b",")?;
            }
            out.write_all(number.format(col[row]).as_bytes())?;
        }
        out.write_all(b"\n")?;
    }
    out.flush()
}
