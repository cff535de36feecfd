//! Neural-network surrogates of the soil column (MODEL.md §3).
