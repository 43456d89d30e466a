//! UTC calendar time from Unix seconds, without a date crate: the one civil-from-days
//! conversion the report names and the synthetic campaigns share. Must not: read clocks.

/// Year, month, day, hour, minute and second (UTC) of `unix_s` seconds since 1970.
pub fn civil(unix_s: i64) -> [i64; 6] {
    let (days, secs) = (unix_s.div_euclid(86_400), unix_s.rem_euclid(86_400));
    // Civil from days (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    [year, month, day, secs / 3600, secs / 60 % 60, secs % 60]
}

#[cfg(test)]
mod tests {
    #[test]
    fn days_and_leap_years_fall_where_the_calendar_puts_them() {
        assert_eq!(super::civil(0), [1970, 1, 1, 0, 0, 0]);
        assert_eq!(super::civil(951_782_400), [2000, 2, 29, 0, 0, 0]);
        assert_eq!(super::civil(1_700_000_000), [2023, 11, 14, 22, 13, 20]);
        assert_eq!(super::civil(-1), [1969, 12, 31, 23, 59, 59]);
    }
}
