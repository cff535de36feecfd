//! The service tests of `tests/sensors.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "sensors.rs"]
mod sensors;
