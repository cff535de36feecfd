//! The service tests of `tests/trust.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "trust.rs"]
mod trust;
