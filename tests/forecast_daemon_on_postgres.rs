//! The service tests of `tests/forecast_daemon.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "forecast_daemon.rs"]
mod forecast_daemon;
