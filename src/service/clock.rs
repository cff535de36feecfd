//! The clock the scheduler, the simulated fields and all timestamps share:
//! real time, or accelerated by a factor.

use std::time::{Duration, Instant};

use chrono::{DateTime, TimeDelta, Utc};

/// Clock time = `origin` + (real time since start) × `speedup`, kept within
/// the years 2000 … 2199 (it stops at the end of 2199 rather than overflow).
#[derive(Debug, Clone, Copy)]
pub struct Clock {
    started: Instant,
    origin: DateTime<Utc>,
    speedup: f64,
}

/// The last instant the clock reaches: the end of 2199.
pub fn end_of_time() -> DateTime<Utc> {
    DateTime::from_timestamp(7_258_118_400, 0).unwrap_or(DateTime::<Utc>::MAX_UTC)
}

fn start_of_time() -> DateTime<Utc> {
    DateTime::from_timestamp(946_684_800, 0).unwrap_or(DateTime::<Utc>::MIN_UTC)
}

/// `t` plus `seconds`, saturating at the ends of the clock's range.
pub fn add_seconds(t: DateTime<Utc>, seconds: f64) -> DateTime<Utc> {
    let end = end_of_time();
    let start = start_of_time();
    let room = (end - t).num_milliseconds() as f64 / 1e3;
    let back = (start - t).num_milliseconds() as f64 / 1e3;
    if seconds.is_nan() {
        return t;
    }
    if seconds >= room {
        return end.max(t);
    }
    if seconds <= back {
        return start.min(t);
    }
    t + TimeDelta::milliseconds((seconds * 1e3).round() as i64)
}

impl Clock {
    /// A clock reading `origin` now and running `speedup` times faster than
    /// real time.
    pub fn new(origin: DateTime<Utc>, speedup: f64) -> Clock {
        Clock {
            started: Instant::now(),
            origin,
            speedup: if speedup.is_finite() && speedup > 0.0 {
                speedup
            } else {
                1.0
            },
        }
    }

    /// The clock of a shared epoch: epoch + (real now − epoch) × speedup;
    /// refused when that lies outside the years 2000 … 2199.
    pub fn anchored(epoch: DateTime<Utc>, speedup: f64) -> Result<Clock, String> {
        let real = Utc::now();
        let gone = (real - epoch).num_milliseconds() as f64 / 1e3;
        let ahead = gone * speedup;
        let room = (end_of_time() - epoch).num_milliseconds() as f64 / 1e3;
        let back = (start_of_time() - epoch).num_milliseconds() as f64 / 1e3;
        if !(ahead.is_finite() && ahead < room && ahead >= back) {
            return Err(format!(
                "the clock would read {:.0} years after {} now, outside the years 2000 to 2199; \
                 choose an epoch closer to now or a smaller speedup",
                ahead / (365.25 * 86_400.0),
                epoch.to_rfc3339()
            ));
        }
        Ok(Clock::new(add_seconds(epoch, ahead), speedup))
    }

    pub fn speedup(&self) -> f64 {
        self.speedup
    }

    pub fn now(&self) -> DateTime<Utc> {
        let real = self.started.elapsed().as_secs_f64();
        add_seconds(self.origin, real * self.speedup)
    }

    /// The real time until clock time `t` (zero if it has passed); a time
    /// the clock never reaches (after 2199) is a day away, again and again.
    pub fn real_until(&self, t: DateTime<Utc>) -> Duration {
        let now = self.now();
        if t > end_of_time() && now >= end_of_time() {
            return Duration::from_secs(86_400);
        }
        let ahead = (t - now).num_milliseconds() as f64 / 1e3;
        Duration::from_secs_f64((ahead / self.speedup).clamp(0.0, 1e9))
    }

    /// Sleeps until clock time `t`.
    pub async fn sleep_until(&self, t: DateTime<Utc>) {
        loop {
            let wait = self.real_until(t);
            if wait.is_zero() {
                return;
            }
            tokio::time::sleep(wait).await;
            if self.now() >= t {
                return;
            }
        }
    }
}

/// The first multiple of `period_s` (counted from the Unix epoch) strictly
/// after `t`.
pub fn next_boundary(t: DateTime<Utc>, period_s: f64) -> DateTime<Utc> {
    let period_ms = (period_s * 1000.0).round().max(1.0) as i64;
    let ms = t.timestamp_millis();
    let next = ms
        .div_euclid(period_ms)
        .saturating_add(1)
        .saturating_mul(period_ms);
    DateTime::from_timestamp_millis(next).unwrap_or(t)
}

/// The last multiple of `period_s` at or before `t`.
pub fn boundary_at_or_before(t: DateTime<Utc>, period_s: f64) -> DateTime<Utc> {
    let period_ms = (period_s * 1000.0).round().max(1.0) as i64;
    let ms = t.timestamp_millis();
    DateTime::from_timestamp_millis(ms.div_euclid(period_ms) * period_ms).unwrap_or(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boundaries_are_multiples_of_the_period() {
        let t = DateTime::parse_from_rfc3339("2026-05-01T03:17:00Z")
            .unwrap()
            .to_utc();
        let next = next_boundary(t, 7200.0);
        assert_eq!(next.to_rfc3339(), "2026-05-01T04:00:00+00:00");
        assert_eq!(
            boundary_at_or_before(t, 7200.0).to_rfc3339(),
            "2026-05-01T02:00:00+00:00"
        );
        // on a boundary: the next one is a period later
        assert_eq!(next_boundary(next, 7200.0) - next, TimeDelta::hours(2));
        assert_eq!(boundary_at_or_before(next, 7200.0), next);
    }

    #[test]
    fn an_accelerated_clock_runs_faster() {
        let origin = Utc::now();
        let clock = Clock::new(origin, 3600.0);
        std::thread::sleep(Duration::from_millis(20));
        let gone = (clock.now() - origin).num_milliseconds() as f64 / 1000.0;
        // 20 ms of real time are at least 72 s of clock time
        assert!((72.0..3600.0).contains(&gone), "{gone}");
        let wait = clock.real_until(clock.now() + TimeDelta::seconds(3600));
        assert!((wait.as_secs_f64() - 1.0).abs() < 0.05, "{wait:?}");
    }

    #[test]
    fn the_clock_stays_within_its_years_instead_of_overflowing() {
        let t = |s: &str| DateTime::parse_from_rfc3339(s).unwrap().to_utc();
        // an epoch far back with a large speedup is refused, not a panic
        assert!(Clock::anchored(t("1000-01-01T00:00:00Z"), 1e3).is_err());
        assert!(Clock::anchored(t("2000-01-01T00:00:00Z"), 1e5).is_err());
        assert!(Clock::anchored(t("2026-01-01T00:00:00Z"), 1.0).is_ok());
        // a clock that runs past 2199 stops at its end
        let clock = Clock::new(t("2199-12-31T23:59:00Z"), 1e5);
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(clock.now(), end_of_time());
        assert_eq!(add_seconds(t("2026-01-01T00:00:00Z"), 1e300), end_of_time());
        assert_eq!(
            add_seconds(t("2026-01-01T00:00:00Z"), 60.0),
            t("2026-01-01T00:01:00Z")
        );
        // beyond the end, a wait does not spin
        assert!(clock.real_until(end_of_time() + TimeDelta::hours(2)) >= Duration::from_secs(1));
    }
}
