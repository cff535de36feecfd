//! `rootzone migrate --from … --to …`: every table of one store copied into
//! another, empty one (SQLite → PostgreSQL when a farm outgrows one
//! machine, or back). Rows keep their ids, so field ids in URLs, MQTT
//! topics and webhooks stay valid; tables are copied in pages, parents
//! before children, each page in one transaction.

use super::{Store, StoreError};

/// A column's type, the same on both backends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Kind {
    Int,
    Real,
    Text,
}

/// One value of a copied row.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Cell {
    Null,
    Int(i64),
    Real(f64),
    Text(String),
}

/// A copied table: its columns and the order it is read in (unique, so
/// pages neither repeat nor skip rows).
pub(super) struct Table {
    pub name: &'static str,
    pub columns: &'static [(&'static str, Kind)],
    pub order: &'static str,
}

use Kind::{Int, Real, Text};

/// Every table, parents first.
pub(super) const TABLES: &[Table] = &[
    Table {
        name: "meta",
        columns: &[("key", Text), ("value", Text)],
        order: "key",
    },
    Table {
        name: "fields",
        columns: &[("id", Int), ("created_at", Int), ("spec", Text)],
        order: "id",
    },
    Table {
        name: "measurements",
        columns: &[
            ("field_id", Int),
            ("time", Int),
            ("theta", Real),
            ("sensor", Text),
            ("true_theta", Real),
            ("raw", Real),
        ],
        order: "field_id, time, COALESCE(sensor, '')",
    },
    Table {
        name: "forecasts",
        columns: &[
            ("id", Int),
            ("field_id", Int),
            ("issued_at", Int),
            ("body", Text),
        ],
        order: "id",
    },
    Table {
        name: "setpoints",
        columns: &[
            ("id", Int),
            ("field_id", Int),
            ("time", Int),
            ("body", Text),
        ],
        order: "id",
    },
    Table {
        name: "simulations",
        columns: &[("field_id", Int), ("body", Text)],
        order: "field_id",
    },
    Table {
        name: "estimates",
        columns: &[("field_id", Int), ("body", Text)],
        order: "field_id",
    },
    Table {
        name: "forecast_sources",
        columns: &[("key", Text), ("body", Text)],
        order: "key",
    },
    Table {
        name: "cycle_runs",
        columns: &[("field_id", Int), ("boundary", Int), ("replica", Text)],
        order: "field_id, boundary",
    },
];

/// Rows per page.
const PAGE: usize = 5_000;

/// What a copy moved: rows per table.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CopyReport {
    pub tables: Vec<(&'static str, u64)>,
}

impl std::fmt::Display for CopyReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let parts: Vec<String> = self
            .tables
            .iter()
            .map(|(t, n)| format!("{t} {n}"))
            .collect();
        write!(f, "{}", parts.join(", "))
    }
}

impl Store {
    /// Copies every row of this store into `target`, which must hold no
    /// fields yet (a copy never merges into live data).
    pub fn copy_into(&self, target: &Store) -> Result<CopyReport, StoreError> {
        let existing = target.fields()?.len();
        if existing > 0 {
            return Err(StoreError::Conflict(format!(
                "the target holds {existing} field(s) already; migrate copies into an empty database only"
            )));
        }
        let mut report = CopyReport::default();
        for table in TABLES {
            let mut copied = 0u64;
            loop {
                let rows = self.read_page(table, copied as usize, PAGE)?;
                if rows.is_empty() {
                    break;
                }
                target.write_rows(table, &rows)?;
                copied += rows.len() as u64;
                if rows.len() < PAGE {
                    break;
                }
            }
            report.tables.push((table.name, copied));
        }
        target.after_copy()?;
        Ok(report)
    }

    fn read_page(
        &self,
        table: &'static Table,
        offset: usize,
        limit: usize,
    ) -> Result<Vec<Vec<Cell>>, StoreError> {
        match &self.backend {
            super::Backend::Sqlite(b) => b.read_page(table, offset, limit),
            super::Backend::Postgres(b) => b.read_page(table, offset, limit),
        }
    }

    fn write_rows(&self, table: &'static Table, rows: &[Vec<Cell>]) -> Result<(), StoreError> {
        match &self.backend {
            super::Backend::Sqlite(b) => b.write_rows(table, rows),
            super::Backend::Postgres(b) => b.write_rows(table, rows.to_vec()),
        }
    }

    fn after_copy(&self) -> Result<(), StoreError> {
        match &self.backend {
            super::Backend::Sqlite(_) => Ok(()),
            super::Backend::Postgres(b) => b.reset_sequences(),
        }
    }
}

/// `SELECT <columns> FROM <table> ORDER BY <order>` with a page's bounds in
/// the backend's placeholder style.
pub(super) fn select_sql(table: &Table, limit: &str, offset: &str) -> String {
    let cols: Vec<&str> = table.columns.iter().map(|(c, _)| *c).collect();
    format!(
        "SELECT {} FROM {} ORDER BY {} LIMIT {limit} OFFSET {offset}",
        cols.join(", "),
        table.name,
        table.order
    )
}

/// `INSERT INTO <table> (<columns>) VALUES (<placeholders>)`, placeholders
/// numbered from 1 with `prefix` (`?` or `$`).
pub(super) fn insert_sql(table: &Table, prefix: char) -> String {
    let cols: Vec<&str> = table.columns.iter().map(|(c, _)| *c).collect();
    let marks: Vec<String> = (1..=cols.len()).map(|i| format!("{prefix}{i}")).collect();
    format!(
        "INSERT INTO {} ({}) VALUES ({})",
        table.name,
        cols.join(", "),
        marks.join(", ")
    )
}
