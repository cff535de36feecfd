//! `GET /v1/fields/{id}/history.csv` (issue 18): a field's measurements,
//! setpoints (with their explanation) and forecasts in one CSV, oldest first
//! within each record kind, streamed page by page so that a long range
//! never sits in memory whole.
//!
//! Columns (RFC 4180, header first):
//! `record,time,sensor,theta,rate_m_s,amount_mm,valve_minutes,status,explanation,step_s,et0_mm,precip_mm`
//! - `measurement`: time, sensor (empty for the primary), theta;
//! - `setpoint`: time (the cycle's), rate, amount, valve minutes, status
//!   and an explanation (solver status, the degraded flags, the fallback
//!   reason, the first predicted θ and the zone of the first step);
//! - `forecast`: one row per forecast step, time = its start, the issue
//!   time in `explanation`.

use chrono::{DateTime, TimeDelta, Utc};

use super::store::{Sensors, Store, StoreError};
use super::wire::{Forecast, Measurement, Setpoint};

/// Rows read from the store per page.
pub const PAGE: usize = 2_000;

pub const HEADER: &str = "record,time,sensor,theta,rate_m_s,amount_mm,valve_minutes,status,explanation,step_s,et0_mm,precip_mm\n";

/// Where the export has got to.
#[derive(Debug, Clone)]
pub struct Cursor {
    phase: Phase,
    /// The time of the last row written, and how many rows at that time
    /// were written (rows at one instant may straddle pages).
    at: DateTime<Utc>,
    skip: usize,
    pub from: DateTime<Utc>,
    pub to: DateTime<Utc>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    Header,
    Measurements,
    Setpoints,
    Forecasts,
    Done,
}

impl Cursor {
    pub fn new(from: DateTime<Utc>, to: DateTime<Utc>) -> Cursor {
        Cursor {
            phase: Phase::Header,
            at: from,
            skip: 0,
            from,
            to,
        }
    }

    /// The next chunk of CSV, or None when the export is complete.
    pub fn next_chunk(&mut self, store: &Store, field: i64) -> Result<Option<String>, StoreError> {
        loop {
            match self.phase {
                Phase::Header => {
                    self.phase = Phase::Measurements;
                    return Ok(Some(HEADER.to_string()));
                }
                Phase::Measurements => {
                    let rows = store.measurements(
                        field,
                        Some(self.at),
                        Some(self.to),
                        PAGE,
                        Sensors::All,
                    )?;
                    if let Some(chunk) = self.page(&rows, |m| m.time, measurement_row) {
                        return Ok(Some(chunk));
                    }
                    self.next_phase(Phase::Setpoints);
                }
                Phase::Setpoints => {
                    let rows = store.setpoints(field, Some(self.at), Some(self.to), PAGE)?;
                    if let Some(chunk) = self.page(&rows, |s| s.time, setpoint_row) {
                        return Ok(Some(chunk));
                    }
                    self.next_phase(Phase::Forecasts);
                }
                Phase::Forecasts => {
                    // forecasts issued in the range (a bounded number: one
                    // per post, each at most 30 days of steps)
                    let mut out = String::new();
                    for f in store.forecasts_since(field, self.from, PAGE)? {
                        if f.issued_at <= self.to {
                            forecast_rows(&f, &mut out);
                        }
                    }
                    self.phase = Phase::Done;
                    if !out.is_empty() {
                        return Ok(Some(out));
                    }
                }
                Phase::Done => return Ok(None),
            }
        }
    }

    fn next_phase(&mut self, phase: Phase) {
        self.phase = phase;
        self.at = self.from;
        self.skip = 0;
    }

    /// The CSV of the rows not yet written, advancing the cursor; None when
    /// the page holds nothing new.
    fn page<T>(
        &mut self,
        rows: &[T],
        time: impl Fn(&T) -> DateTime<Utc>,
        write: impl Fn(&T, &mut String),
    ) -> Option<String> {
        // the first `skip` rows at the cursor's instant were written before
        let repeated = rows
            .iter()
            .take(self.skip)
            .take_while(|r| time(r) == self.at)
            .count();
        let fresh: Vec<&T> = rows[repeated..].iter().collect();
        if fresh.is_empty() {
            return None;
        }
        let mut out = String::new();
        for r in &fresh {
            write(r, &mut out);
        }
        let last = time(fresh[fresh.len() - 1]);
        let same = fresh.iter().rev().take_while(|r| time(r) == last).count();
        self.skip = if last == self.at {
            self.skip + same
        } else {
            same
        };
        self.at = last;
        Some(out)
    }
}

