//! RFC 3339 times of the admin API and of the account commands (`myriad user ban
//! --until`, `user list`), to and from milliseconds since the Unix epoch (the store's
//! unit), in UTC.

use std::time::{SystemTime, UNIX_EPOCH};

use time::OffsetDateTime;
use time::format_description::well_known::Rfc3339;

/// `ms` (since the Unix epoch) as RFC 3339 in UTC, with milliseconds.
pub fn format_ms(ms: i64) -> String {
    let nanos = i128::from(ms) * 1_000_000;
    OffsetDateTime::from_unix_timestamp_nanos(nanos)
        .ok()
        .and_then(|t| t.format(&Rfc3339).ok())
        .unwrap_or_else(|| format!("@{ms}ms"))
}

/// A wall-clock time as RFC 3339.
pub fn format_system(t: SystemTime) -> String {
    let ms = match t.duration_since(UNIX_EPOCH) {
        Ok(d) => d.as_millis() as i64,
        Err(e) => -(e.duration().as_millis() as i64),
    };
    format_ms(ms)
}

/// Parses an RFC 3339 time (`2026-12-03T09:00:00Z`, `…+01:00`, fractions allowed) into
/// milliseconds since the Unix epoch.
pub fn parse_ms(text: &str) -> Result<i64, String> {
    let t = OffsetDateTime::parse(text.trim(), &Rfc3339)
        .map_err(|e| format!("{text:?} is not an RFC 3339 time (like 2026-12-03T09:00:00Z): {e}"))?;
    i64::try_from(t.unix_timestamp_nanos() / 1_000_000).map_err(|_| format!("{text:?} is out of range"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects_junk() {
        assert_eq!(format_ms(0), "1970-01-01T00:00:00Z");
        assert_eq!(parse_ms("2026-12-03T09:00:00Z").unwrap(), 1_796_288_400_000);
        assert_eq!(parse_ms("2026-12-03T10:00:00+01:00").unwrap(), 1_796_288_400_000);
        assert_eq!(parse_ms(&format_ms(1_796_288_400_123)).unwrap(), 1_796_288_400_123);
        assert!(parse_ms("tomorrow").unwrap_err().contains("RFC 3339"));
        assert!(parse_ms("2026-13-03T09:00:00Z").is_err());
    }
}
