//! The service tests of `tests/mqtt.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "mqtt.rs"]
mod mqtt;