/// One CSV record (quoted by the csv crate where a cell needs it).
fn row(out: &mut String, cells: [&str; 12]) {
    let mut w = csv::WriterBuilder::new()
        .has_headers(false)
        .from_writer(Vec::with_capacity(128));
    // writing to memory cannot fail, and the cells are UTF-8
    if w.write_record(cells).is_ok()
        && let Ok(bytes) = w.into_inner()
    {
        out.push_str(&String::from_utf8_lossy(&bytes));
    }
}

fn measurement_row(m: &Measurement, out: &mut String) {
    let time = m.time.to_rfc3339();
    let theta = m.theta.to_string();
    row(
        out,
        [
            "measurement",
            &time,
            m.sensor.as_deref().unwrap_or(""),
            &theta,
            "",
            "",
            "",
            "",
            "",
            "",
            "",
            "",
        ],
    );
}

fn setpoint_row(s: &Setpoint, out: &mut String) {
    let time = s.time.to_rfc3339();
    let rate = s.rate.to_string();
    let amount = s.amount_mm.to_string();
    let minutes = s
        .valve
        .as_ref()
        .map(|v| v.valve_minutes.to_string())
        .unwrap_or_default();
    let why = &s.explanation;
    row(
        out,
        [
            "setpoint", &time, "", "", &rate, &amount, &minutes, &s.status, why, "", "", "",
        ],
    );
}

fn forecast_rows(f: &Forecast, out: &mut String) {
    let issued = format!("issued {}", f.issued_at.to_rfc3339());
    let step = f.step_s.to_string();
    for (i, (et0, p)) in f.et0_mm.iter().zip(&f.precip_mm).enumerate() {
        let t = f.start + TimeDelta::milliseconds((i as f64 * f.step_s * 1e3) as i64);
        row(
            out,
            [
                "forecast",
                &t.to_rfc3339(),
                "",
                "",
                "",
                "",
                "",
                "",
                &issued,
                &step,
                &et0.to_string(),
                &p.to_string(),
            ],
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::wire::FieldSpec;

    #[test]
    fn a_long_range_streams_in_pages_with_every_row_once() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let t0: DateTime<Utc> = "2026-06-01T00:00:00Z".parse().unwrap();
        let field = store
            .create_field(
                &FieldSpec {
                    actuator: crate::service::wire::Actuator::None,
                    simulation: None,
                    ..FieldSpec::demo()
                },
                t0,
            )
            .unwrap();
        // 2.5 pages of readings, three at each instant (so instants
        // straddle page ends), each θ distinct
        let n = PAGE * 5 / 2;
        let batch: Vec<Measurement> = (0..n)
            .map(|i| Measurement {
                time: t0 + TimeDelta::minutes((i / 3) as i64),
                theta: 0.1 + i as f64 * 1e-6,
                sensor: [None, Some("b".to_string()), Some("c".to_string())][i % 3].clone(),
                true_theta: None,
                raw: None,
            })
            .collect();
        assert_eq!(store.add_measurements(field.id, &batch).unwrap(), n);
        let mut cursor = Cursor::new(t0, t0 + TimeDelta::days(30));
        let mut chunks = 0;
        let mut text = String::new();
        while let Some(chunk) = cursor.next_chunk(&store, field.id).unwrap() {
            chunks += 1;
            text.push_str(&chunk);
        }
        assert!(chunks >= 4, "header + three pages, got {chunks}");
        let mut reader = csv::Reader::from_reader(text.as_bytes());
        let thetas: Vec<f64> = reader
            .records()
            .map(|r| r.unwrap())
            .filter(|r| &r[0] == "measurement")
            .map(|r| r[3].parse().unwrap())
            .collect();
        assert_eq!(thetas.len(), n);
        for (i, t) in thetas.iter().enumerate() {
            assert!((t - (0.1 + i as f64 * 1e-6)).abs() < 1e-12, "row {i}");
        }
    }

    #[test]
    fn cells_with_commas_and_quotes_are_quoted() {
        let mut out = String::new();
        row(
            &mut out,
            ["a,b", "say \"hi\"", "", "", "", "", "", "", "", "", "", ""],
        );
        let mut reader = csv::ReaderBuilder::new()
            .has_headers(false)
            .from_reader(out.as_bytes());
        let r = reader.records().next().unwrap().unwrap();
        assert_eq!(&r[0], "a,b");
        assert_eq!(&r[1], "say \"hi\"");
    }
}
