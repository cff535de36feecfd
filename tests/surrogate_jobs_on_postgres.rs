//! The service tests of `tests/surrogate_jobs.rs`, every daemon on PostgreSQL
//! (`common::on_postgres`).
#[path = "surrogate_jobs.rs"]
mod surrogate_jobs;
