//! The contract test of `tests/contract.rs` (schemathesis against
//! `openapi.yaml`), its daemon on PostgreSQL (`common::on_postgres`).
#[path = "contract.rs"]
mod contract;
