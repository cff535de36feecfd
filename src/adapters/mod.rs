//! Adapters to the outside world the daemon pulls from: forecast providers.

pub mod forecast;
