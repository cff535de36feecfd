//! The service tests of `tests/service.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "service.rs"]
mod service;
