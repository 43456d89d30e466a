//! Readable TOML errors for every configuration file: line, table, the line's text and the
//! closest valid key for a misspelt one; formats only (no I/O, no validation of values).

/// "at line 6 in [loop] (`rat_hz = 4096.0`): unknown field `rat_hz`, expected one of
/// `rate_hz`, ... (did you mean `rate_hz`?)".
pub fn describe(text: &str, e: &toml::de::Error) -> String {
    let message = e.message().trim().replace('\n', " ");
    let Some(span) = e.span() else {
        return message;
    };
    let start = span.start.min(text.len());
    // A top-level table missing: the span is the file's start (empty) or the whole file,
    // whose first line says nothing.
    if let Some(field) = message
        .strip_prefix("missing field `")
        .and_then(|r| r.split_once('`'))
        .map(|(f, _)| f)
    {
        if start == 0 && (span.end == 0 || span.end >= text.trim_end().len()) {
            return format!(
                "at the top: {message}: the file has no `[{field}]` table (add it with its keys, or `{field} = ...` at the top when it is a value; docs/config.md lists them)"
            );
        }
    }
    let line_no = text[..start].matches('\n').count() + 1;
    let line = text.lines().nth(line_no - 1).unwrap_or("").trim();
    let table = text
        .lines()
        .take(line_no)
        .filter_map(|l| {
            let l = l.trim();
            (l.starts_with('[') && l.ends_with(']')).then_some(l)
        })
        .last();
    let mut out = format!("at line {line_no}");
    if let Some(t) = table.filter(|t| *t != line) {
        out.push_str(&format!(" in {t}"));
    }
    if !line.is_empty() {
        out.push_str(&format!(" (`{line}`)"));
    }
    out.push_str(&format!(": {message}"));
    if let Some(guess) = closest_known_field(&message) {
        out.push_str(&format!(" (did you mean `{guess}`?)"));
    }
    // The table the error is in: the line itself when it is a header.
    let header = table.map(|t| t.trim_matches(['[', ']']));
    if message.starts_with("invalid type: map, expected a sequence")
        && line.starts_with('[')
        && !line.starts_with("[[")
    {
        out.push_str(&format!(
            " (a list of tables: write `[[{}]]`, one per entry)",
            line.trim_matches(['[', ']'])
        ));
    } else if let (Some(field), Some(t)) = (
        message
            .strip_prefix("missing field `")
            .and_then(|r| r.split_once('`'))
            .map(|(f, _)| f),
        header,
    ) {
        out.push_str(&format!(
            " (add `{field}` to [{t}]: `{field} = ...`, or its own table `[{t}.{field}]` when it is one)"
        ));
    }
    out
}

/// For serde's "unknown field `x`, expected one of `a`, `b`", the valid key nearest to `x`
/// when it is near enough to be a misspelling.
fn closest_known_field(message: &str) -> Option<String> {
    let rest = message.strip_prefix("unknown field `")?;
    let (unknown, rest) = rest.split_once('`')?;
    let candidates: Vec<&str> = rest
        .split('`')
        .skip(1)
        .step_by(2)
        .filter(|c| !c.is_empty())
        .collect();
    closest_key(unknown, &candidates).map(str::to_string)
}

/// The key among `candidates` nearest to `unknown`, when it is near enough to be a
/// misspelling of it (for keys checked outside serde, such as `[rig.actuator]`'s).
pub fn closest_key<'a>(unknown: &str, candidates: &[&'a str]) -> Option<&'a str> {
    let (distance, best) = candidates
        .iter()
        .map(|c| (edit_distance(unknown, c), *c))
        .min_by_key(|(d, _)| *d)?;
    if distance <= (unknown.len() / 3).max(2) {
        return Some(best);
    }
    // Else the one key that shares the most words (two at least) with it: a misnamed
    // key (`valve_bandwidth_hz` for `valve_frequency_hz`) rather than a misspelt one.
    let shared = |c: &str| {
        c.split('_')
            .filter(|w| unknown.split('_').any(|u| u == *w))
            .count()
    };
    let most = candidates.iter().map(|c| shared(c)).max()?;
    let mut with_most = candidates.iter().filter(|c| shared(c) == most);
    match (with_most.next(), with_most.next()) {
        (Some(only), None) if most >= 2 => Some(*only),
        _ => None,
    }
}

