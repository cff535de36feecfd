//! The clock the scheduler, the simulated fields and all timestamps share:
//! real time, or accelerated by a factor.

use std::time::{Duration, Instant};

use chrono::{DateTime, TimeDelta, Utc};

/// Clock time = `origin` + (real time since start) × `speedup`.
#[derive(Debug, Clone, Copy)]
pub struct Clock {
    started: Instant,
    origin: DateTime<Utc>,
    speedup: f64,
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

    /// The clock of a shared epoch: epoch + (real now − epoch) × speedup.
    pub fn anchored(epoch: DateTime<Utc>, speedup: f64) -> Clock {
        let real = Utc::now();
        let gone = (real - epoch).num_microseconds().unwrap_or(0) as f64;
        let origin = epoch + TimeDelta::microseconds((gone * speedup) as i64);
        Clock::new(origin, speedup)
    }

    pub fn speedup(&self) -> f64 {
        self.speedup
    }

    pub fn now(&self) -> DateTime<Utc> {
        let real = self.started.elapsed().as_secs_f64();
        self.origin + TimeDelta::microseconds((real * self.speedup * 1e6) as i64)
    }

    /// The real time until clock time `t` (zero if it has passed).
    pub fn real_until(&self, t: DateTime<Utc>) -> Duration {
        let ahead = (t - self.now()).num_microseconds().unwrap_or(i64::MAX) as f64 / 1e6;
        Duration::from_secs_f64((ahead / self.speedup).max(0.0))
    }

    /// Sleeps until clock time `t`.
    pub async fn sleep_until(&self, t: DateTime<Utc>) {
        let wait = self.real_until(t);
        if !wait.is_zero() {
            tokio::time::sleep(wait).await;
        }
    }
}

/// The first multiple of `period_s` (counted from the Unix epoch) strictly
/// after `t`.
pub fn next_boundary(t: DateTime<Utc>, period_s: f64) -> DateTime<Utc> {
    let period_ms = (period_s * 1000.0).round().max(1.0) as i64;
    let ms = t.timestamp_millis();
    let next = (ms.div_euclid(period_ms) + 1) * period_ms;
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
}
