//! The service tests of `tests/water.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "water.rs"]
mod water;