/// Levenshtein distance over chars.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diagonal = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let substitution = diagonal + usize::from(ca != *cb);
            diagonal = row[j + 1];
            row[j + 1] = substitution.min(row[j] + 1).min(diagonal + 1);
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Loop {
        rate_hz: f64,
        spin_us: f64,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct File {
        #[serde(rename = "loop")]
        loop_: Loop,
    }

    fn error_of(text: &str) -> String {
        describe(text, &toml::from_str::<File>(text).unwrap_err())
    }

    #[test]
    fn a_misspelt_key_names_line_table_text_and_the_closest_key() {
        let text = "# header\n[loop]\nspin_us = 20.0\nrat_hz = 4096.0\n";
        let e = error_of(text);
        assert!(
            e.starts_with("at line 4 in [loop] (`rat_hz = 4096.0`): unknown field `rat_hz`"),
            "{e}"
        );
        assert!(e.ends_with("(did you mean `rate_hz`?)"), "{e}");
        // Nothing near: no guess.
        let e = error_of("[loop]\nrate_hz = 1.0\nspin_us = 1.0\nbandwidth = 3\n");
        assert!(
            e.contains("unknown field `bandwidth`") && !e.contains("did you mean"),
            "{e}"
        );
    }

    #[test]
    fn a_wrong_type_names_its_line_and_value() {
        let e = error_of("[loop]\nrate_hz = \"fast\"\nspin_us = 1.0\n");
        assert!(
            e.starts_with("at line 2 in [loop] (`rate_hz = \"fast\"`): invalid type"),
            "{e}"
        );
    }

    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct Lists {
        rig: Rig,
        #[serde(default)]
        inject: Vec<Loop>,
    }
    #[derive(serde::Deserialize, Debug)]
    #[allow(dead_code)]
    struct Rig {
        seed: u64,
        actuator: Loop,
    }

    /// A table written for a list of tables, and a missing table, say what to write.
    #[test]
    fn a_list_written_as_a_table_and_a_missing_table_say_what_to_write() {
        let of = |text: &str| describe(text, &toml::from_str::<Lists>(text).unwrap_err());
        let e = of("[rig]\nseed = 1\n[rig.actuator]\nrate_hz = 1.0\nspin_us = 1.0\n[inject]\nrate_hz = 1.0\nspin_us = 1.0\n");
        assert!(
            e.starts_with("at line 6 (`[inject]`): invalid type: map, expected a sequence")
                && e.ends_with("(a list of tables: write `[[inject]]`, one per entry)"),
            "{e}"
        );
        let e = of("[rig]\nseed = 1\n");
        assert!(
            e.contains("missing field `actuator`")
                && e.ends_with(
                    "(add `actuator` to [rig]: `actuator = ...`, or its own table `[rig.actuator]` when it is one)"
                ),
            "{e}"
        );
    }

    /// A table the file lacks is named as such, not at its first line (a new user's
    /// trial: "at line 1 (`# fastemu hil: ...`): missing field `compensation`"); a key
    /// misnamed by a word gets the key that shares its words.
    #[test]
    fn a_missing_table_and_a_misnamed_key_are_named() {
        #[derive(Debug, serde::Deserialize)]
        #[allow(dead_code)]
        struct Top {
            #[serde(rename = "loop")]
            loop_: Loop,
            other: Loop,
        }
        let text = "# a comment
[loop]
rate_hz = 1.0
spin_us = 1.0
";
        let e = describe(text, &toml::from_str::<Top>(text).unwrap_err());
        assert!(
            e.starts_with("at the top: missing field `other`: the file has no `[other]` table"),
            "{e}"
        );
        assert!(!e.contains("line 1"), "{e}");
        let keys = [
            "valve_frequency_hz",
            "valve_damping_ratio",
            "force_loop_bandwidth_hz",
        ];
        assert_eq!(
            closest_key("valve_bandwith_hz", &keys),
            Some("valve_frequency_hz")
        );
        // One shared word, or a tie: no guess.
        assert_eq!(closest_key("loop_gain", &keys), None);
        assert_eq!(closest_key("valve_ratio_hz", &keys), None);
    }

    #[test]
    fn edit_distance_counts_single_edits() {
        assert_eq!(edit_distance("rate_hz", "rate_hz"), 0);
        assert_eq!(edit_distance("rat_hz", "rate_hz"), 1);
        assert_eq!(edit_distance("spin_su", "spin_us"), 2);
        assert_eq!(edit_distance("", "abc"), 3);
    }
}
