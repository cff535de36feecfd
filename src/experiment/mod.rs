//! The paper's experiments: tables, figures and reports.

pub mod plot;
