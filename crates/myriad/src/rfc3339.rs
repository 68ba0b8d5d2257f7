//! RFC 3339 times for the account commands (`user ban --until`, `user list`), to and from
//! milliseconds since the Unix epoch. Written here rather than taken from a date crate:
//! two conversions of the proleptic Gregorian calendar are all the commands need.

use anyhow::{Result, bail};

/// Days from 1970-01-01 to the given civil date (H. Hinnant's `days_from_civil`).
fn days_from_civil(year: i64, month: i64, day: i64) -> i64 {
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// The civil date of a day count from 1970-01-01 (`civil_from_days`).
fn civil_from_days(days: i64) -> (i64, i64, i64) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    (yoe + era * 400 + i64::from(month <= 2), month, day)
}

fn days_in_month(year: i64, month: i64) -> i64 {
    let leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
    match month {
        2 if leap => 29,
        2 => 28,
        4 | 6 | 9 | 11 => 30,
        _ => 31,
    }
}

fn number(s: &str, what: &str) -> Result<i64> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        bail!("bad {what} {s:?}");
    }
    Ok(s.parse()?)
}

/// Parses `YYYY-MM-DDTHH:MM:SS[.fraction](Z|+HH:MM|-HH:MM)` (a space may replace the `T`)
/// into milliseconds since the Unix epoch.
pub fn parse_ms(text: &str) -> Result<i64> {
    let t = text.trim();
    let bad = || anyhow::anyhow!("{text:?} is not an RFC 3339 time (e.g. 2026-12-24T18:00:00Z)");
    if t.len() < 20 || !t.is_ascii() {
        return Err(bad());
    }
    let (date, rest) = t.split_at(10);
    let sep = rest.as_bytes()[0];
    if !matches!(sep, b'T' | b't' | b' ') || date.as_bytes()[4] != b'-' || date.as_bytes()[7] != b'-' {
        return Err(bad());
    }
    let (year, month, day) = (number(&date[..4], "year")?, number(&date[5..7], "month")?, number(&date[8..10], "day")?);
    let time = &rest[1..];
    if time.len() < 9 || time.as_bytes()[2] != b':' || time.as_bytes()[5] != b':' {
        return Err(bad());
    }
    let (hour, minute, second) =
        (number(&time[..2], "hour")?, number(&time[3..5], "minute")?, number(&time[6..8], "second")?);
    let mut rest = &time[8..];
    let mut millis = 0;
    if let Some(frac) = rest.strip_prefix('.') {
        let digits = frac.bytes().take_while(u8::is_ascii_digit).count();
        if digits == 0 {
            return Err(bad());
        }
        let ms: String = frac[..digits].chars().chain("000".chars()).take(3).collect();
        millis = number(&ms, "fraction")?;
        rest = &frac[digits..];
    }
    let offset_min = match rest {
        "Z" | "z" => 0,
        _ if rest.len() == 6 && rest.as_bytes()[3] == b':' => {
            let sign = match rest.as_bytes()[0] {
                b'+' => 1,
                b'-' => -1,
                _ => return Err(bad()),
            };
            let (h, m) = (number(&rest[1..3], "offset hour")?, number(&rest[4..6], "offset minute")?);
            if h > 23 || m > 59 {
                return Err(bad());
            }
            sign * (h * 60 + m)
        }
        _ => return Err(bad()),
    };
    if !(1..=12).contains(&month) || day < 1 || day > days_in_month(year, month) {
        bail!("{text:?}: no such date");
    }
    // Leap seconds (60) are read as the next second, which is what an epoch count holds.
    if hour > 23 || minute > 59 || second > 60 {
        bail!("{text:?}: no such time of day");
    }
    let seconds = days_from_civil(year, month, day) * 86_400 + hour * 3600 + minute * 60 + second - offset_min * 60;
    Ok(seconds * 1000 + millis)
}

/// Formats milliseconds since the Unix epoch as `YYYY-MM-DDTHH:MM:SSZ` (UTC, seconds).
pub fn format_ms(ms: i64) -> String {
    let seconds = ms.div_euclid(1000);
    let (days, in_day) = (seconds.div_euclid(86_400), seconds.rem_euclid(86_400));
    let (y, m, d) = civil_from_days(days);
    format!("{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z", in_day / 3600, in_day % 3600 / 60, in_day % 60)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_instants() {
        assert_eq!(parse_ms("1970-01-01T00:00:00Z").unwrap(), 0);
        assert_eq!(parse_ms("2000-03-01T00:00:00Z").unwrap(), 951_868_800_000);
        assert_eq!(parse_ms("2026-12-02T16:00:00.5Z").unwrap(), 1_796_227_200_500);
        assert_eq!(parse_ms("2026-12-02T18:00:00+02:00").unwrap(), parse_ms("2026-12-02T16:00:00Z").unwrap());
        assert_eq!(parse_ms("2026-12-02 10:30:00-05:30").unwrap(), parse_ms("2026-12-02T16:00:00Z").unwrap());
        assert_eq!(format_ms(951_868_800_000), "2000-03-01T00:00:00Z");
        assert_eq!(format_ms(1_796_227_200_500), "2026-12-02T16:00:00Z");
    }

    #[test]
    fn round_trips_over_centuries() {
        for ms in (-5_000_000_000_000i64..8_000_000_000_000).step_by(86_399_997_000) {
            let s = ms - ms.rem_euclid(1000);
            assert_eq!(parse_ms(&format_ms(s)).unwrap(), s, "{}", format_ms(s));
        }
    }

    #[test]
    fn refuses_what_is_not_a_time() {
        for bad in [
            "2026-12-02",
            "2026-12-02T16:00:00",
            "2026-13-02T16:00:00Z",
            "2026-02-29T16:00:00Z",
            "2026-12-02T24:00:00Z",
            "2026-12-02T16:00:00+2:00",
            "tomorrow",
            "2026-12-02T16:00:00.Z",
        ] {
            assert!(parse_ms(bad).is_err(), "{bad}");
        }
        assert!(parse_ms("2024-02-29T00:00:00Z").is_ok(), "a leap day");
    }
}
