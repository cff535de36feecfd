//! Neural-network surrogates of the soil column (MODEL.md §3).

pub mod dataset;
pub mod evaluate;
